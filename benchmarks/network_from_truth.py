"""The network on scan pairs started near the truth: does it hold a right pose, or leave it?

    python -m benchmarks.network_from_truth [--weights default incongruent partial]
        [--scans ../shared/data/stanford_bunny] [--angles 0 15 30 45 90] [--passes 3] [--seed 0]

For every pair of a folder of scans (`o3dsoft.bench.scan_folder`, as `o3dsoft bench scans` takes
them), the network's samples of the two clouds are prepared as `register` prepares them
(`o3dsoft.pair.PreparedPair`); the source is turned onto the target by the ground-truth rotation
and then by a further random turn of each angle (degrees, about a random axis), and the network
runs `--passes` times from there, each pass from the estimate so far. Prints, per weights and
angle, the median and quartiles of the rotation error in degrees (lower is better) and the share
of pairs within 5 degrees (higher is better). A network that aligns surfaces keeps the 0-degree
start; one that does not moves away from the truth itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from o3dsoft.bench import scan_folder
from o3dsoft.coarse import CoarseModel, cached_model
from o3dsoft.config import RegisterConfig
from o3dsoft.pair import PreparedPair
from o3dsoft.search import network_candidates
from o3dsoft.transforms import axis_angle_to_matrix, rotation_angle_deg

DEFAULT_SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "stanford_bunny"


def errors_from_truth(model: CoarseModel, folder: Path, angles: list, passes: int, seed: int) -> np.ndarray:
    """(P, A) rotation errors in degrees of `model` after `passes` passes, per pair of the scans
    in `folder` and start angle (degrees from the truth)."""
    pairs = scan_folder(folder).pairs
    config = RegisterConfig()
    rng = np.random.default_rng(seed)
    errors = np.zeros((len(pairs), len(angles)))
    for i, p in enumerate(pairs):
        source, target = PreparedPair(p.source, p.target, config, model.config.k).net_normalised
        R_true = p.transform[:3, :3]
        axes = rng.normal(size=(len(angles), 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        starts = np.stack([axis_angle_to_matrix(np.radians(a) * axis) @ R_true for a, axis in zip(angles, axes)])
        for _ in range(passes):  # each pass from the rotation so far (the network centres the source itself)
            starts = network_candidates(model, source, target, starts)[:, :3, :3]
        errors[i] = [rotation_angle_deg(R.T @ R_true) for R in starts]
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", nargs="+", default=["default", "incongruent", "partial"])
    parser.add_argument("--scans", type=Path, default=DEFAULT_SCANS)
    parser.add_argument("--angles", type=float, nargs="+", default=[0.0, 15.0, 30.0, 45.0, 90.0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("weights | start (deg from the truth) | rotation error median [q25, q75] (deg, lower is better) | within 5 deg (higher is better)")
    for weights in args.weights:
        errors = errors_from_truth(cached_model(weights, "cpu"), args.scans, args.angles, args.passes, args.seed)
        for j, angle in enumerate(args.angles):
            e = errors[:, j]
            print(f"{weights} | {angle:g} | {np.median(e):.1f} [{np.quantile(e, 0.25):.1f}, {np.quantile(e, 0.75):.1f}] | {100 * np.mean(e < 5):.1f} %")


if __name__ == "__main__":
    main()
