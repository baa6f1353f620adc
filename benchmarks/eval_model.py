"""Accuracy of a model on ModelNet40 test pairs: the network alone and followed by ICP.

    python -m benchmarks.eval_model [--weights weights/o3dsoft_default.pt] [--protocol paper dcp] [--search off]
        [--limit 300] [--data ../shared/data/modelnet40_ply_hdf5_1024] [--seed 0] [--iterations 1 2]

The model alone (no second network, ``RegisterConfig.second_network``). Prints one JSON object per protocol and stage with the summary of o3dsoft.metrics.summarise
(isotropic rotation error in degrees, translation error in shape units, DCP's Euler RMSE/MAE,
recall at (1 deg, 0.01) and (5 deg, 0.05)) and the median time per pair in ms.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from o3dsoft.coarse import load_model
from o3dsoft.config import SearchConfig, SecondNetworkConfig
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.metrics import pair_errors, summarise
from o3dsoft.pipeline import RegisterConfig, register

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "modelnet40_ply_hdf5_1024"


def evaluate_protocol(model, data: str, protocol: str, limit: int, seed: int, iterations: int = 1, search: str = "auto") -> dict:
    pairs = load_pairs(data, "test", get_protocol(protocol), seed)
    n = min(limit, len(pairs)) if limit else len(pairs)
    coarse, fine, times = [], [], []
    # This model alone: no second network.
    config = RegisterConfig(coarse_iterations=iterations, search=SearchConfig(mode=search), second_network=SecondNetworkConfig(weights=None))
    for i in range(n):
        p = pairs[i]
        t0 = time.perf_counter()
        result = register(p.source, p.target, config, model=model)
        times.append((time.perf_counter() - t0) * 1000)
        coarse.append(pair_errors(result.coarse_transformation, p.transform))
        fine.append(pair_errors(result.transformation, p.transform))
    return {
        "protocol": protocol,
        "pairs": n,
        "coarse_iterations": iterations,
        "network": summarise(coarse),
        "network+icp": summarise(fine),
        "median_ms_per_pair": statistics.median(times),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--protocol", nargs="+", default=["paper", "dcp"])
    ap.add_argument("--limit", type=int, default=300, help="first N test pairs (0: all 2,468)")
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, nargs="+", default=[1], help="network passes of the coarse stage (several: one run each)")
    ap.add_argument("--search", choices=["auto", "always", "off"], default="auto", help="the global search (off: the network's own estimate)")
    args = ap.parse_args()
    model = load_model(args.weights)
    for protocol in args.protocol:
        for iterations in args.iterations:
            print(json.dumps(evaluate_protocol(model, args.data, protocol, args.limit, args.seed, iterations, args.search)), flush=True)


if __name__ == "__main__":
    main()
