"""Register two real scans (LiDAR, RGB-D, structured light): the README's recipe in code.

    python examples/register_scans.py                                  # the bundled bunny scans
    python examples/register_scans.py SRC TGT --voxel 0.05 --icp-distance 0.5 [--gt T.txt]

The recipe, for scans in metres of up to a few million points:
1. Voxel-downsample both scans to a common spacing (`--voxel`): it evens out the density of
   near and far regions, which ICP and the confidence otherwise weigh unevenly, and bounds the
   time. A few times the sensor noise: 2-5 mm for RGB-D or structured light, 5-10 cm for LiDAR.
2. Give ICP an absolute correspondence distance (`--icp-distance`, metres): about the size of the
   error you expect from the coarse stage, here 10 x the voxel. ICP then runs at 1, 0.3 and 0.1 of
   it, so the last stage keeps only pairs closer than about one voxel.
3. Keep the global search's FPFH feature match (`search.features.enabled`, on by default): scans overlap
   partly and can be turned any way, where a coarse stage trained on whole objects is least reliable.
4. Read the confidence: below 0.5 the result is flagged as likely failed; scans that share less
   than ~80 % of their surface can be flagged although right, so look at them (`--render`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import o3dsoft

DATA = Path(__file__).resolve().parent / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", nargs="?", type=Path, default=DATA / "bun045.ply")
    ap.add_argument("target", nargs="?", type=Path, default=DATA / "bun000.ply")
    ap.add_argument("--gt", type=Path, help="ground-truth T_target_source (default: the bundled pair's)")
    ap.add_argument("--voxel", type=float, default=0.002, help="voxel size in the scans' units (default 0.002: 2 mm)")
    ap.add_argument("--icp-distance", type=float, default=None, help="ICP distance in the scans' units (default 10 x voxel)")
    args = ap.parse_args()
    gt = args.gt or (DATA / "bun045_to_bun000.txt" if args.source == DATA / "bun045.ply" else None)

    source, target = o3dsoft.read_points(args.source), o3dsoft.read_points(args.target)
    config = o3dsoft.RegisterConfig(
        voxel=args.voxel,  # step 1
        icp=o3dsoft.ICPConfig(distance=args.icp_distance or 10 * args.voxel, absolute=True),  # step 2
    )  # step 3: the search's feature match is on by default
    result = o3dsoft.register(source, target, config)
    print(
        f"{args.source.name}: {len(source)} points, {args.target.name}: {len(target)} points; "
        f"{result.num_source} and {result.num_target} on the {args.voxel:g} voxel grid"
    )
    print("T_target_source:\n" + np.array2string(result.transformation, precision=6, suppress_small=True))
    print(
        f"confidence {result.confidence:.3f} (0-1, higher is better){'  LIKELY FAILED' if result.likely_failed else ''}; "
        f"fitness {result.fitness:.3f} (higher is better); inlier RMSE {result.inlier_rmse:.4g} units (lower is better)"
    )
    print(f"search ran: {result.searched}; time {result.timings_ms['total']:.0f} ms (lower is better)")
    if gt is not None:
        e = o3dsoft.pair_errors(result.transformation, o3dsoft.read_transform(gt))
        print(f"error against the ground truth: rotation {e.rotation_deg:.3f} deg, translation {e.translation:.4g} units (lower is better)")


if __name__ == "__main__":
    main()
