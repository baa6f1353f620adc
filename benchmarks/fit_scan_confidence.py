"""Fit the coefficients of o3dsoft.confidence.scan_confidence on scan pairs the scans bench does
not run.

    python -m benchmarks.fit_scan_confidence [--data ../shared/data] [--failure-weight 100]

The pairs: the Stanford bunny's ordered scan pairs under the bench's 0.3 overlap, and the 3DMatch
red-kitchen fragment pairs that its pairs.txt does not list (both directions), their ground truth
composed from the listed transforms, where at least 5 % of the source lies within 1 % of the
scale of the target. Each pair is aligned by its ground truth and by point-to-plane ICP on the
work clouds from the ground truth turned by random rotations of up to 30, 60, 90 and 180 degrees;
an alignment is right within the folder's loose test (bunny 5 deg / 5 % of the size, 3DMatch 15 deg
/ 0.3 m). The planar share (``Features.planar``) is measured by the pipeline's own scorer of the
work clouds, and a logistic regression fitted on the alignments that touch (overlap at least
``min_overlap``), failures weighing `--failure-weight` times the successes in total: a wrong pose
reported as trusted costs far more than a right one flagged. Prints the coefficients to paste into
``ConfidenceConfig.scan_coefficients``, and where 0.5 lies.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from o3dsoft.bench import scan_folder
from o3dsoft.clock import StageClock
from o3dsoft.config import RegisterConfig
from o3dsoft.io import read_points, read_transform
from o3dsoft.pair import PreparedPair
from o3dsoft.preprocess import normalisation_for
from o3dsoft.refine import icp
from o3dsoft.transforms import apply_transform, rotation_angle_deg

from .fit_confidence import fit_logistic, random_rotation_within

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TURNS = ((30, 3), (60, 3), (90, 3), (180, 4))  # (largest turn in degrees, starts)


def problems(data: Path):
    """Yield (name, source, target, T_target_source, (degrees, distance) of a right pose)."""
    bunny = data / "stanford_bunny"
    benched = {pair.category for pair in scan_folder(bunny).pairs}
    folder = scan_folder(bunny, min_overlap=0.0)
    for pair in folder.pairs:
        if pair.category not in benched:
            yield f"bunny {pair.category}", pair.source, pair.target, pair.transform, folder.recall[-1]
    kitchen = data / "real_scans" / "3dmatch_redkitchen"
    listed = [line.split()[:2] for line in (kitchen / "pairs.txt").read_text().splitlines() if line and not line.startswith("#")]
    poses = {"cloud_bin_1.ply": np.eye(4)}  # in fragment 1's frame, along the listed chain
    for _ in range(len(listed)):
        for (s, t), gt in zip(listed, (read_transform(kitchen / f"gt_{s[10:-4]}_to_{t[10:-4]}.txt") for s, t in listed)):
            if t in poses and s not in poses:
                poses[s] = poses[t] @ gt
    clouds = {name: read_points(kitchen / name) for name in poses}
    for s in poses:
        for t in poses:
            if s == t or [s, t] in listed:
                continue
            T = np.linalg.inv(poses[t]) @ poses[s]
            reach = 0.01 * normalisation_for(clouds[s], clouds[t]).scale
            if np.isfinite(cKDTree(clouds[t]).query(apply_transform(T, clouds[s]), distance_upper_bound=reach)[0]).mean() > 0.05:
                yield f"3dmatch {s[:-4]}->{t[:-4]}", clouds[s], clouds[t], T, (15.0, 0.3)


def measure(data: Path, seed: int):
    """(planar, overlap, right) of every alignment: three (N,) arrays."""
    config = RegisterConfig()
    rng = np.random.default_rng(seed)
    rows = []
    for name, source, target, truth, (degrees, distance) in problems(data):
        pair = PreparedPair(source, target, config, 20, ("source", "target"), StageClock())
        src, tgt = pair.clouds("work")
        centre = src.mean(axis=0)
        poses = [truth]
        for largest, starts in TURNS:
            for _ in range(starts):
                turn = np.eye(4)
                turn[:3, :3] = random_rotation_within(rng, largest)
                turn[:3, 3] = centre - turn[:3, :3] @ centre  # about the source's centre
                poses.append(icp(src, tgt, truth @ turn, pair.distance, config.icp, pair.target_normals("work")).transformation)
        for T in poses:
            f = pair.scorer("work")(T)
            right = rotation_angle_deg(T[:3, :3] @ truth[:3, :3].T) <= degrees and np.linalg.norm(T[:3, 3] - truth[:3, 3]) <= distance
            rows.append((f.planar, f.overlap, right))
        print(f"{name}: {sum(r[2] for r in rows[-len(poses) :])} of {len(poses)} right", flush=True)
    return tuple(np.array(column, dtype=float) for column in zip(*rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--failure-weight", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    planar, overlap, right = measure(args.data, args.seed)
    touch = (overlap >= RegisterConfig().confidence.min_overlap) & np.isfinite(planar)
    X, y = planar[touch, None], right[touch]
    w = fit_logistic(X, y, failure_weight=args.failure_weight)
    score = 1 / (1 + np.exp(-(w[0] + w[1] * X[:, 0])))
    print(f"alignments that touch: {len(y)} ({int(y.sum())} right)")
    print(f"scan_coefficients = ({w[0]:.2f}, {w[1]:.2f}); 0.5 at planar {-w[0] / w[1]:.3f}")
    print(f"wrong at 0.5 or more: {int(((score >= 0.5) & (y < 0.5)).sum())}; right below 0.5: {int(((score < 0.5) & (y > 0.5)).sum())}")
    print(f"largest planar share of a wrong alignment: {X[y < 0.5, 0].max():.3f}")


if __name__ == "__main__":
    main()
