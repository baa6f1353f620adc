"""Fit the coefficients of o3dsoft.confidence.scan_confidence on scan pairs the scans bench does
not run.

    python -m benchmarks.fit_scan_confidence [--data ../shared/data] [--failure-weight 100]

The pairs: the Stanford bunny's ordered scan pairs that the bench runs in neither direction
(under its 0.3 overlap both ways), and the 3DMatch red-kitchen fragment pairs that its pairs.txt
lists in neither direction, their ground truth composed from the listed transforms, where over
5 % of the source lies within 1 % of the scale of the target. Each pair is aligned by its ground truth and by point-to-plane ICP on the
work clouds from the ground truth turned by random rotations of up to 30, 60, 90 and 180 degrees;
an alignment is right within the folder's loose test (bunny 5 deg / 5 % of the size, 3DMatch 15 deg
/ 0.3 m). The planar share (``Features.planar``) is measured by the pipeline's own scorer of the
work clouds, and a logistic regression fitted on the alignments that touch (overlap at least
``min_overlap``), failures weighing `--failure-weight` times the successes in total: a wrong pose
reported as trusted costs far more than a right one flagged. Prints the coefficients to paste into
``ConfidenceConfig.scan_coefficients``, and where 0.5 lies. With ``--bench pairs.csv`` (an ``o3dsoft
bench scans`` run), the bench's pairs are measured the same way, with o3dsoft's results among the
alignments, and judged by these coefficients: the right results the strict confidence flags, and
every wrong alignment that touches, with its planar share and reported confidence.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import List

import numpy as np
from scipy.spatial import cKDTree

from o3dsoft import confidence as conf
from o3dsoft.bench import scan_folder
from o3dsoft.clock import StageClock
from o3dsoft.config import RegisterConfig
from o3dsoft.io import read_points, read_transform
from o3dsoft.metrics import pair_errors
from o3dsoft.pair import PreparedPair
from o3dsoft.preprocess import normalisation_for
from o3dsoft.refine import icp
from o3dsoft.scans import read_pairs_file
from o3dsoft.transforms import apply_transform

from .fit_confidence import fit_logistic, random_rotation_within

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TURNS = ((30, 3), (60, 3), (90, 3), (180, 4))  # (largest turn in degrees, starts)


def problems(data: Path):
    """Yield (name, source, target, T_target_source, (degrees, distance) of a right pose)."""
    bunny = data / "stanford_bunny"
    benched = {frozenset(pair.category.split("->")) for pair in scan_folder(bunny).pairs}
    folder = scan_folder(bunny, min_overlap=0.0)
    for pair in folder.pairs:
        if frozenset(pair.category.split("->")) not in benched:
            yield f"bunny {pair.category}", pair.source, pair.target, pair.transform, folder.recall[-1]
    kitchen = data / "real_scans" / "3dmatch_redkitchen"
    entries = read_pairs_file(kitchen / "pairs.txt")
    listed = [[entry.source.name, entry.target.name] for entry in entries]
    truths = {(entry.source.name, entry.target.name): read_transform(entry.transform) for entry in entries}
    poses = {listed[0][1]: np.eye(4)}  # in one fragment's frame, along the listed transforms
    for _ in range(len(listed)):
        for (s, t), gt in truths.items():
            if t in poses and s not in poses:
                poses[s] = poses[t] @ gt
    clouds = {name: read_points(kitchen / name) for name in poses}
    for s in poses:
        for t in poses:
            if s == t or [s, t] in listed or [t, s] in listed:
                continue
            T = np.linalg.inv(poses[t]) @ poses[s]
            reach = 0.01 * normalisation_for(clouds[s], clouds[t]).scale
            if np.isfinite(cKDTree(clouds[t]).query(apply_transform(T, clouds[s]), distance_upper_bound=reach)[0]).mean() > 0.05:
                yield f"3dmatch {s[:-4]}->{t[:-4]}", clouds[s], clouds[t], T, (15.0, 0.3)


def bench_problems(data: Path, results: Path):
    """Yield (name, source, target, T_target_source, test, o3dsoft's result or None) for every pair
    of the scans bench (3DMatch, the laser pair, the bunny), its result read from a bench run's
    pairs.csv."""
    found = {}
    with open(results) as f:
        for row in csv.DictReader(f):
            if row["method"] == "o3dsoft":
                found[(row["protocol"], int(row["index"]))] = np.array(row["transform"].split(), dtype=float).reshape(4, 4)
    for folder in (data / "real_scans" / "3dmatch_redkitchen", data / "real_scans" / "outdoor_laser_car", data / "stanford_bunny"):
        scans = scan_folder(folder)
        for pair in scans.pairs:
            yield f"{scans.name} {pair.category}", pair.source, pair.target, pair.transform, scans.recall[-1], found.get((scans.name, pair.index))


def measure(problems, seed: int) -> List[dict]:
    """Every alignment of each problem (the ground truth, ICP from it turned, and the problem's
    result when it has one): its name, kind, features (:class:`o3dsoft.confidence.Features`) and
    whether it is right (within the problem's test)."""
    config = RegisterConfig()
    rng = np.random.default_rng(seed)
    rows = []
    for name, source, target, truth, (degrees, distance), *result in problems:
        pair = PreparedPair(source, target, config, 20, ("source", "target"), StageClock())
        src, tgt = pair.clouds("work")
        centre = src.mean(axis=0)
        poses = [("truth", truth)] + [("result", T) for T in result if T is not None]
        for largest, starts in TURNS:
            for _ in range(starts):
                turn = np.eye(4)
                turn[:3, :3] = random_rotation_within(rng, largest)
                turn[:3, 3] = centre - turn[:3, :3] @ centre  # about the source's centre
                poses.append(("turned", icp(src, tgt, truth @ turn, pair.distance, pair.config.icp, pair.target_normals("work")).transformation))
        for kind, T in poses:
            errors = pair_errors(T, truth)
            right = errors.rotation_deg <= degrees and errors.translation <= distance
            rows.append(dict(name=name, kind=kind, features=pair.scorer("work")(T), right=bool(right)))
        print(f"{name}: {sum(r['right'] for r in rows[-len(poses) :])} of {len(poses)} right", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--failure-weight", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--bench", type=Path, help="pairs.csv of an `o3dsoft bench scans` run: also measure the bench's pairs, with its results")
    args = parser.parse_args()
    min_overlap = RegisterConfig().confidence.min_overlap
    rows = [r for r in measure(problems(args.data), args.seed) if r["features"].overlap >= min_overlap and np.isfinite(r["features"].planar)]
    X, y = np.array([[r["features"].planar] for r in rows]), np.array([r["right"] for r in rows], dtype=float)
    w = fit_logistic(X, y, failure_weight=args.failure_weight)
    config = conf.ConfidenceConfig(scan_coefficients=tuple(w))
    score = np.array([conf.scan_confidence(r["features"], config) for r in rows])
    print(f"alignments that touch: {len(y)} ({int(y.sum())} right)")
    print(f"scan_coefficients = ({w[0]:.2f}, {w[1]:.2f}); 0.5 at planar {-w[0] / w[1]:.3f}")
    print(f"wrong at 0.5 or more: {int(((score >= 0.5) & (y < 0.5)).sum())}; right below 0.5: {int(((score < 0.5) & (y > 0.5)).sum())}")
    print(f"largest planar share of a wrong alignment: {X[y < 0.5, 0].max():.3f}")
    if args.bench is None:
        return
    # The bench's pairs, judged by these coefficients: reported = max(strict, scan confidence).
    for r in measure(bench_problems(args.data, args.bench), args.seed):
        f = r["features"]
        strict = conf.confidence(f, config)
        reported = max(strict, conf.scan_confidence(f, config))
        if r["kind"] == "result" and r["right"] and strict < 0.5:
            print(f"flagged right result {r['name']}: planar {f.planar:.3f}, reported {reported:.2f}")
        if not r["right"] and f.overlap >= min_overlap:
            print(f"wrong {r['kind']} {r['name']}: planar {f.planar:.3f}, strict {strict:.2f}, reported {reported:.2f}")


if __name__ == "__main__":
    main()
