"""Register the bundled pair of real Stanford Bunny scans and compare with the ground truth.

    python examples/register_pair.py

The two scans were taken about 35 degrees apart and overlap partly; the ground truth comes from
the scanner's bun.conf.
"""

from pathlib import Path

import o3dsoft

DATA = Path(__file__).resolve().parent / "data"


def main() -> None:
    source = o3dsoft.read_points(DATA / "bun045.ply")
    target = o3dsoft.read_points(DATA / "bun000.ply")
    T_gt = o3dsoft.read_transform(DATA / "bun045_to_bun000.txt")

    result = o3dsoft.register(source, target)

    coarse = o3dsoft.pair_errors(result.coarse_transformation, T_gt)
    final = o3dsoft.pair_errors(result.transformation, T_gt)
    print(f"source {len(source)} points, target {len(target)} points")
    print(f"network alone : rotation error {coarse.rotation_deg:7.3f} deg, translation error {coarse.translation * 1000:7.3f} mm (lower is better)")
    print(f"network + ICP : rotation error {final.rotation_deg:7.3f} deg, translation error {final.translation * 1000:7.3f} mm (lower is better)")
    print(f"fitness {result.fitness:.3f} (higher is better), inlier RMSE {result.inlier_rmse * 1000:.3f} mm (lower is better)")
    print("time per stage (ms, lower is better): " + ", ".join(f"{k} {v:.1f}" for k, v in result.timings_ms.items()))


if __name__ == "__main__":
    main()
