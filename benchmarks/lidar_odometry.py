"""Odometry on ray-cast LiDAR sequences: the drift of ``o3dsoft.odometry`` for local maps of
several sizes, on sweeps of 32, 16 and 8 rings.

    python -m benchmarks.lidar_odometry [--data DIR] [--sequences 4] [--sweeps 25]
        [--rings 32 16 8] [--map-sweeps 1 5 10] [--out FILE.json]

The scene: the two scans of ``real_scans/outdoor_laser_car`` joined by their reference transform
and meshed (Open3D's Poisson reconstruction, depth 10, trimmed where no scan point lies within
0.8 m). Each sequence starts at the same place and heading with its own seed: the sensor rides
1.8 m over the ground plane (a RANSAC fit), moves 0.5-2.0 m per sweep and turns up to 4 degrees
about the vertical. A sweep: rings from -25 to +15 degrees of elevation (32; 16 and 8 keep every
2nd and 4th), 0.2 degrees between rays, 2 cm range noise, returns from 1 to 60 m, in the
sensor's frame. Errors against the poses the sweeps were cast from: a step (a sweep's pose
relative to the previous one's) is wrong beyond 1 degree or 0.3 m. Run it alone on the machine:
the times are medians of its own run.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_scans" / "outdoor_laser_car"


def scene(folder: Path):
    """The Open3D ray-casting scene of the two laser scans' mesh, and the ground plane (a, b, c, d)."""
    import open3d as o3d

    import o3dsoft

    source, target = o3dsoft.read_points(folder / "car_cloud401.ply"), o3dsoft.read_points(folder / "car_cloud400.ply")
    truth = o3dsoft.read_transform(folder / "gt_401_to_400.txt")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack([target, o3dsoft.transforms.apply_transform(truth, source)])))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.0, max_nn=30))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=10, n_threads=1)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.15))
    from scipy.spatial import cKDTree

    near, _ = cKDTree(np.asarray(cloud.points)).query(np.asarray(mesh.vertices), distance_upper_bound=0.8)
    mesh.remove_vertices_by_mask(~np.isfinite(near))
    rays = o3d.t.geometry.RaycastingScene()
    rays.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    o3d.utility.random.seed(0)
    plane, _ = cloud.segment_plane(distance_threshold=0.2, ransac_n=3, num_iterations=2000)
    plane = np.asarray(plane) * (1 if plane[2] > 0 else -1)
    return rays, plane


def sequence(rays, plane: np.ndarray, rings: int, sweeps: int, seed: int):
    """`sweeps` (N_k, 3) sweeps of `rings` rings (every 32/rings-th of 32) and their (4, 4)
    world_T_sensor poses."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(-25.0, 15.0, 32)[:: 32 // rings])
    azimuth = np.radians(np.arange(0.0, 360.0, 0.2))
    E, A = np.meshgrid(elevation, azimuth, indexing="ij")
    directions = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    position, heading = np.array([-8.0, -6.0, 0.0]), np.radians(35.0)
    clouds, poses = [], []
    for _ in range(sweeps):
        a, b, c, d = plane
        position[2] = -(a * position[0] + b * position[1] + d) / c + 1.8
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(heading), -np.sin(heading), 0.0], [np.sin(heading), np.cos(heading), 0.0], [0.0, 0.0, 1.0]]
        pose[:3, 3] = position
        world = directions @ pose[:3, :3].T
        cast = np.hstack([np.repeat(position[None], len(world), axis=0), world]).astype(np.float32)
        hit = rays.cast_rays(o3d.core.Tensor(cast))["t_hit"].numpy().astype(np.float64)
        keep = np.isfinite(hit) & (hit > 1.0) & (hit < 60.0)
        clouds.append(directions[keep] * (hit[keep] + 0.02 * rng.standard_normal(keep.sum()))[:, None])
        poses.append(pose)
        heading += np.radians(rng.uniform(-4.0, 4.0))
        position = position + rng.uniform(0.5, 2.0) * np.array([np.cos(heading), np.sin(heading), 0.0])
    return clouds, poses


def measure(clouds: List[np.ndarray], truth: List[np.ndarray], map_sweeps: int, model) -> dict:
    """One odometry run: its step errors, final drift, wrong and trusted-wrong steps, flagged steps
    and those of them left out of the local maps, time per sweep."""
    import o3dsoft
    from o3dsoft.odometry import errors_against

    start = time.perf_counter()
    result = o3dsoft.odometry(clouds, o3dsoft.OdometryConfig(map_sweeps=map_sweeps), model=model)
    seconds = (time.perf_counter() - start) / (len(clouds) - 1)
    rotation, translation, drift, path = errors_against(result, truth)
    wrong, flagged = (rotation > 1.0) | (translation > 0.3), np.array(result.flagged[1:])
    return {
        "path_m": path,
        "step_rotation_deg_median": float(np.median(rotation)),
        "step_translation_m_median": float(np.median(translation)),
        "drift_m": drift.translation,
        "wrong": int(wrong.sum()),
        "trusted_wrong": int((wrong & ~flagged).sum()),
        "flagged": int(flagged.sum()),
        "left_out_of_map": int(sum(not kept for kept in result.mapped)),
        "seconds_per_sweep": seconds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--sweeps", type=int, default=25)
    ap.add_argument("--rings", type=int, nargs="+", default=[32, 16, 8], choices=[32, 16, 8, 4])
    ap.add_argument("--map-sweeps", type=int, nargs="+", default=[1, 5, 10])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.sequences < 1 or args.sweeps < 2 or min(args.map_sweeps) < 1:
        ap.error("--sequences and --map-sweeps must be at least 1, --sweeps at least 2")
    import o3dsoft

    model = o3dsoft.load_model()
    rays, plane = scene(args.data)
    rows = []
    print(
        "rings  map  drift per sequence (m)        step error median (deg / cm)  wrong  trusted wrong  ms per sweep (median)   (all lower is better)",
        flush=True,
    )
    for rings in args.rings:
        runs = [sequence(rays, plane, rings, args.sweeps, seed) for seed in range(args.sequences)]
        for size in args.map_sweeps:
            found = [measure(clouds, truth, size, model) for clouds, truth in runs]
            rows.append({"rings": rings, "map_sweeps": size, "sequences": found})
            drift = " ".join(f"{r['drift_m']:5.2f}" for r in found)
            print(
                f"{rings:5d} {size:4d}  {drift:29s} {np.median([r['step_rotation_deg_median'] for r in found]):6.3f} / "
                f"{100 * np.median([r['step_translation_m_median'] for r in found]):4.1f}            "
                f"{sum(r['wrong'] for r in found):5d}  {sum(r['trusted_wrong'] for r in found):13d}  "
                f"{1000 * np.median([r['seconds_per_sweep'] for r in found]):8.0f}",
                flush=True,
            )
    if args.out is not None:
        args.out.write_text(
            json.dumps({"command": "python -m benchmarks.lidar_odometry", "args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=2)
        )


if __name__ == "__main__":
    main()
