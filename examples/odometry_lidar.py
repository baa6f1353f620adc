"""Track a spinning LiDAR through a yard: the poses of a sequence of sweeps with o3dsoft.odometry.

python examples/odometry_lidar.py

A 16-ring sensor 1.8 m over the ground drives 0.8 m per sweep through a 60 x 40 m yard of
buildings, walls and posts, turning 2 degrees per sweep; 2 cm of range noise. Each sweep is in the
sensor's frame, as a LiDAR driver writes it. `o3dsoft.odometry` registers each onto a local map of
the sweeps before it and returns world_T_sweep for every sweep, with each step's confidence.
"""

import time

import numpy as np
import open3d as o3d

import o3dsoft
from o3dsoft.odometry import errors_against
from o3dsoft.transforms import euler_to_matrix, rigid


def yard() -> o3d.t.geometry.RaycastingScene:
    """The scene: the ground, four buildings, a long wall and a row of posts (metres)."""
    scene = o3d.t.geometry.RaycastingScene()
    boxes = [
        ((60.0, 40.0, 0.2), (-30.0, -20.0, -0.2)),  # the ground, its top at z = 0
        ((8.0, 6.0, 5.0), (6.0, 6.0, 0.0)),
        ((5.0, 9.0, 3.5), (-14.0, 4.0, 0.0)),
        ((10.0, 4.0, 7.0), (10.0, -12.0, 0.0)),
        ((6.0, 6.0, 4.0), (22.0, 2.0, 0.0)),
        ((40.0, 0.4, 2.0), (-20.0, -17.0, 0.0)),  # a wall along the yard
    ]
    boxes += [((0.3, 0.3, 3.0), (x, 2.5, 0.0)) for x in np.arange(-20.0, 20.0, 6.0)]  # posts
    for size, corner in boxes:
        box = o3d.geometry.TriangleMesh.create_box(*size).translate(corner)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    return scene


def sweep(scene: o3d.t.geometry.RaycastingScene, world_T_sensor: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) returns of 16 rings (-15 to +15 degrees), 0.2 degrees apart in azimuth, up to 60 m,
    in the sensor's frame."""
    azimuth, elevation = np.meshgrid(np.radians(np.arange(0.0, 360.0, 0.2)), np.radians(np.linspace(-15.0, 15.0, 16)))
    rays = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1).reshape(-1, 3)
    world = rays @ world_T_sensor[:3, :3].T
    origin = np.broadcast_to(world_T_sensor[:3, 3], world.shape)
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origin, world]).astype(np.float32)))["t_hit"].numpy()
    seen = np.isfinite(hit) & (hit < 60.0)
    return rays[seen] * (hit[seen] + rng.normal(0.0, 0.02, seen.sum()))[:, None]


def main() -> None:
    rng = np.random.default_rng(0)
    scene = yard()
    step = rigid(euler_to_matrix([0.0, 0.0, 2.0]), np.array([0.8, 0.0, 0.0]))  # the sensor's motion per sweep
    truth = [rigid(np.eye(3), np.array([-16.0, -6.0, 1.8]))]
    for _ in range(14):
        truth.append(truth[-1] @ step)
    sweeps = [sweep(scene, pose, rng) for pose in truth]

    start = time.perf_counter()
    result = o3dsoft.odometry(sweeps, names=[f"sweep{k:02d}" for k in range(len(sweeps))])
    seconds = time.perf_counter() - start

    errors = errors_against(result, truth)  # each step against the true motion, and the drift
    print(f"{len(sweeps)} sweeps of about {np.median([len(s) for s in sweeps]):.0f} points, {seconds / (len(sweeps) - 1):.2f} s per sweep (lower is better)")
    print("step errors (lower is better):")
    for k, (deg, metres, flagged) in enumerate(zip(errors.rotation_deg, errors.translation, result.flagged[1:]), start=1):
        print(f"  sweep{k:02d}: {deg:.3f} deg, {100 * metres:.1f} cm, confidence {result.steps[k].confidence:.3f}{' (flagged)' if flagged else ''}")
    print(
        f"path {errors.path:.2f} m; the last sweep ends {100 * errors.drift.translation:.1f} cm and {errors.drift.rotation_deg:.2f} deg from its pose (drift, lower is better)"
    )


if __name__ == "__main__":
    main()
