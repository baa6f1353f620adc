"""Rotations and rigid transforms: conversions and helpers shared by every module.

Conventions: a transform is a (4, 4) float64 array T_target_source, p_target = R p_source + t.
"""

from __future__ import annotations

import math

import numpy as np


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The (4, 4) float64 transform of a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points mapped by a (4, 4) transform."""
    return points @ T[:3, :3].T + T[:3, 3]


def euler_to_matrix(angles_deg: np.ndarray) -> np.ndarray:
    """R = Rx(a) Ry(b) Rz(c) for angles (a, b, c) in degrees; (3,) -> (3, 3)."""
    a, b, c = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rx @ ry @ rz


def matrix_to_euler_deg(R: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) in degrees with R = Rx(a) Ry(b) Rz(c), as DCP reports them (its 'zyx')."""
    R = np.asarray(R, dtype=np.float64)
    b = math.asin(max(-1.0, min(1.0, R[0, 2])))
    a = math.atan2(-R[1, 2], R[2, 2])
    c = math.atan2(-R[0, 1], R[0, 0])
    return np.degrees([a, b, c])


def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion given as (x, y, z, w); normalised first."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation uniform on SO(3): the quaternion of a normalised 4-D Gaussian; (3, 3)."""
    x, y, z, w = rng.normal(size=4)
    return quaternion_to_matrix(x, y, z, w)


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees."""
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2))))
