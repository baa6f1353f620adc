"""Register real scans (RGB-D fragments, LiDAR sweeps, structured-light views) with the defaults.

    python examples/register_scans.py                          # the shared real scans, else the bundled bunny pair
    python examples/register_scans.py FOLDER [FOLDER ...]      # every pair of each folder's pairs.txt
    python examples/register_scans.py SRC.ply TGT.ply [--gt T.txt]
    ... --render DIR                                           # one picture per pair

No setting depends on the scans' units or size: o3dsoft registers dense scans on a voxel grid of
1 % of the scene's size, refines with point-to-plane ICP, and
decides whether to trust the result on the clouds it is the answer for. A pairs.txt lists one
pair per line, ``source target transform`` (paths relative to its folder, the transform a 4x4
T_target_source); see ../shared/data/real_scans/README.md.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Iterator, Optional, Tuple

import o3dsoft
from o3dsoft.scans import read_pairs_file

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data" / "real_scans"
BUNDLED = (HERE / "data" / "bun045.ply", HERE / "data" / "bun000.ply", HERE / "data" / "bun045_to_bun000.txt")


def pairs(args: argparse.Namespace) -> Iterator[Tuple[Path, Path, Optional[Path]]]:
    """(source, target, ground truth or None) for every pair asked for."""
    if len(args.inputs) == 2 and all(p.is_file() for p in args.inputs):
        yield args.inputs[0], args.inputs[1], args.gt
        return
    folders = args.inputs or sorted(p for p in SHARED.glob("*") if (p / "pairs.txt").is_file())
    if not folders:  # no shared data: the bundled pair
        yield BUNDLED
        return
    for folder in folders:
        for entry in read_pairs_file(folder / "pairs.txt"):
            yield entry.source, entry.target, entry.transform


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="*", type=Path, help="folders with a pairs.txt, or two scans")
    ap.add_argument("--gt", type=Path, help="ground-truth T_target_source of two scans")
    ap.add_argument("--render", type=Path, help="folder for one picture per pair")
    args = ap.parse_args()
    model = o3dsoft.load_model()  # once, for every pair
    for source_path, target_path, gt in pairs(args):
        source, target = o3dsoft.read_points(source_path), o3dsoft.read_points(target_path)
        start = time.perf_counter()
        result = o3dsoft.register(source, target, model=model)
        seconds = time.perf_counter() - start
        grid = f"{result.voxel:.3g}-unit grid" if result.voxel is not None else "every point"
        print(f"{source_path.name} -> {target_path.name}: {len(source)} and {len(target)} points, registered on {grid}, ICP point-to-{result.icp_method}")
        print(
            f"  confidence {result.confidence:.3f} (0-1, higher is better){'  LIKELY FAILED: ' + str(result.failure_reason) if result.likely_failed else ''}; "
            f"time {1000 * seconds:.0f} ms (lower is better)"
        )
        if gt is not None:
            e = o3dsoft.pair_errors(result.transformation, o3dsoft.read_transform(gt))
            print(f"  error against the ground truth: rotation {e.rotation_deg:.3f} deg, translation {e.translation:.4g} units (lower is better)")
        if args.render is not None:
            from o3dsoft.render import render_registration

            args.render.mkdir(parents=True, exist_ok=True)
            picture = args.render / f"{source_path.stem}_to_{target_path.stem}.png"
            scale = 3 * result.voxel if result.voxel is not None else result.tight_distance
            render_registration(picture, source, target, [("input", None), ("result", result.transformation)], scale, f"Confidence {result.confidence:.2f}.")
            print(f"  picture: {picture}")


if __name__ == "__main__":
    main()
