"""register --pairs: many pairs, in worker processes or on a local Ray, resumable."""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import List

import numpy as np
import pytest
from click.testing import CliRunner

from o3dsoft.batch import COLUMNS, PairJob, done_lines, read_pair_jobs, run_job, run_jobs
from o3dsoft.cli.main import main
from o3dsoft.config import RegisterConfig
from o3dsoft.errors import InputError, UsageError
from o3dsoft.io import write_transform

from .conftest import apply, blob, georeferenced_bunny, random_transform

CONFIG = RegisterConfig()


def crash_once_or_always(job: PairJob, config) -> dict:
    """The pair task of a worker that dies: on a source named *crash-once* the first time only,
    on *crash-always* every time."""
    name = Path(job.source).name
    marker = Path(job.source + ".crashed")
    if "crash-always" in name or ("crash-once" in name and not marker.exists()):
        marker.touch()
        os._exit(1)
    return run_job(job, config)


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory):
    """Four pairs of small blobs with their ground truth, and a fifth naming a missing file."""
    folder = tmp_path_factory.mktemp("pairs")
    rng = np.random.default_rng(5)
    lines = []
    for k in range(4):
        shape = blob(rng, 400)
        T = random_transform(rng, 30.0, 0.3)
        np.save(folder / f"s{k}.npy", shape)
        np.save(folder / f"t{k}.npy", apply(T, shape)[rng.permutation(400)])
        write_transform(folder / f"gt{k}.txt", T)
        lines.append(f"s{k}.npy t{k}.npy gt{k}.txt")
    lines.insert(2, "missing.npy t0.npy  # a file that is not there")
    (folder / "pairs.txt").write_text("# source target truth\n" + "\n".join(lines) + "\n")
    return folder / "pairs.txt"


def _rows(path):
    with open(path, newline="") as f:
        return {int(r["line"]): r for r in csv.DictReader(f)}


def _same_results(a, b):
    assert a.keys() == b.keys()
    for line in a:
        for column in ("status", "error", "likely_failed", "failure_reason"):
            assert a[line][column] == b[line][column], (line, column)
        if a[line]["status"] == "ok":
            assert np.allclose(np.array(a[line]["T_target_source"].split(), float), np.array(b[line]["T_target_source"].split(), float), atol=1e-9)
            assert float(a[line]["confidence"]) == pytest.approx(float(b[line]["confidence"]), abs=1e-9)


def test_pairs_file_lines(tmp_path, pairs_file):
    jobs = read_pair_jobs(pairs_file)
    assert [j.line for j in jobs] == [2, 3, 4, 5, 6]
    assert jobs[0].source == str(pairs_file.parent / "s0.npy") and jobs[0].transform == str(pairs_file.parent / "gt0.txt")
    assert jobs[2].transform is None
    bad = tmp_path / "bad.txt"
    bad.write_text("a.ply b.ply\na.ply\n")
    with pytest.raises(InputError, match="bad.txt, line 2: expected 'source target \\[transform\\] \\[init=transform\\]'"):
        read_pair_jobs(bad)
    with pytest.raises(UsageError, match="no such pairs file"):
        read_pair_jobs(tmp_path / "none.txt")
    spaced = tmp_path / "spaced.txt"
    spaced.write_text("\"scan 1.ply\" 'scan 2.ply'  # quoted: names with spaces\nC:\\scans\\a.ply b.ply\nscan 1.ply scan 2.ply\n")
    with pytest.raises(InputError, match="spaced.txt, line 3: expected .*, got 4 field\\(s\\) \\(a file name with spaces goes in quotes\\)"):
        read_pair_jobs(spaced)
    spaced.write_text(spaced.read_text().splitlines()[0] + "\n" + spaced.read_text().splitlines()[1] + "\n")
    first, second = read_pair_jobs(spaced)
    assert (first.source, first.target) == (str(tmp_path / "scan 1.ply"), str(tmp_path / "scan 2.ply"))
    assert second.source == str(tmp_path / "C:\\scans\\a.ply")  # an unquoted line keeps its backslashes
    spaced.write_text('"scan 1.ply scan 2.ply\n')
    with pytest.raises(InputError, match="spaced.txt, line 1: No closing quotation"):
        read_pair_jobs(spaced)
    guessed = tmp_path / "guessed.txt"
    guessed.write_text("a.ply b.ply gt.txt init=guess.txt\na.ply b.ply init=guess.txt  # a guess, no ground truth\nc.ply d.ply\n")
    with_truth, without, plain = read_pair_jobs(guessed)
    assert (with_truth.transform, with_truth.init) == (str(tmp_path / "gt.txt"), str(tmp_path / "guess.txt"))
    assert (without.transform, without.init) == (None, str(tmp_path / "guess.txt")) and plain.init is None
    guessed.write_text("a.ply init init=guess.txt\n")  # a file named "init" is a file
    (named,) = read_pair_jobs(guessed)
    assert (named.target, named.init) == (str(tmp_path / "init"), str(tmp_path / "guess.txt"))
    guessed.write_text("a.ply init=guess.txt\n")
    with pytest.raises(InputError, match=r"line 1: expected 'source target \[transform\] \[init=transform\]', got 1 field"):
        read_pair_jobs(guessed)


def test_sequential_rows_report_the_missing_file_and_run_the_rest(tmp_path, pairs_file):
    rows = run_jobs(read_pair_jobs(pairs_file), CONFIG, tmp_path / "r.csv")
    assert [r["status"] for r in rows] == ["ok", "ok", "failed", "ok", "ok"]
    assert "missing.npy: no such file" in rows[2]["error"]
    for r in rows:
        if r["status"] == "ok":
            assert r["rotation_error_deg"] < 1.0 and not r["likely_failed"]
    on_disk = _rows(tmp_path / "r.csv")
    assert list(on_disk) == [2, 3, 4, 5, 6]  # the pairs file's order
    # The file's transform is the library's to the bit (georeferenced translations need every digit).
    job = read_pair_jobs(pairs_file)[0]
    from o3dsoft import read_points, register

    alone = register(read_points(job.source), read_points(job.target), CONFIG, source_name=job.source, target_name=job.target)
    assert np.array_equal(np.array(on_disk[2]["T_target_source"].split(), float).reshape(4, 4), alone.transformation)
    assert list(csv.reader(open(tmp_path / "r.csv")))[0] == list(COLUMNS)


def test_two_workers_give_the_sequential_results(tmp_path, pairs_file):
    jobs = read_pair_jobs(pairs_file)
    run_jobs(jobs, CONFIG, tmp_path / "one.csv")
    run_jobs(jobs, CONFIG, tmp_path / "two.csv", workers=2)
    _same_results(_rows(tmp_path / "one.csv"), _rows(tmp_path / "two.csv"))


def test_an_interrupted_run_resumes_from_its_results(tmp_path, pairs_file):
    jobs = read_pair_jobs(pairs_file)
    results = tmp_path / "r.csv"
    run_jobs(jobs[:2], CONFIG, results)
    with open(results, "a") as f:
        f.write("6,s,t,ok,,1 0")  # a row cut short by a kill: run again
    ran = []
    run_jobs(jobs, CONFIG, results, progress=ran.append)
    assert [r["line"] for r in ran] == [4, 5, 6]
    assert list(_rows(results)) == [2, 3, 4, 5, 6]
    # Mid-run, as a kill would leave it, the file holds whole rows: the first new one does not
    # continue the row cut short.
    results.unlink()
    run_jobs(jobs[:2], CONFIG, results)
    with open(results, "a") as f:
        f.write("6,s,t,ok,,1 0")
    seen = []
    run_jobs(jobs, CONFIG, results, progress=lambda row: seen.append(set(done_lines(results))))
    assert seen[0] == {2, 3, 4}
    assert done_lines(results).keys() == {2, 3, 4, 5, 6}


def test_a_resumed_run_runs_edited_lines_and_failed_pairs_again(tmp_path, pairs_file):
    data = pairs_file.parent
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{data}/s0.npy {data}/t0.npy {data}/gt0.txt\n{data}/s1.npy {data}/t1.npy\nlate.npy {data}/t2.npy\n")
    results = tmp_path / "r.csv"
    assert [r["status"] for r in run_jobs(read_pair_jobs(pairs), CONFIG, results)] == ["ok", "ok", "failed"]
    (tmp_path / "late.npy").write_bytes((data / "s2.npy").read_bytes())  # the missing file, put in place
    pairs.write_text(f"{data}/s0.npy {data}/t0.npy {data}/gt0.txt\n{data}/s1.npy {data}/t1.npy {data}/gt1.txt\nlate.npy {data}/t2.npy\n")
    ran = []
    rows = run_jobs(read_pair_jobs(pairs), CONFIG, results, progress=ran.append)
    assert [r["line"] for r in ran] == [2, 3]  # line 2 now names a ground truth; line 3 could not run
    assert [r["status"] for r in rows] == ["ok", "ok", "ok"] and float(rows[1]["rotation_error_deg"]) < 1.0
    assert _rows(results)[2]["ground_truth"] == f"{data}/gt1.txt"


def test_a_resumed_run_finds_its_rows_where_their_lines_moved(tmp_path, pairs_file):
    """Rows belong to the files a line names, not to its number: with a comment and a new pair
    put in above them, the rows are kept under their new lines and only the new pair runs."""
    data = pairs_file.parent
    pairs = tmp_path / "pairs.txt"
    first = [f"{data}/s{k}.npy {data}/t{k}.npy {data}/gt{k}.txt" for k in (0, 1)]
    pairs.write_text("\n".join(first) + "\n")
    results = tmp_path / "r.csv"
    before = run_jobs(read_pair_jobs(pairs), CONFIG, results)
    pairs.write_text("\n".join(["# a comment", first[0], f"{data}/s2.npy {data}/t2.npy", first[1]]) + "\n")
    ran: List[dict] = []
    rows = run_jobs(read_pair_jobs(pairs), CONFIG, results, progress=ran.append)
    assert [r["line"] for r in ran] == [3]
    assert [int(r["line"]) for r in rows] == [2, 3, 4]
    assert [(r["T_target_source"], r["seconds"]) for r in (rows[0], rows[2])] == [(r["T_target_source"], str(r["seconds"])) for r in before]
    assert list(_rows(results)) == [2, 3, 4]
    r = CliRunner().invoke(main, ["register", "--pairs", str(pairs), "--out", str(results), "--no-progress"])
    assert r.exit_code == 0 and "Resuming: 3 of 3 pairs already in" in r.stderr and "run again" not in r.stderr and "dropped" not in r.stderr


def test_a_resumed_run_runs_a_pair_whose_file_changed_since(tmp_path, pairs_file):
    """A ground truth edited under its name after the results were written: its pair runs again,
    measured against the truth as it is now."""
    data = pairs_file.parent
    gt = tmp_path / "gt.txt"
    gt.write_bytes((data / "gt0.txt").read_bytes())
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{data}/s0.npy {data}/t0.npy {gt}\n{data}/s1.npy {data}/t1.npy\n")
    results = tmp_path / "r.csv"
    first = run_jobs(read_pair_jobs(pairs), CONFIG, results)
    assert float(first[0]["translation_error"]) < 0.05
    T = np.loadtxt(gt)
    T[0, 3] += 1.0
    np.savetxt(gt, T)
    edited = results.stat().st_mtime + 1.0  # whatever the file system's clock resolution
    os.utime(gt, (edited, edited))
    r = CliRunner().invoke(main, ["register", "--pairs", str(pairs), "--out", str(results), "--no-progress"])
    assert r.exit_code == 0 and "Resuming: 1 of 2 pairs already in" in r.stderr and "1 run again" in r.stderr
    rows = _rows(results)
    assert float(rows[1]["translation_error"]) > 0.9 and rows[2]["seconds"] == str(first[1]["seconds"])


def test_a_resumed_run_knows_its_rows_by_another_path_and_in_an_earlier_layout(tmp_path, pairs_file, monkeypatch):
    data, sub = pairs_file.parent, tmp_path / "sub"
    sub.mkdir()
    for name in ("s0.npy", "t0.npy", "gt0.txt"):
        (sub / name).write_bytes((data / name).read_bytes())
    (sub / "pairs.txt").write_text("s0.npy t0.npy gt0.txt\n")
    results = tmp_path / "r.csv"
    run_jobs(read_pair_jobs(sub / "pairs.txt"), CONFIG, results)
    monkeypatch.chdir(sub)  # the same pairs file, named from its folder
    ran = []
    run_jobs(read_pair_jobs("pairs.txt"), CONFIG, results, progress=ran.append)
    assert ran == []
    # A file written before rows named their ground truth and initial guess.
    with open(results, newline="") as f:
        rows = list(csv.DictReader(f))
    earlier = [c for c in COLUMNS if c not in ("ground_truth", "init")]
    with open(results, "w", newline="") as f:
        writer = csv.DictWriter(f, earlier, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    rows = run_jobs(read_pair_jobs("pairs.txt"), CONFIG, results, progress=ran.append)
    assert ran == [] and rows[0]["ground_truth"].endswith("gt0.txt")
    assert list(csv.reader(open(results)))[0] == list(COLUMNS)  # rewritten in today's layout


def test_a_results_file_of_another_kind_is_not_overwritten(tmp_path, pairs_file):
    other = tmp_path / "notes.csv"
    other.write_text("name,value\na,1\n")
    with pytest.raises(InputError, match="not an o3dsoft results file"):
        run_jobs(read_pair_jobs(pairs_file), CONFIG, other)
    assert other.read_text() == "name,value\na,1\n"


def test_the_results_of_another_pairs_file_are_not_replaced(tmp_path, pairs_file):
    data = pairs_file.parent
    results = tmp_path / "r.csv"
    (tmp_path / "one.txt").write_text(f"{data}/s0.npy {data}/t0.npy\n{data}/s1.npy {data}/t1.npy\n")
    (tmp_path / "other.txt").write_text(f"{data}/s2.npy {data}/t2.npy\n{data}/s3.npy {data}/t3.npy\n")
    run_jobs(read_pair_jobs(tmp_path / "one.txt"), CONFIG, results)
    before = results.read_text()
    with pytest.raises(InputError, match="r.csv: holds the results of other pairs \\(none of its 2 rows names the source and target of a line here\\)"):
        run_jobs(read_pair_jobs(tmp_path / "other.txt"), CONFIG, results)
    assert results.read_text() == before
    # The same file with a line left out: the rows of the lines it has are kept, the others dropped, and said so.
    (tmp_path / "one.txt").write_text(f"{data}/s0.npy {data}/t0.npy\n")
    r = CliRunner().invoke(main, ["register", "--pairs", str(tmp_path / "one.txt"), "--out", str(results), "--no-progress"])
    assert r.exit_code == 0 and "Resuming: 1 of 1 pairs already in" in r.stderr and "1 rows of pairs the pairs file no longer lists are dropped" in r.stderr
    assert list(_rows(results)) == [1]


@pytest.mark.parametrize("ray, died", [(None, "its worker process died twice"), ("local", "its Ray actor died twice")], ids=["pool", "ray"])
def test_a_crashed_worker_is_retried_once_then_reported(tmp_path, pairs_file, ray, died):
    if ray:
        pytest.importorskip("ray")
    folder = tmp_path / "crash"
    folder.mkdir()
    for name in ("crash-once.npy", "crash-always.npy"):
        (folder / name).write_bytes((pairs_file.parent / "s0.npy").read_bytes())
    jobs = [
        PairJob(1, str(folder / "crash-once.npy"), str(pairs_file.parent / "t0.npy")),
        PairJob(2, str(folder / "crash-always.npy"), str(pairs_file.parent / "t0.npy")),
    ]
    jobs += [PairJob(3, str(pairs_file.parent / "s1.npy"), str(pairs_file.parent / "t1.npy"))]
    rows = run_jobs(jobs, CONFIG, tmp_path / "r.csv", workers=2, ray=ray, task=crash_once_or_always)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert rows[1]["error"] == died


def test_cli_pairs_with_workers_and_resume(tmp_path, pairs_file):
    runner = CliRunner()
    out = tmp_path / "results.csv"
    first = runner.invoke(main, ["register", "--pairs", str(pairs_file), "--out", str(out), "--workers", "2", "--no-progress"])
    assert first.exit_code == 3, first.output  # one pair could not run
    assert "5 pairs: 4 trusted, 0 flagged likely failed, 1 could not run" in first.output
    assert "line 4: " in first.output and "missing.npy" in first.output
    seconds = sorted(float(r["seconds"]) for r in _rows(out).values() if r["status"] == "ok")
    assert f"median {(seconds[1] + seconds[2]) / 2:.2f} s per pair" in first.output  # of 4 pairs: the mean of the middle two
    again = runner.invoke(main, ["register", "--pairs", str(pairs_file), "--out", str(out), "--no-progress"])
    assert "Resuming: 4 of 5 pairs already in" in again.output and "1 run again" in again.output  # the missing file's pair


@pytest.mark.parametrize(
    "args, message",
    [
        (["--pairs", "P", "--out", "r.ply"], "--pairs writes a CSV file; give --out RESULTS.csv"),
        (["--pairs", "P"], "--pairs needs --out RESULTS.csv"),
        (["--pairs", "D", "--out", "r.csv"], "is a folder; expected a pairs file"),
        (["--pairs", "P", "a.ply", "--out", "r.csv"], "SOURCE belong(s) to a single pair"),
        (["a.ply", "b.ply", "--workers", "2"], "--workers and --ray go with --pairs"),
        ([], "give SOURCE and TARGET, or --pairs FILE"),
    ],
)
def test_cli_pairs_usage_errors(tmp_path, pairs_file, args, message):
    args = [str(pairs_file) if a == "P" else str(tmp_path) if a == "D" else str(tmp_path / a) if a.endswith((".ply", ".csv")) else a for a in args]
    result = CliRunner().invoke(main, ["register", *args])
    assert result.exit_code == 2
    assert message in result.output


def test_ray_on_this_machine_gives_the_workers_results(tmp_path, pairs_file):
    pytest.importorskip("ray")
    jobs = read_pair_jobs(pairs_file)
    run_jobs(jobs, CONFIG, tmp_path / "pool.csv", workers=2)
    run_jobs(jobs, CONFIG, tmp_path / "ray.csv", workers=2, ray="local")
    _same_results(_rows(tmp_path / "pool.csv"), _rows(tmp_path / "ray.csv"))


def test_an_unreachable_ray_cluster_is_one_line_and_writes_nothing(tmp_path, pairs_file):
    pytest.importorskip("ray")
    out = tmp_path / "r.csv"
    result = CliRunner().invoke(main, ["register", "--pairs", str(pairs_file), "--out", str(out), "--ray", "127.0.0.1:1", "--no-progress"])
    assert result.exit_code == 1
    assert result.output.strip().splitlines()[-1].startswith("Error: --ray 127.0.0.1:1: cannot connect to a Ray cluster")
    assert not out.exists()


def test_a_pair_registers_from_its_initial_guess(tmp_path, pairs_file, monkeypatch):
    from o3dsoft import pipeline
    from o3dsoft.io import read_transform
    from o3dsoft.transforms import euler_to_matrix, rigid

    job = read_pair_jobs(pairs_file)[0]
    T = read_transform(job.transform)
    guess = rigid(euler_to_matrix([4.0, -3.0, 2.0]) @ T[:3, :3], T[:3, 3] + 0.02)
    write_transform(tmp_path / "guess.txt", guess)
    register, given = pipeline.register, []
    monkeypatch.setattr(pipeline, "register", lambda *a, **k: given.append(k["init"]) or register(*a, **k))
    row = run_job(PairJob(job.line, job.source, job.target, job.transform, str(tmp_path / "guess.txt")), CONFIG)
    assert row["status"] == "ok" and row["rotation_error_deg"] < 1.0 and not row["likely_failed"]
    assert np.allclose(given[0], guess)
    (tmp_path / "skew.txt").write_text("1 1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    row = run_job(PairJob(job.line, job.source, job.target, job.transform, str(tmp_path / "skew.txt")), CONFIG)
    assert row["status"] == "failed" and "skew.txt: not a rigid transform" in row["error"]


def test_a_row_measures_georeferenced_errors_as_register_does(tmp_path):
    """Clouds 4e6 units from their frame's origin, a truth rounded as published truths are: the
    row's errors are taken about the target, the truth made exact about the source."""
    source, target, truth = georeferenced_bunny(tmp_path)
    row = run_job(PairJob(1, str(source), str(target), str(truth)), CONFIG)
    assert row["status"] == "ok" and not row["likely_failed"]
    assert row["rotation_error_deg"] < 1.0 and row["translation_error"] < 0.002  # the bunny is 0.2 units across


def sigint_blocked(job=None, config=None) -> bool:
    import signal

    return signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])


@pytest.mark.skipif(not hasattr(__import__("signal"), "pthread_sigmask"), reason="POSIX signal masks")
def test_pool_workers_start_with_ctrl_c_held_until_they_are_set_up():
    """A terminal's Ctrl-C reaches every process of the command: a worker still importing torch
    must not print a traceback of its own, but once set up it must still stop on it."""
    from concurrent.futures import ProcessPoolExecutor

    from o3dsoft.batch import _process_pool
    from o3dsoft.errors import spawn_context

    with ProcessPoolExecutor(1, mp_context=spawn_context()) as pool:
        assert pool.submit(sigint_blocked).result(timeout=120)  # as the worker starts
    assert not sigint_blocked()  # the parent's own mask is as it was
    with _process_pool(1) as pool:
        assert not pool.submit(sigint_blocked).result(timeout=120)  # released by the worker's set-up


def spawned_workers(pid: int) -> List[str]:
    """The process ids of `pid`'s children that multiprocessing spawned (Linux)."""
    found = []
    for child in Path(f"/proc/{pid}/task/{pid}/children").read_text().split():
        try:
            if "spawn_main" in Path(f"/proc/{child}/cmdline").read_text():
                found.append(child)
        except OSError:  # it ended meanwhile
            pass
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads the process tree from Linux's /proc")
def test_ctrl_c_while_the_workers_start_is_one_line(tmp_path, pairs_file):
    """The terminal's Ctrl-C, sent to the whole process group while both workers import their
    modules: the command says where the results are and "Interrupted.", no traceback, and exits 130."""
    import signal
    import subprocess
    import sys
    import time

    command = [sys.executable, "-m", "o3dsoft.cli.main", "register", "--pairs", str(pairs_file), "--out", str(tmp_path / "r.csv"), "--workers", "2"]
    run = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and run.poll() is None and len(spawned_workers(run.pid)) < 2:
        time.sleep(0.02)
    assert run.poll() is None, "the command ended before its workers started"
    time.sleep(0.5)  # the workers are importing torch and Open3D
    os.killpg(run.pid, signal.SIGINT)
    out, err = run.communicate(timeout=120)
    assert run.returncode == 130, err
    assert err.strip().splitlines() == [f"Stopped: the pairs done so far are in {tmp_path / 'r.csv'}; the same command goes on from there.", "Interrupted."], (
        err
    )


def worker_pid(job: PairJob, config) -> dict:
    return {"line": job.line, "pid": os.getpid()}


def test_a_worker_process_is_replaced_after_its_share_of_pairs(monkeypatch):
    """KISS-Matcher keeps memory it never gives back: a long run replaces its workers."""
    import o3dsoft.batch as batch

    monkeypatch.setattr(batch, "PAIRS_PER_WORKER", 2)
    jobs = [PairJob(line, f"s{line}.ply", f"t{line}.ply") for line in range(1, 6)]
    rows = list(batch._run_pool(jobs, CONFIG, 1, worker_pid))
    assert sorted(r["line"] for r in rows) == [1, 2, 3, 4, 5]
    assert len({r["pid"] for r in rows}) == 3  # 2 + 2 + 1 pairs
