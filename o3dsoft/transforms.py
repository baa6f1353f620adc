"""Rotations and rigid transforms: conversions and helpers shared by every module.

Conventions: a transform is a (4, 4) float64 array T_target_source, p_target = R p_source + t.
"""

from __future__ import annotations

import math
from typing import List, Optional

import numpy as np


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The (4, 4) float64 transform of a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def nearest_rigid(T: np.ndarray, centre: Optional[np.ndarray] = None, keep_within: float = 1e-9) -> np.ndarray:
    """(4, 4) float64 rigid transform nearest (4, 4) or (3, 4) `T`: its rotation block R replaced
    by the nearest rotation R' (Frobenius norm; SVD), the translation changed so that the (3,)
    point `centre` goes where `T` takes it (t' = t + (R - R') centre: far from the origin a turn
    of 1e-7 would move the points; None: the origin), the last row exact. Products of float32
    network rotations are orthonormal only to about 1e-7; projected, R R^T = I to float64
    precision. A rotation whose R R^T is within `keep_within` of I (float64 products) is kept."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    if not (np.abs(R @ R.T - np.eye(3)).max() <= keep_within and np.linalg.det(R) > 0):
        U, _, Vt = np.linalg.svd(R)
        if np.linalg.det(U @ Vt) < 0:
            U[:, -1] = -U[:, -1]
        R = U @ Vt
    shift = np.zeros(3) if centre is None else (T[:3, :3] - R) @ np.asarray(centre, dtype=np.float64)
    return rigid(R, T[:3, 3] + shift)


def in_frame_at(T: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) T seen in a frame whose origin lies at (3,) `origin` of T's frame (axes unchanged):
    the same rotation, the translation t + R o - o."""
    T = np.array(T, dtype=np.float64)
    T[:3, 3] += T[:3, :3] @ origin - origin
    return T


def axis_angle_to_matrix(omega: np.ndarray) -> np.ndarray:
    """(3, 3) rotation by |omega| radians about omega (3,) (Rodrigues); the identity for 0."""
    omega = np.asarray(omega, dtype=np.float64)
    angle = float(np.linalg.norm(omega))
    if angle == 0.0:
        return np.eye(3)
    k = omega / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


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
    """The angle of a (3, 3) rotation matrix, in degrees (0-180).

    Computed as 2 asin(||R - I||_F / (2 sqrt 2)), the same angle as the textbook
    arccos((tr R - 1) / 2) but accurate near 0, where arccos cannot resolve angles below ~0.02
    degrees in float32.
    """
    d = np.linalg.norm(np.asarray(R, np.float64) - np.eye(3))
    return math.degrees(2.0 * math.asin(min(1.0, d / (2.0 * math.sqrt(2.0)))))


def rotations_within(R: np.ndarray, R0: np.ndarray, degrees: float) -> np.ndarray:
    """Which rotations R (H, 3, 3) lie within `degrees` of R0 (3, 3): (H,) bool."""
    cos = (np.einsum("ij,hij->h", R0, R) - 1.0) / 2.0  # cos of the angle of R0^T R, from its trace
    return cos > np.cos(np.radians(degrees))


def near_poses(R: np.ndarray, moved: np.ndarray, R0: np.ndarray, moved0: np.ndarray, scale: float, degrees: float, shift: float) -> np.ndarray:
    """Which poses are one with a pose (R0 (3, 3), moved0 (3,)): within `degrees` in rotation
    (R (H, 3, 3)), and putting the source's centre (`moved` (H, 3), where each pose puts it)
    within `shift` x `scale` of `moved0`. Not compared by t, which depends on where the frame's
    origin lies. (H,) bool."""
    return rotations_within(R, R0, degrees) & (np.linalg.norm(moved - moved0, axis=1) < shift * scale)


def first_of_each_pose(T: np.ndarray, centre: np.ndarray, scale: float, degrees: float, shift: float) -> List[int]:
    """Indices of the poses T (H, 4, 4), in order, less those one (:func:`near_poses`, the
    source's `centre` (3,) moved by each) with an earlier kept one."""
    moved = T[:, :3, :3] @ centre + T[:, :3, 3]
    first: List[int] = []
    for k in range(len(T)):
        if not near_poses(T[first, :3, :3], moved[first], T[k, :3, :3], moved[k], scale, degrees, shift).any():
            first.append(k)
    return first
