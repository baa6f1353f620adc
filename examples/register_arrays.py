"""Register NumPy arrays: move a ModelNet-like shape by a known transform and recover it.

python examples/register_arrays.py
"""

import numpy as np

import o3dsoft
from o3dsoft.transforms import euler_to_matrix


def main() -> None:
    rng = np.random.default_rng(0)
    # A closed, non-symmetric surface: an ellipsoid with a bump, 5,000 points, in millimetres.
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    source = d * [60.0, 35.0, 20.0] + 15.0 * np.exp(-8 * np.sum((d - [0.6, 0.6, 0.5]) ** 2, axis=1))[:, None] * d

    T_gt = np.eye(4)
    T_gt[:3, :3] = euler_to_matrix(np.array([20.0, -15.0, 30.0]))
    T_gt[:3, 3] = [12.0, -7.0, 30.0]
    target = source @ T_gt[:3, :3].T + T_gt[:3, 3]
    target = target[rng.permutation(len(target))]

    result = o3dsoft.register(source, target)
    err = o3dsoft.pair_errors(result.transformation, T_gt)
    np.set_printoptions(precision=5, suppress=True)
    print("estimated T_target_source (translation in mm):\n", result.transformation)
    print(f"rotation error {err.rotation_deg:.2e} deg, translation error {err.translation:.2e} mm (lower is better)")
    print(
        f"fitness {result.fitness:.3f} (higher is better), confidence {result.confidence:.3f} (0-1, higher is better)"
        + (" - likely failed" if result.likely_failed else "")
    )


if __name__ == "__main__":
    main()
