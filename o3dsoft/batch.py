"""Many pairs at once: ``o3dsoft register --pairs pairs.txt --out results.csv``.

Every pair of a pairs file is registered in turn, in a pool of worker processes on this machine
(``workers``), or on a Ray cluster (``ray``); each worker loads the network once. One CSV row per
pair, written as each pair ends, so that an interrupted run resumes from its results file and
skips the pairs already there (unless their line names other files now, or they failed). A pair whose worker process dies is retried once, then reported as
failed; a pair whose files cannot be read is reported as failed with the reason. The rows do not
depend on how the pairs were spread over workers.

This module imports neither torch nor Open3D at import time: worker processes set their thread
counts before those start.
"""

from __future__ import annotations

import csv
import math
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

from .errors import InputError, O3dsoftError, UsageError, first_line, release_interrupt, spawn_context

COLUMNS = (
    "line",
    "source",
    "target",
    "ground_truth",
    "init",
    "status",
    "error",
    "T_target_source",
    "fitness",
    "confidence",
    "likely_failed",
    "failure_reason",
    "rotation_error_deg",
    "translation_error",
    "seconds",
)
# The columns of results files written before rows named their ground truth and initial guess.
_EARLIER_COLUMNS = tuple(c for c in COLUMNS if c not in ("ground_truth", "init"))
RETRIES = 1  # a pair whose worker process dies is run this many more times
# A worker process is replaced after this many pairs: KISS-Matcher keeps about 0.2 MB per call on a
# 3DMatch pair that it never gives back (docs/scans.md), 1 GB over 5,000 pairs; a new process costs seconds.
PAIRS_PER_WORKER = 500


@dataclass(frozen=True)
class PairJob:
    """One line of a pairs file: source and target files, the ground truth's file if given
    (T_target_source), the initial guess's file if given (``register(init=...)``), and the line
    number (the pair's key in the results)."""

    line: int
    source: str
    target: str
    transform: Optional[str] = None
    init: Optional[str] = None


def read_pair_jobs(path) -> List[PairJob]:
    """The pairs of a file of lines ``source target [transform] [init=transform]`` (paths relative
    to the file's folder; ``#`` starts a comment; ``init=``: an initial guess). Files are not
    checked here: a pair naming a missing file fails on its own row, and the others run.

    Raises:
        UsageError: no such pairs file.
        InputError: a line with other than 2 or 3 names besides ``init=`` (names the line), or
            no pair at all.
    """
    from .scans import pair_lines

    jobs = []
    for lineno, files, named in pair_lines(path, (2, 3), ("init",)):
        truth, init = files[2] if len(files) == 3 else None, named.get("init")
        jobs.append(PairJob(lineno, str(files[0]), str(files[1]), None if truth is None else str(truth), None if init is None else str(init)))
    return jobs


# --- one pair, in whichever process runs it -------------------------------------------------


def model_for(config):
    """The network of `config` (its weights on its device), loaded once per process."""
    from .coarse import cached_model

    return cached_model(config.weights, config.device)


def run_job(job: PairJob, config) -> dict:
    """Register one pair and return its results row (a dict of :data:`COLUMNS`); an error of the
    input (a missing or unreadable file) is the row's ``error``, never an exception."""
    from . import io
    from .metrics import pair_errors
    from .pipeline import register
    from .preprocess import local_origin

    t0 = time.perf_counter()
    row = _named(job)
    try:
        model = model_for(config)
        source, target = io.read_points(job.source), io.read_points(job.target)
        moved = local_origin(source)  # where a rounded rotation, made exact, still moves the source
        truth = io.read_transform(job.transform, moved) if job.transform else None
        guess = io.read_transform(job.init, moved) if job.init else None
        result = register(source, target, config, model=model, source_name=job.source, target_name=job.target, init=guess)
    except O3dsoftError as e:
        return {**row, "status": "failed", "error": str(e), "seconds": time.perf_counter() - t0}
    row.update(
        status="ok",
        T_target_source=" ".join(f"{v:.17g}" for v in result.transformation.reshape(-1)),  # every bit: georeferenced translations
        fitness=result.fitness,
        confidence=result.confidence,
        likely_failed=result.likely_failed,
        failure_reason=result.failure_reason or "",
        seconds=time.perf_counter() - t0,
    )
    if truth is not None:
        errors = pair_errors(result.transformation, truth, local_origin(target))  # as register --gt: about the target (georeferenced scans)
        row.update(rotation_error_deg=errors.rotation_deg, translation_error=errors.translation)
    return row


def _named(job: PairJob) -> dict:
    """The start of `job`'s row: its line and the files it names ("" where none)."""
    return {"line": job.line, "source": job.source, "target": job.target, "ground_truth": job.transform or "", "init": job.init or ""}


def _worker_start(threads: int) -> None:
    """A pool process's set-up: its share of the CPU's threads, fixed before torch and Open3D
    start their thread pools."""
    os.environ["OMP_NUM_THREADS"] = str(threads)
    import torch

    torch.set_num_threads(threads)


# --- the results file ------------------------------------------------------------------------


def done_lines(results) -> Dict[int, dict]:
    """Rows already in a results file, by line number (pairs a resumed run skips); {} if none.

    Raises:
        InputError: the file exists but is not an o3dsoft results file.
    """
    results = Path(results)
    if not results.is_file() or results.stat().st_size == 0:
        return {}
    with open(results, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or tuple(reader.fieldnames) not in (COLUMNS, _EARLIER_COLUMNS):
            raise InputError(f"{results}: exists and is not an o3dsoft results file (its header differs); choose another --out or remove it")
        rows = {}
        for row in reader:
            if row.get("seconds"):  # a row cut short by a kill has no last field
                rows[int(row["line"])] = row
    return rows


def reusable_rows(jobs: Sequence[PairJob], rows: Dict[int, dict], results=None) -> Dict[int, dict]:
    """The rows of `rows` (:func:`done_lines`) that a resumed run keeps, by the line of `jobs` they
    now belong to: those that ran and name the files a line names now (source, target, ground
    truth, initial guess; a row of a file without the ground_truth and init columns: the same
    source and target), wherever that line has moved in the pairs file. A pair that failed (a
    missing file since put in place), a line edited since, or one whose files changed after the
    CSV `results` was last written (their modification time), runs again."""
    written = _modified(results) if results is not None else None
    free: Dict[tuple, List[dict]] = {}
    for row in rows.values():
        if row["status"] == "ok":
            files = (row["source"], row["target"]) + ((row["ground_truth"], row["init"]) if "ground_truth" in row else ())
            free.setdefault(_files_key(files), []).append(row)
    kept = {}
    for job in jobs:
        named = _named(job)
        files = (job.source, job.target, named["ground_truth"], named["init"])
        matches = free.get(_files_key(files)) or free.get(_files_key(files[:2]))
        if matches and (written is None or all(_modified(f) <= written for f in files if f)):
            kept[job.line] = {**matches.pop(0), **named}
    return kept


def resume_counts(jobs: Sequence[PairJob], rows: Dict[int, dict], results) -> Tuple[int, int, int]:
    """What a resumed run does with the rows of the CSV `results` (:func:`done_lines`): how many
    pairs of `jobs` keep theirs (:func:`reusable_rows`), how many run again though a row names
    their source and target (it failed, or a file changed since), and how many rows name no
    pair of `jobs` and are dropped."""
    kept = len(reusable_rows(jobs, rows, results))
    named = [_files_key((row["source"], row["target"])) for row in rows.values()]  # each file's realpath once
    listed = [_files_key((job.source, job.target)) for job in jobs]
    in_rows, in_jobs = set(named), set(listed)
    again = sum(key in in_rows for key in listed) - kept
    dropped = sum(key not in in_jobs for key in named)
    return kept, again, dropped


def _files_key(names: Sequence[str]) -> tuple:
    """The files of a results row or a pairs line ("" for none), as a key that names each file
    one way (relative to the working folder; the pairs file may have been given by another path)."""
    return tuple(os.path.realpath(n) if n else "" for n in names)


def _modified(path) -> float:
    """The modification time of the file at `path`; infinite where it cannot be read."""
    try:
        return os.stat(path).st_mtime
    except OSError:
        return math.inf


def check_results_belong(jobs: Sequence[PairJob], rows: Dict[int, dict], results) -> None:
    """Refuse to resume a results file none of whose rows (:func:`done_lines`) names the source
    and target of a line of `jobs`: the results of another pairs file, which the run would
    replace.

    Raises:
        InputError: naming the file and how many rows it holds.
    """
    pairs = {_files_key((job.source, job.target)) for job in jobs}
    if rows and not any(_files_key((row["source"], row["target"])) in pairs for row in rows.values()):
        raise InputError(
            f"{results}: holds the results of other pairs (none of its {len(rows)} rows names the source and target of a line here); "
            "choose another --out, or remove it to start again"
        )


class ResultsFile:
    """Appends rows to the CSV as pairs end (each row one write, flushed). It starts by rewriting
    the file with the rows kept, so that a row cut short by a kill is not continued by the next
    one, and ends by rewriting it in the pairs file's order."""

    def __init__(self, path, rows: Dict[int, dict]) -> None:
        self.path = Path(path)
        self.rows = dict(rows)
        self._write_all(sorted(self.rows))
        self._file = open(self.path, "a", newline="")
        self._writer = csv.DictWriter(self._file, COLUMNS)

    def add(self, row: dict) -> None:
        self.rows[int(row["line"])] = row
        self._writer.writerow(row)
        self._file.flush()

    def close(self, order: Sequence[int]) -> None:
        """Rewrite the file with the rows in `order`, then close it."""
        self._file.close()
        self._write_all(order)

    def _write_all(self, order: Sequence[int]) -> None:
        """The header and the rows of `order` that are done, written atomically."""
        from .io import atomic_output

        with atomic_output(self.path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, COLUMNS)
            writer.writeheader()
            for line in order:
                if line in self.rows:
                    writer.writerow(self.rows[line])


# --- running many ----------------------------------------------------------------------------


def run_jobs(
    jobs: Sequence[PairJob],
    config,
    results,
    workers: int = 1,
    ray: Optional[str] = None,
    progress: Optional[Callable[[dict], None]] = None,
    task: Optional[Callable[[PairJob, object], dict]] = None,
    done: Optional[Dict[int, dict]] = None,
) -> List[dict]:
    """Register every pair of `jobs` not already in the CSV `results`; append each row as it ends.

    Args:
        jobs: the pairs (:func:`read_pair_jobs`).
        config: RegisterConfig of every pair.
        results: the CSV file (created, or resumed: the rows there that :func:`reusable_rows` keeps
            are skipped).
        workers: processes on this machine (1: this process), or Ray actors with `ray`.
        ray: None (no Ray), "local" (start Ray on this machine), "auto" (the cluster ``ray start``
            set up) or a head's address.
        progress: called with each row as it ends.
        task: what runs each pair, :func:`run_job` (a module-level function, so that worker
            processes can import it; tests pass one that crashes).
        done: the rows `results` holds, as :func:`done_lines` read them (read here when None).
    Returns:
        All rows, in the order of `jobs`.
    """
    task = task or run_job
    if len({j.line for j in jobs}) != len(jobs):
        raise InputError("two pairs share a line number")
    done = done_lines(results) if done is None else done
    check_results_belong(jobs, done, results)
    rows = reusable_rows(jobs, done, results)
    todo = [j for j in jobs if j.line not in rows]
    ray_module = _ray_connect(ray) if ray is not None else None  # before any file is written
    out = ResultsFile(results, rows)
    try:
        if ray_module is not None:
            runner: Iterator[dict] = _run_ray(ray_module, todo, config, workers, task)
        elif workers > 1:
            runner = _run_pool(todo, config, workers, task)
        else:
            runner = (task(j, config) for j in todo)
        for row in runner:
            out.add(row)
            if progress is not None:
                progress(row)
    finally:
        out.close([j.line for j in jobs])
        if ray_module is not None and ray == "local":
            ray_module.shutdown()
    return [out.rows[j.line] for j in jobs if j.line in out.rows]


def _crashed(job: PairJob, why: str) -> dict:
    """The row of a pair whose process died each time it ran (`why`, in words)."""
    return {**_named(job), "status": "failed", "error": why, "seconds": 0.0}


def _run_pool(jobs: Sequence[PairJob], config, workers: int, task) -> Iterator[dict]:
    """Rows from a pool of `workers` processes, which runs at most `workers` pairs at a time.
    When a process dies the pool breaks, and it is not known which of the pairs it was running
    killed it: each of those is run again in a process of its own, where a death is its own
    (retried once, then reported as failed); the other pairs go on in a new pool."""
    from concurrent.futures import FIRST_COMPLETED, wait
    from concurrent.futures.process import BrokenProcessPool

    queue = list(jobs)
    while queue:
        suspects: List[PairJob] = []
        with _process_pool(workers) as pool:
            running: Dict[object, PairJob] = {}
            while (queue or running) and not suspects:
                while queue and len(running) < workers:
                    job = queue.pop(0)
                    running[pool.submit(task, job, config)] = job
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    try:
                        row = future.result()
                    except BrokenProcessPool:
                        suspects = sorted(running.values(), key=lambda j: j.line)
                        break
                    running.pop(future)
                    yield row
        for job in suspects:
            yield _run_alone(job, config, task)


def _run_alone(job: PairJob, config, task) -> dict:
    """Run one pair in a process of its own, again after a death (:data:`RETRIES` times)."""
    from concurrent.futures.process import BrokenProcessPool

    for _ in range(1 + RETRIES):
        with _process_pool(1) as alone:
            try:
                return alone.submit(task, job, config).result()
            except BrokenProcessPool:
                continue
    return _crashed(job, "its worker process died twice")


def _process_pool(workers: int):
    """A pool of `workers` fresh processes, each with its share of the CPU's threads."""
    from concurrent.futures import ProcessPoolExecutor

    threads = max(1, (os.cpu_count() or 1) // workers)
    # spawn: no fork of a process whose threads hold locks
    return ProcessPoolExecutor(workers, mp_context=spawn_context(), initializer=_pool_worker_start, initargs=(threads,), max_tasks_per_child=PAIRS_PER_WORKER)


def _pool_worker_start(threads: int) -> None:
    """A pool process's set-up (:func:`_worker_start`); from then on Ctrl-C ends it quietly, and
    the parent reports the interrupt."""
    _worker_start(threads)
    release_interrupt()


def _run_ray(ray, jobs: Sequence[PairJob], config, workers: int, task) -> Iterator[dict]:
    """Rows from `workers` Ray actors, each holding the network; a pair whose actor dies is
    retried once on a new actor."""
    Worker = ray.remote(num_cpus=1)(_RayWorker)
    actors = [Worker.remote(workers) for _ in range(workers)]
    tries = {j.line: 0 for j in jobs}
    queue = list(jobs)
    running: Dict[object, Tuple[PairJob, int]] = {}
    while queue or running:
        free = [k for k in range(len(actors)) if k not in {a for _, a in running.values()}]
        while queue and free:
            job, k = queue.pop(0), free.pop(0)
            running[actors[k].run.remote(job, config, task)] = (job, k)
        finished, _ = ray.wait(list(running), num_returns=1)
        for ref in finished:
            job, k = running.pop(ref)
            try:
                yield ray.get(ref)
            except ray.exceptions.RayActorError:
                actors[k] = Worker.remote(workers)
                tries[job.line] += 1
                if tries[job.line] > RETRIES:
                    yield _crashed(job, "its Ray actor died twice")
                else:
                    queue.insert(0, job)


class _RayWorker:
    """A Ray actor registering pairs with one loaded network (see :func:`run_job`)."""

    def __init__(self, workers: int) -> None:
        _worker_start(max(1, (os.cpu_count() or 1) // workers))  # this node's threads, shared as on one machine

    def run(self, job: PairJob, config, task) -> dict:
        return task(job, config)


def _ray_connect(address: str):
    """The ray module, connected to (for "local": started on this machine) a Ray cluster.

    Raises:
        UsageError: Ray is not installed.
        InputError: the cluster cannot be reached (in one line).
    """
    try:
        import ray
    except ImportError:
        raise UsageError("--ray needs Ray: pip install 'o3dsoft[ray]'") from None
    if ray.is_initialized():
        return ray
    if address not in ("local", "auto"):
        _check_reachable(address)
    from .io import quiet_c_output

    kwargs = dict(include_dashboard=False, log_to_driver=False, logging_level="ERROR", configure_logging=False)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with quiet_c_output("stdout"), quiet_c_output("stderr"):  # Ray's own notices and retry logs; the outcome is reported here
            ray.init(**kwargs) if address == "local" else ray.init(address=address, **kwargs)
    except Exception as e:  # ConnectionError, ValueError, Ray's own: all mean "cannot reach it"
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({first_line(e)})") from None
    finally:
        if threading.current_thread() is threading.main_thread():  # Ray installs its own; Ctrl-C and kill stay o3dsoft's
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
    return ray


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """InputError unless a TCP connection to ``[ray://]HOST:PORT`` opens within `timeout` seconds
    (Ray itself retries an address that refuses for a long time)."""
    import socket

    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"--ray {address}: expected local, auto or HOST:PORT (ray://HOST:PORT for Ray Client)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({e.strerror or e})") from None
