"""The search's feature match against Open3D's RANSAC, on the same FPFH features.

    python -m benchmarks.feature_match [--protocol rpmnet-crop] [--pairs 200] [--candidates 20] [--data D]

For each of the first test pairs of the protocol: Open3D's RANSAC (seed 0) and
:meth:`o3dsoft.search.FeatureMatch.candidates` (seed 0) from the same features (the search's,
:class:`o3dsoft.search.FeatureMatchConfig`); every estimate is
refined by o3dsoft's ICP and scored by the confidence. Prints the share of pairs within
(1 deg, 0.01) for Open3D's estimate, for the first candidate, for the most confident of the
candidates, and for the best of them (had one known the truth), and the median time of Open3D's
RANSAC and of drawing the candidates (ms, same run, lower is better).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft import baselines, refine
from o3dsoft import confidence as conf
from o3dsoft.bench import modelnet_pairs
from o3dsoft.metrics import pair_errors
from o3dsoft.preprocess import normalisation_for
from o3dsoft.search import FeatureMatch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--protocol", default="rpmnet-crop")
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--candidates", type=int, default=20)
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    args = parser.parse_args()

    _, pairs = modelnet_pairs(args.data, [args.protocol], args.pairs, 0)
    right = {"open3d": [], "first": [], "most confident": [], "best": []}
    ms = {"open3d": [], "candidates": []}
    for pair in pairs:
        src, tgt = pair.source.astype(np.float64), pair.target.astype(np.float64)
        scale = normalisation_for(src, tgt).scale
        distance = refine.ICPConfig().distance_for(scale)

        def refined(T: np.ndarray):
            fine = refine.icp(src, tgt, T, distance).transformation
            errors = pair_errors(fine, pair.transform)
            return errors.rotation_deg < 1.0 and errors.translation < 0.01, conf.confidence(conf.features(src, tgt, fine, distance))

        match = FeatureMatch(src, tgt, scale)
        t0 = time.perf_counter()
        T_open3d = baselines.ransac(match.source, match.target, scale, 0)
        ms["open3d"].append((time.perf_counter() - t0) * 1000.0)
        t0 = time.perf_counter()
        candidates = match.candidates(0, args.candidates)
        ms["candidates"].append((time.perf_counter() - t0) * 1000.0)
        right["open3d"].append(refined(T_open3d)[0])
        scored = [refined(T) for T in candidates] or [(False, 0.0)]
        right["first"].append(scored[0][0])
        right["most confident"].append(max(scored, key=lambda r: r[1])[0])
        right["best"].append(any(ok for ok, _ in scored))
    print(f"{args.protocol}, first {len(right['open3d'])} test pairs; within (1 deg, 0.01) after ICP, higher is better:")
    for name, oks in right.items():
        print(f"  {name:15s} {100.0 * np.mean(oks):5.1f} %")
    print(f"median ms, lower is better: Open3D RANSAC {np.median(ms['open3d']):.1f}, {args.candidates} candidates {np.median(ms['candidates']):.1f}")


if __name__ == "__main__":
    main()
