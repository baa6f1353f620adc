"""Scan pairs whose source the user thinned first: is a right alignment still trusted?

    python -m benchmarks.sparse_source [FOLDER ...] [--voxels 0 0.015 0.025 0.035] [--every 1]
        [--starts 25] [--seed 1] [--out FILE.json]

Each FOLDER is one `o3dsoft bench scans` takes (a ``pairs.txt``, or a Stanford ``.conf``: every
ordered pair overlapping 30 % or more; default: the 3DMatch fragments of ``real_scans``); every
`every`-th pair is used. For each voxel size (a share of the target's scene size: 0.025 is 9 cm on
a 3DMatch fragment, 5 mm on a bunny scan; 0: as given), the source is voxel-downsampled (Open3D)
and the target kept as it is. Two measurements per voxel size:

- ``register``: `o3dsoft.register` on the thinned source: rotation error (degrees), translation
  error (cloud units) and the reported confidence (0-1) of each pair;
- ``starts``: ICP as the pipeline runs it on the same clouds (its grid, distance and normals) from
  `starts` poses turned 5-90 degrees about the source's centre and shifted by 0.05 x the target's
  scene size per axis (standard deviation) off the truth, each result scored by the larger of the
  strict and the scan confidence: how many right results (within 5 deg and 0.03 x the scene size
  of the truth) are trusted (higher is better) and how many wrong ones are (lower is better).

A confidence that does not depend on how densely the user sampled the source trusts as many right
results, and as few wrong ones, at every voxel size as on the clouds as given. About 15 s per
voxel size on the six 3DMatch pairs on a 2-core CPU.
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
from o3dsoft.bench import BenchPair, scan_folder
from o3dsoft.config import RegisterConfig
from o3dsoft.metrics import PairErrors, pair_errors
from o3dsoft.pair import PreparedPair
from o3dsoft.pipeline import register
from o3dsoft.preprocess import scene_size

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


def is_right(errors: PairErrors, size: float) -> bool:
    """Within RIGHT_DEG degrees and RIGHT_SHIFT x `size` (cloud units) of the truth."""
    return errors.rotation_deg < RIGHT_DEG and errors.translation < RIGHT_SHIFT * size


def starts_outcome(pair: BenchPair, source: np.ndarray, starts: int, seed: int) -> Dict[str, int]:
    """ICP from `starts` perturbed poses of the truth, as the pipeline refines `source` (N, 3)
    onto the pair's target: how many results are right and wrong, and how many of each trusted."""
    truth = pair.transform
    prepared = PreparedPair(source, pair.target, RegisterConfig(), k=20)
    src, tgt = prepared.full
    scorer, normals = prepared.scorer("full"), prepared.target_normals("full")
    size = scene_size(tgt)
    rng = np.random.default_rng(seed)
    out = {"right_trusted": 0, "right": 0, "wrong_trusted": 0, "wrong": 0}
    for _ in range(starts):
        result = refine_stage.icp(src, tgt, perturbed(truth, src.mean(axis=0), 0.05 * size, rng), prepared.distance, prepared.config.icp, normals)
        errors = pair_errors(result.transformation, truth, pair.origin)
        f = scorer(result.transformation)
        trusted = max(confidence_stage.confidence(f), confidence_stage.scan_confidence(f)) >= 0.5
        kind = "right" if is_right(errors, size) else "wrong"
        out[kind] += 1
        out[f"{kind}_trusted"] += int(trusted)
    return out


def main(argv: "List[str] | None" = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", type=Path, default=[DEFAULT_FOLDER])
    parser.add_argument("--voxels", type=float, nargs="+", default=[0.0, 0.015, 0.025, 0.035])
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--starts", type=int, default=25)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    pairs = [pair for folder in args.folders for pair in scan_folder(folder).pairs[:: args.every]]
    report = []
    for share in args.voxels:
        rows, totals = [], {"right_trusted": 0, "right": 0, "wrong_trusted": 0, "wrong": 0}
        for pair in pairs:
            source = thinned(pair.source, share * scene_size(pair.target))
            result = register(source, pair.target)
            errors = pair_errors(result.transformation, pair.transform, pair.origin)
            rows.append(
                {
                    "pair": f"{pair.protocol}/{pair.category}",
                    "points": len(source),
                    "rotation_deg": errors.rotation_deg,
                    "translation": errors.translation,
                    "right": is_right(errors, scene_size(pair.target)),
                    "confidence": result.confidence,
                }
            )
            for key, value in starts_outcome(pair, source, args.starts, args.seed).items():
                totals[key] += value
        report.append({"voxel_share": share, "register": rows, "starts": totals})
        right = [r for r in rows if r["right"]]
        print(
            f"voxel {share:g} x scene size: register right on {len(right)} of {len(rows)} pairs, "
            f"trusted {sum(r['confidence'] >= 0.5 for r in right)} of them (higher is better); "
            f"wrong results trusted {sum(r['confidence'] >= 0.5 for r in rows if not r['right'])} (lower is better)"
        )
        print(
            f"  starts: right trusted {totals['right_trusted']} of {totals['right']} (higher is better), wrong trusted {totals['wrong_trusted']} of {totals['wrong']} (lower is better)",
            flush=True,
        )
    if args.out:
        args.out.write_text(
            json.dumps({"folders": [str(f) for f in args.folders], "every": args.every, "starts": args.starts, "seed": args.seed, "voxels": report}, indent=1)
            + "\n"
        )


if __name__ == "__main__":
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    main()
