"""Speed and memory of the network: fast exact layers vs the paper's literal conv2d layers.

    python -m benchmarks.bench_speed [--data ../shared/data/modelnet40_ply_hdf5_1024] [--steps 5]
        [--literal-steps 2] [--inference-runs 30] [--weights weights/o3dsoft_default.pt]

Measures, in one run on the same batches (protocol `paper`, batch 10, N = 1024, K = 32):
- training steps per second (forward + backward + Adam) of the fast form (shared encoder, and
  separate encoders) and of the literal form, medians over the steps after one warm-up step, and
  the literal / fast ratio;
- peak resident memory of training with each form (a fresh process each, one or two steps);
- the coarse stage on one 1024-point pair through the TorchScript file: median latency of one
  network pass, of two, and of the search's batch of 24 rotation hypotheses.
Times are wall-clock on whatever machine runs it; compare ratios, not absolute values, across runs.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "modelnet40_ply_hdf5_1024"


def _batches(data: str, steps: int, batch_size: int):
    from o3dsoft.data import get_protocol, load_pairs
    from o3dsoft.train import normalised_batch

    pairs = load_pairs(data, "train", get_protocol("paper"))
    return [normalised_batch([pairs[i] for i in range(s * batch_size, (s + 1) * batch_size)]) for s in range(steps)]


def _step_times(net, batches) -> list:
    from o3dsoft.model import registration_loss

    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    times = []
    for src, tgt, R_gt, t_gt in batches:
        t0 = time.perf_counter()
        R, t, _ = net(src, tgt)
        loss = registration_loss(R, t, R_gt, t_gt)
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    return times[1:] if len(times) > 1 else times  # first step warms up allocators


def train_speed(data: str, steps: int, literal_steps: int, batch_size: int = 10) -> dict:
    from o3dsoft.model import NetConfig, SoftAlignNet

    batches = _batches(data, max(steps, literal_steps) + 1, batch_size)
    fast_times = _step_times(_network(literal=False), batches[: steps + 1])
    torch.manual_seed(0)
    separate_times = _step_times(SoftAlignNet(NetConfig(shared_encoder=False)), batches[: steps + 1])
    literal_times = _step_times(_network(literal=True), batches[: literal_steps + 1])
    f, l = statistics.median(fast_times), statistics.median(literal_times)
    return {
        "batch_size": batch_size,
        "fast_step_s_median": f,
        "fast_separate_encoders_step_s_median": statistics.median(separate_times),
        "literal_step_s_median": l,
        "fast_pairs_per_s": batch_size / f,
        "literal_pairs_per_s": batch_size / l,
        "speedup": l / f,
        "fast_steps_timed": len(fast_times),
        "literal_steps_timed": len(literal_times),
    }


def peak_rss_gb() -> float:
    """This process's peak resident memory in GB (VmHWM; ru_maxrss would carry a parent's peak over exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024**2  # kB -> GB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def peak_memory(data: str, steps: int, literal: bool) -> float:
    """Peak RSS (GB) of a fresh process that runs training steps of one form only."""
    code = (
        "import sys; sys.path.insert(0, %r); "
        "from benchmarks.bench_speed import _batches, _step_times, _network, peak_rss_gb; "
        "_step_times(_network(%r), _batches(%r, %d, 10)); "
        "print(peak_rss_gb())"
    ) % (str(REPO), literal, data, steps)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    return float(out.stdout.strip().splitlines()[-1])


def _network(literal: bool):
    from o3dsoft.model import LiteralEncoder, NetConfig, SoftAlignNet

    torch.manual_seed(0)
    net = SoftAlignNet(NetConfig())
    if literal:
        net.encoder_p = net.encoder_q = LiteralEncoder(NetConfig().channels)
    return net


def inference_latency(weights: str | None, runs: int, data: str) -> dict:
    """The coarse stage on one 1024-point `paper` test pair: one network pass (the default), two
    passes, and the search's batch of 24 rotation hypotheses (on its smaller samples)."""
    from o3dsoft.coarse import estimate, load_model
    from o3dsoft.data import get_protocol, load_pairs
    from o3dsoft.pipeline import RegisterConfig
    from o3dsoft.preprocess import normalise_pair, sample_points
    from o3dsoft.search import cube_rotations, network_candidates

    model = load_model(weights)
    pairs = load_pairs(data, "test", get_protocol("paper"))
    normalised = [normalise_pair(pairs[i].source, pairs[i].target)[:2] for i in range(runs + 3)]
    small = RegisterConfig().search.starts.points
    jobs = {
        "one_pass": lambda s, t: estimate(model, s, t),
        "two_passes": lambda s, t: estimate(model, s, t, iterations=2),
        "search_24_hypotheses": lambda s, t: network_candidates(model, sample_points(s, small), sample_points(t, small), cube_rotations()),
    }
    report = {"search_points": small}
    for name, job in jobs.items():
        times = []
        for s, t in normalised:
            t0 = time.perf_counter()
            job(s, t)
            times.append(time.perf_counter() - t0)
        warm = times[3:]  # TorchScript's profiling executor optimises during the first calls
        report[name] = {
            "first_call_ms": times[0] * 1000,
            "median_ms": statistics.median(warm) * 1000,
            "p90_ms": float(np.percentile(warm, 90)) * 1000,
            "runs": len(warm),
        }
    return report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--literal-steps", type=int, default=2)
    ap.add_argument("--inference-runs", type=int, default=30)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--skip-train", action="store_true")
    args = ap.parse_args()
    report = {"torch": torch.__version__, "threads": torch.get_num_threads()}
    if not args.skip_train:
        report["train"] = train_speed(args.data, args.steps, args.literal_steps)
        report["train"]["fast_peak_rss_gb"] = peak_memory(args.data, 2, literal=False)
        report["train"]["literal_peak_rss_gb"] = peak_memory(args.data, 1, literal=True)
        report["train"]["epoch_minutes_estimate"] = 9843 / report["train"]["fast_pairs_per_s"] / 60
    report["inference"] = inference_latency(args.weights, args.inference_runs, args.data)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
