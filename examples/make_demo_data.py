"""Rebuild the demo pair in examples/data/ from the Stanford Bunny scans in ../shared/data.

    python examples/make_demo_data.py [--data ../shared/data/stanford_bunny] [--voxel 0.002]

Writes bun045.ply (source), bun000.ply (target), both voxel-downsampled, and
bun045_to_bun000.txt, the ground-truth T_target_source computed from bun.conf.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from o3dsoft.io import read_points, write_points, write_transform
from o3dsoft.refine import to_open3d
from o3dsoft.scans import read_conf, relative_pose

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(HERE.parent.parent / "shared" / "data" / "stanford_bunny"))
    parser.add_argument("--voxel", type=float, default=0.002, help="voxel size in metres")
    args = parser.parse_args()
    data = Path(args.data)
    out = HERE / "data"
    out.mkdir(exist_ok=True)
    poses = read_conf(data / "bun.conf")
    for name in ("bun045.ply", "bun000.ply"):
        points = np.asarray(to_open3d(read_points(data / name)).voxel_down_sample(args.voxel).points)
        write_points(out / name, points)
        print(f"{name}: {len(points)} points")
    write_transform(out / "bun045_to_bun000.txt", relative_pose(poses, "bun045.ply", "bun000.ply"))


if __name__ == "__main__":
    main()
