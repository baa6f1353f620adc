"""Many depth views of rooms alike: ``o3dsoft.multiway`` without initial poses, against the poses
the views were cast from.

    python -m benchmarks.indoor_rooms [--views 12 24] [--pixels 160] [--noise 0.004] [--seed 0]
        [--out FILE.json]

The scene: a flat of 8 x 8 m, 2.6 m high, four rooms of about 4 x 4 m behind inner walls with
doors, each with its own few pieces of furniture (boxes and cylinders). Walls, floor and ceiling
are most of what a view sees, and they look alike from room to room: a pose turned 90 or 180
degrees that lays one room's walls on another's fits most points of two views closely. The views:
a depth camera (60 x 45 degrees, `--pixels` across, `--noise` m of range noise, 4 mm by default) on a loop of radius 1.9 m
about the flat's middle, looking along the loop, turned 25 degrees outwards and 10 degrees down;
each sees about a room. A view's pose is wrong beyond 2 degrees or 0.1 m (relative to the first
view). Run it alone on the machine: the times are its own.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

HEIGHT = 2.6  # m, floor to ceiling
WALL = 0.1  # m, wall thickness
RANGE_NOISE = 0.004  # m, along each ray (standard deviation)


def _boxes() -> List[Tuple[float, float, float, float, float, float]]:
    """(x0, y0, z0, x1, y1, z1) of every box of the flat, in metres: slabs, walls, furniture."""
    h, t = HEIGHT, WALL
    boxes = [(-t, -t, -t, 8 + t, 8 + t, 0), (-t, -t, h, 8 + t, 8 + t, h + t)]  # floor, ceiling
    boxes += [(-t, -t, 0, 8 + t, 0, h), (-t, 8, 0, 8 + t, 8 + t, h), (-t, 0, 0, 0, 8, h), (8, 0, 0, 8 + t, 8, h)]
    for axis, at, doors in ((0, 4.6, (2.2, 5.8)), (1, 3.6, (2.15, 5.85))):  # inner walls, doors 1 m wide, 2.1 m high
        start = 0.0
        for door in doors:
            boxes += [(start, at - t / 2, 0, door - 0.5, at + t / 2, h), (door - 0.5, at - t / 2, 2.1, door + 0.5, at + t / 2, h)]
            start = door + 0.5
        boxes.append((start, at - t / 2, 0, 8, at + t / 2, h))
        if axis == 0:  # the same walls along x: swap the first two coordinates of each
            boxes[-5:] = [(y0, x0, z0, y1, x1, z1) for x0, y0, z0, x1, y1, z1 in boxes[-5:]]
    boxes += [
        (0.3, 0.3, 0, 1.5, 0.9, 0.75),  # a table
        (0.2, 3.0, 0, 0.6, 3.5, 1.8),  # a shelf
        (6.5, 0.3, 0, 7.7, 1.2, 0.5),  # a bed
        (7.3, 2.5, 0, 7.8, 3.2, 2.0),  # a wardrobe
        (6.0, 6.8, 0, 7.8, 7.7, 0.8),  # a sofa
        (4.8, 7.3, 0, 5.4, 7.8, 1.2),
        (0.3, 6.5, 0, 1.0, 7.7, 0.9),  # a desk
        (2.5, 7.4, 0, 3.4, 7.8, 2.2),
        (2.8, 5.0, 0, 3.2, 5.4, 0.45),
    ]
    return boxes


def scene():
    """The Open3D ray-casting scene of the flat."""
    import open3d as o3d

    rays = o3d.t.geometry.RaycastingScene()
    meshes = []
    for x0, y0, z0, x1, y1, z1 in _boxes():
        meshes.append(o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0).translate((x0, y0, z0)))
    for x, y, radius, height in ((3.0, 0.8, 0.25, 0.9), (5.0, 3.0, 0.15, 1.1), (7.2, 5.0, 0.3, 0.6), (1.2, 4.8, 0.2, 1.4)):
        meshes.append(o3d.geometry.TriangleMesh.create_cylinder(radius, height, 24).translate((x, y, height / 2)))
    for mesh in meshes:
        rays.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return rays


def views(count: int, pixels: int = 160, seed: int = 0, noise: float = RANGE_NOISE, rays=None) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """`count` depth views around the loop, each (N_k, 3) in metres in its camera's frame (x right,
    y down, z forward), with `noise` m of Gaussian noise along each ray, and their (4, 4)
    world_T_camera poses."""
    import open3d as o3d

    rays = scene() if rays is None else rays
    rng = np.random.default_rng(seed)
    width, height = pixels, pixels * 3 // 4
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    fx, fy = (width / 2) / np.tan(np.radians(30)), (height / 2) / np.tan(np.radians(22.5))
    directions = np.stack([(u - width / 2) / fx, (v - height / 2) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    clouds, poses = [], []
    for k in range(count):
        a = -np.pi / 2 + 2 * np.pi * k / count
        centre = np.array([4 + 1.9 * np.cos(a), 4 + 1.9 * np.sin(a), 1.4 + 0.05 * np.sin(3 * a)])
        yaw, pitch = a + np.pi / 2 + np.radians(25), np.radians(-10)
        forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
        pose[:3, 3] = centre
        cast = np.hstack([np.tile(centre, (len(directions), 1)), directions @ pose[:3, :3].T]).astype(np.float32)
        hit = rays.cast_rays(o3d.core.Tensor(cast))["t_hit"].numpy().astype(np.float64)
        seen = np.isfinite(hit)
        depth = hit[seen] + rng.normal(0.0, noise, seen.sum())
        clouds.append(directions[seen] * depth[:, None])
        poses.append(pose)
    return clouds, poses


def pose_errors(estimated: Sequence[Optional[np.ndarray]], truth: Sequence[np.ndarray]) -> List[Optional[Tuple[float, float]]]:
    """Per view, (rotation error in degrees, translation error in metres) of its pose relative to
    the first view's, against the truth; None where it has no pose."""
    from o3dsoft.metrics import pair_errors

    first = estimated[0]
    errors: List[Optional[Tuple[float, float]]] = []
    for pose, true in zip(estimated, truth):
        if pose is None or first is None:
            errors.append(None)
            continue
        e = pair_errors(np.linalg.inv(first) @ pose, np.linalg.inv(truth[0]) @ true)
        errors.append((e.rotation_deg, e.translation))
    return errors


def measure(count: int, pixels: int, noise: float, seed: int, model) -> dict:
    """multiway on `count` views: pose errors, trusted edges that are wrong, time."""
    import o3dsoft

    clouds, truth = views(count, pixels, seed, noise)
    result = o3dsoft.multiway(clouds, model=model)
    errors = pose_errors(result.poses, truth)
    placed = [e for e in errors if e is not None]
    wrong_edges = 0
    for edge in result.edges:
        true = np.linalg.inv(truth[edge.target]) @ truth[edge.source]
        e = o3dsoft.pair_errors(edge.transformation, true)
        wrong_edges += (not edge.likely_failed) and (e.rotation_deg > 2 or e.translation > 0.1)
    return {
        "views": count,
        "points_per_view": int(np.median([len(c) for c in clouds])),
        "joined": int(sum(result.joined)),
        "wrong_views": sum(1 for e in placed if e[0] > 2 or e[1] > 0.1),
        "rotation_error_deg_max": max(e[0] for e in placed),
        "rotation_error_deg_median": float(np.median([e[0] for e in placed])),
        "translation_error_m_max": max(e[1] for e in placed),
        "translation_error_m_median": float(np.median([e[1] for e in placed])),
        "edges": len(result.edges),
        "trusted_edges": sum(not e.likely_failed for e in result.edges),
        "trusted_wrong_edges": int(wrong_edges),
        "pruned_edges": sum(e.pruned for e in result.edges),
        "searched_edges": sum(e.searched for e in result.edges),
        "seconds": result.timings_s["total"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, nargs="+", default=[12, 24])
    parser.add_argument("--pixels", type=int, default=160)
    parser.add_argument("--noise", type=float, default=RANGE_NOISE, help="range noise (m, standard deviation)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    from o3dsoft.coarse import load_model

    model = load_model()
    rows = []
    for count in args.views:
        t0 = time.perf_counter()
        row = measure(count, args.pixels, args.noise, args.seed, model)
        rows.append(row)
        print(
            f"{count} views ({row['points_per_view']} points each): {row['joined']} joined, {row['wrong_views']} placed wrong; "
            f"pose error (lower is better) at most {row['rotation_error_deg_max']:.2f} deg and {row['translation_error_m_max']:.3f} m, "
            f"median {row['rotation_error_deg_median']:.2f} deg and {row['translation_error_m_median']:.3f} m; "
            f"edges {row['edges']}, trusted {row['trusted_edges']} ({row['trusted_wrong_edges']} of them wrong), pruned {row['pruned_edges']}, "
            f"searched {row['searched_edges']}; {row['seconds']:.1f} s multiway, {time.perf_counter() - t0:.1f} s in all (lower is better)",
            flush=True,
        )
    if args.out:
        args.out.write_text(json.dumps({"pixels": args.pixels, "noise": args.noise, "seed": args.seed, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
