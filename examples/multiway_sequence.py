"""Join a sequence of scans whose poses come from drifting odometry: multiway with initial poses.

python examples/multiway_sequence.py

Six views of the bundled bunny scan, as a sensor moving around it would take them: each a
different random 60 % of the points with 0.5 mm of noise of its own (no two views share a point),
cut to the side that faces the sensor, in the sensor's frame.
The odometry gives each view's pose with an error that grows along the sequence (as dead
reckoning's does). `o3dsoft.multiway` registers the pairs from those poses and returns the poses
in the odometry's frame, corrected.
"""

from pathlib import Path

import numpy as np

import o3dsoft
from o3dsoft.transforms import euler_to_matrix, rigid

DATA = Path(__file__).resolve().parent / "data"


def main() -> None:
    rng = np.random.default_rng(0)
    shape = o3dsoft.read_points(DATA / "bun000.ply")  # metres
    centre = shape.mean(axis=0)
    views, truth, odometry = [], [], []
    drift = np.eye(4)
    for k in range(6):
        # The sensor turns 15 degrees about the vertical axis and moves 2 cm per step.
        world_T_view = rigid(euler_to_matrix([0.0, 15.0 * k, 0.0]), [0.02 * k, 0.0, 0.0])
        points = shape[rng.random(len(shape)) < 0.6]
        points = points + rng.normal(scale=0.0005, size=points.shape)
        facing = (points - centre) @ (world_T_view[:3, :3] @ [0.0, 0.0, 1.0])
        points = points[facing > np.quantile(facing, 0.25)]  # the side that faces the sensor
        views.append(o3dsoft.transforms.apply_transform(np.linalg.inv(world_T_view), points))
        truth.append(world_T_view)
        odometry.append(drift @ world_T_view)
        drift = rigid(euler_to_matrix(rng.uniform(-1.5, 1.5, 3)), rng.uniform(-0.003, 0.003, 3)) @ drift

    result = o3dsoft.multiway(views, names=[f"view{k}" for k in range(6)], init_poses=odometry)

    print("pose error of each view (lower is better): odometry -> multiway")
    for k in range(6):
        before = o3dsoft.pair_errors(odometry[k], truth[k])
        after = o3dsoft.pair_errors(result.poses[k], truth[k])
        print(
            f"  view{k}: rotation {before.rotation_deg:5.2f} -> {after.rotation_deg:5.2f} deg, "
            f"translation {1000 * before.translation:5.1f} -> {1000 * after.translation:5.1f} mm"
        )
    trusted = sum(e.used for e in result.edges)
    print(f"{sum(result.joined)} of 6 views joined; {trusted} of {len(result.edges)} pairs trusted; {result.timings_s['total']:.1f} s (lower is better)")


if __name__ == "__main__":
    main()
