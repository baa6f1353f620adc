"""Where a pair's time goes: the median time of each stage of ``o3dsoft.register``.

    python -m benchmarks.stage_times [--protocol paper] [--limit 100] [--data PATH] [--rounds 2]

Registers the first `limit` ModelNet40 test pairs of a protocol with the default settings,
`rounds` times over, and prints the median and mean of each stage's time (ms, lower is better)
over the last round (the earlier ones warm the process up). Run it alone on the machine: other
work on the same cores slows the network most (docs/speed.md).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft.bench import modelnet_pairs
from o3dsoft.coarse import load_model
from o3dsoft.pipeline import RegisterConfig, register


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--protocol", default="paper")
    ap.add_argument("--limit", type=int, default=100)
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    if args.rounds < 1 or args.limit < 1:
        ap.error("--rounds and --limit must be at least 1")
    _, pairs = modelnet_pairs(args.data, [args.protocol], args.limit, 0)
    clouds = [(p.source.astype(np.float64), p.target.astype(np.float64)) for p in pairs]
    model = load_model(None)
    for _ in range(args.rounds):
        timings = [register(s, t, RegisterConfig(), model=model).timings_ms for s, t in clouds]
    print(f"{args.protocol}, first {len(clouds)} pairs, ms per pair (lower is better):")
    for stage in sorted({k for t in timings for k in t}):
        values = [t.get(stage, 0.0) for t in timings]
        print(f"  {stage:18s} median {np.median(values):7.2f}   mean {np.mean(values):7.2f}")


if __name__ == "__main__":
    main()
