"""Scan pairs whose source the user thinned first: is a right alignment still trusted?

    python -m benchmarks.sparse_source [FOLDER] [--voxels 0.05 0.08 0.12] [--starts 25]
        [--seed 1] [--out FILE.json]

FOLDER holds scans and a ``pairs.txt`` (default: the 3DMatch fragments of ``real_scans``). For
each pair and voxel size (cloud units), the source is voxel-downsampled (Open3D) and the target
kept as it is. Two measurements per voxel size:

- ``register``: `o3dsoft.register` on the thinned source: rotation error (degrees), translation
  error (cloud units) and the reported confidence (0-1) of each pair;
- ``starts``: ICP as the pipeline runs it on the same clouds (its grid, distance and normals) from
  `starts` poses turned 5-90 degrees about the source's centre and shifted by 0.05 x the target's
  scene size per axis (standard deviation) off the truth, each result scored by the larger of the
  strict and the scan confidence: how many right results (within 5 deg and 0.03 x the scene size
  of the truth: 10 cm on a 3DMatch fragment) are trusted (higher is better) and how many wrong ones
  are (lower is better).

A confidence that does not depend on how densely the user sampled the source trusts the right
results at every voxel size and the wrong ones at none. About 15 s per voxel size on the six 3DMatch
pairs on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, List

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from o3dsoft import confidence as confidence_stage
from o3dsoft import refine as refine_stage
from o3dsoft.config import RegisterConfig
from o3dsoft.io import read_points
from o3dsoft.metrics import pair_errors
from o3dsoft.pair import PreparedPair
from o3dsoft.pipeline import register
from o3dsoft.preprocess import scene_size
from o3dsoft.scans import read_pairs_file

DEFAULT_FOLDER = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_scans" / "3dmatch_redkitchen"
# A start's result is right within these of the truth (degrees; share of the target's scene size).
RIGHT_DEG, RIGHT_SHIFT = 5.0, 0.03


def thinned(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N', 3): `points` (N, 3) voxel-downsampled at `voxel` (cloud units); as they are at 0."""
    return points if voxel <= 0 else np.asarray(refine_stage.to_open3d(points).voxel_down_sample(voxel).points)


def perturbed(truth: np.ndarray, centre: np.ndarray, shift: float, rng: np.random.Generator) -> np.ndarray:
    """(4, 4) `truth` after a turn of 5-90 degrees about `centre` (3,) and a random shift."""
    axis = rng.normal(size=3)
    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(np.deg2rad(rng.uniform(5.0, 90.0)) * axis / np.linalg.norm(axis)).as_matrix()
    P[:3, 3] = centre - P[:3, :3] @ centre + rng.normal(size=3) * shift
    return truth @ P


def starts_outcome(source: np.ndarray, target: np.ndarray, truth: np.ndarray, starts: int, seed: int) -> Dict[str, int]:
    """ICP from `starts` perturbed poses, as the pipeline refines: right/wrong results, trusted or not."""
    pair = PreparedPair(source, target, RegisterConfig(), k=20)
    src, tgt = pair.full
    scorer, normals = pair.scorer("full"), pair.target_normals("full")
    size = scene_size(tgt)
    rng = np.random.default_rng(seed)
    out = {"right_trusted": 0, "right": 0, "wrong_trusted": 0, "wrong": 0}
    for _ in range(starts):
        result = refine_stage.icp(src, tgt, perturbed(truth, src.mean(axis=0), 0.05 * size, rng), pair.distance, pair.config.icp, normals)
        errors = pair_errors(result.transformation, truth)
        f = scorer(result.transformation)
        trusted = max(confidence_stage.confidence(f), confidence_stage.scan_confidence(f)) >= 0.5
        kind = "right" if errors.rotation_deg < RIGHT_DEG and errors.translation < RIGHT_SHIFT * size else "wrong"
        out[kind] += 1
        out[f"{kind}_trusted"] += int(trusted)
    return out


def main(argv: "List[str] | None" = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", type=Path, default=DEFAULT_FOLDER)
    parser.add_argument("--voxels", type=float, nargs="+", default=[0.0, 0.05, 0.08, 0.12])
    parser.add_argument("--starts", type=int, default=25)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    entries = read_pairs_file(args.folder / "pairs.txt")
    report = []
    for voxel in args.voxels:
        pairs, totals = [], {"right_trusted": 0, "right": 0, "wrong_trusted": 0, "wrong": 0}
        for entry in entries:
            source, target, truth = thinned(read_points(entry.source), voxel), read_points(entry.target), np.loadtxt(entry.transform)
            result = register(source, target)
            errors = pair_errors(result.transformation, truth)
            pairs.append(
                {
                    "pair": f"{entry.source.name}->{entry.target.name}",
                    "points": len(source),
                    "rotation_deg": errors.rotation_deg,
                    "translation": errors.translation,
                    "confidence": result.confidence,
                }
            )
            for key, value in starts_outcome(source, target, truth, args.starts, args.seed).items():
                totals[key] += value
        report.append({"voxel": voxel, "register": pairs, "starts": totals})
        rows = ", ".join(f"{p['pair']} {p['rotation_deg']:.1f} deg conf {p['confidence']:.2f}" for p in pairs)
        print(f"voxel {voxel:g}: register (rotation error, lower is better; confidence): {rows}")
        print(
            f"  starts: right trusted {totals['right_trusted']} of {totals['right']} (higher is better), wrong trusted {totals['wrong_trusted']} of {totals['wrong']} (lower is better)",
            flush=True,
        )
    if args.out:
        args.out.write_text(json.dumps({"folder": str(args.folder), "starts": args.starts, "seed": args.seed, "voxels": report}, indent=1) + "\n")


if __name__ == "__main__":
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    main()
