"""Registration errors against a ground truth: one definition for register, bench, train and tests.

Transforms are (4, 4) arrays T_target_source (p_target = R p_source + t). Every error is >= 0 and
lower is better. Angles are in degrees, translations in the units of the clouds.
"""

from __future__ import annotations

import math
from typing import Dict, NamedTuple, Optional

import numpy as np

from .errors import InputError
from .transforms import apply_transform, in_frame_at, matrix_to_euler_deg, rotation_angle_deg


def _as_transform(T: np.ndarray, name: str = "transform") -> np.ndarray:
    """T as a (4, 4) float64 array. InputError naming `name` for any other shape, and for a finite
    one whose 3x3 block is no rotation (|R^T R - I| over 0.01, or a reflection): its errors would
    mean nothing. A non-finite one (a method that failed) is let through: its errors are NaN or
    180 degrees."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"{name}: expected a (4, 4) transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.isfinite(T).all() and (np.abs(R.T @ R - np.eye(3)).max() > 0.01 or np.linalg.det(R) < 0):
        raise InputError(f"{name}: not a rigid transform (its 3x3 block is no rotation)")
    return T


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Isotropic rotation error: the angle of R_gt^T R_est, in degrees (accurate near 0)."""
    return rotation_angle_deg(np.asarray(R_gt, np.float64).T @ np.asarray(R_est, np.float64))


class PairErrors(NamedTuple):
    """Errors of one estimate against its ground truth (all: lower is better).

    rotation_deg: isotropic rotation error (degrees). translation: ||t_est - t_gt|| (cloud units).
    rotation_l1, rotation_l2: entrywise L1 and Frobenius norms of R_est - R_gt (the paper's tables).
    translation_l1, translation_l2: L1 and L2 norms of t_est - t_gt.
    euler_abs_deg: (3,) |Euler angle differences| (degrees, wrapped to [0, 180]), for DCP's MSE/MAE.
    translation_abs: (3,) |t_est - t_gt| per axis, for DCP's translation MSE/MAE.
    """

    rotation_deg: float
    translation: float
    rotation_l1: float
    rotation_l2: float
    translation_l1: float
    translation_l2: float
    euler_abs_deg: np.ndarray
    translation_abs: np.ndarray


def _euler_differences(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """(3,) |Euler angle differences| (degrees, wrapped to [0, 180]) of two rotations, DCP's; where
    both middle angles b lie within ``LOCK_DEG`` of +-90 degrees, of the estimate's two Euler
    triples (a, b, c) and (a + 180, 180 - b, c + 180), which make the same rotation, the one
    nearer the truth's: there the triple the angles' formula picks flips to the other for a turn
    of a fraction of a degree."""
    first = matrix_to_euler_deg(R_est)
    truth = matrix_to_euler_deg(R_gt)
    triples = [first]
    if min(abs(first[1]), abs(truth[1])) > 90.0 - LOCK_DEG:
        triples.append(first * [1.0, -1.0, 1.0] + [180.0, 180.0, 180.0])
    wrapped = [np.abs((e - truth + 180.0) % 360.0 - 180.0) for e in triples]
    return min(wrapped, key=lambda d: float(np.sum(d**2)))


LOCK_DEG = 10.0  # middle Euler angles within this of +-90 degrees are near the gimbal lock


def pair_errors(T_est: np.ndarray, T_gt: np.ndarray, origin: Optional[np.ndarray] = None) -> PairErrors:
    """All per-pair errors of the literature's protocols for one estimate (4, 4) against the truth
    (4, 4). `origin` (3,): the translation errors of both moved to a frame there (t + R o - o), for
    clouds far from their own frame's origin (georeferenced scans: a turn of 0.1 degrees about the
    origin moves a cloud 4e6 m away by 7 km; :func:`o3dsoft.preprocess.local_origin`)."""
    T_est, T_gt = _as_transform(T_est, "T_est"), _as_transform(T_gt, "T_gt")
    if origin is not None and np.any(origin):
        T_est, T_gt = in_frame_at(T_est, origin), in_frame_at(T_gt, origin)
    R_e, t_e = T_est[:3, :3], T_est[:3, 3]
    R_g, t_g = T_gt[:3, :3], T_gt[:3, 3]
    dR = R_e - R_g
    dt = t_e - t_g
    de = _euler_differences(R_e, R_g)
    return PairErrors(
        rotation_deg=rotation_error_deg(R_e, R_g),
        translation=float(np.linalg.norm(dt)),
        rotation_l1=float(np.abs(dR).sum()),
        rotation_l2=float(np.linalg.norm(dR)),
        translation_l1=float(np.abs(dt).sum()),
        translation_l2=float(np.linalg.norm(dt)),
        euler_abs_deg=de,
        translation_abs=np.abs(dt),
    )


def modified_chamfer_distance(
    source: np.ndarray,
    target: np.ndarray,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    clean_target: Optional[np.ndarray] = None,
) -> float:
    """RPM-Net's modified Chamfer distance (squared distances, cloud units^2; lower is better).

    mean_p min_q* ||T_est p - q*||^2 + mean_q min_p* ||q - T_est T_gt^-1 q*||^2, where q* runs over
    the clean, complete target (`clean_target`, default `target`) so that a crop or noise in the
    inputs does not count against an exact estimate.

    Args:
        source: (N, 3); target: (M, 3); clean_target: (L, 3) in the target frame.
    """
    clean = target if clean_target is None else clean_target
    T_est = _as_transform(T_est)
    src_est = apply_transform(T_est, np.asarray(source, np.float64))
    T_rel = T_est @ np.linalg.inv(np.asarray(T_gt, np.float64))
    clean_moved = apply_transform(T_rel, np.asarray(clean, np.float64))
    return _mean_squared_nearest(src_est, clean) + _mean_squared_nearest(np.asarray(target, np.float64), clean_moved)


def input_chamfer_distance(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> float:
    """How well `T` fits the two clouds as given (squared distances, cloud units^2; lower is
    better): mean_p min_q ||T p - q||^2 + mean_q min_p ||q - T p||^2 over the input points only,
    so, unlike :func:`modified_chamfer_distance`, it measures nothing a method could not see.

    Args:
        source: (N, 3); target: (M, 3); T: (4, 4) T_target_source.
    """
    moved = apply_transform(_as_transform(T), np.asarray(source, np.float64))
    target = np.asarray(target, np.float64)
    return _mean_squared_nearest(moved, target) + _mean_squared_nearest(target, moved)


def _mean_squared_nearest(points: np.ndarray, cloud: np.ndarray) -> float:
    """Mean over the (N, 3) `points` of the squared distance to the nearest point of the (M, 3) `cloud`."""
    from scipy.spatial import cKDTree  # noqa: WPS433 - optional, only metrics need it

    d, _ = cKDTree(cloud).query(points)
    return float(np.mean(d**2))


MODELNET_RECALL = ((1.0, 0.01), (2.0, 0.02), (5.0, 0.05))


def within(rotation_deg, translation, threshold: "tuple") -> np.ndarray:
    """Success at one recall threshold (degrees, cloud units): both errors below it; works
    elementwise on arrays of errors."""
    deg, dist = threshold
    return (np.asarray(rotation_deg) < deg) & (np.asarray(translation) < dist)


def summarise(errors: "list[PairErrors]", recall: "tuple" = MODELNET_RECALL) -> Dict[str, float]:
    """Summary over pairs: DCP's Euler/translation MSE, RMSE, MAE; isotropic mean/median; recall.

    Recall is the share of pairs (0-1, higher is better) within both thresholds of each entry of
    `recall` ((degrees, cloud units)); by default rotation error < 1 degree and translation error
    < 0.01 (``recall_1deg``), < 2 degrees and < 0.02 (``recall_2deg``), and < 5 degrees and < 0.05
    (``recall_5deg``), for ModelNet40's radius-1 shapes.
    """
    if not errors:
        return {}
    rot = np.array([e.rotation_deg for e in errors])
    trans = np.array([e.translation for e in errors])
    eul = np.stack([e.euler_abs_deg for e in errors])
    tab = np.stack([e.translation_abs for e in errors])
    return {
        "pairs": len(errors),
        "rotation_deg_mean": float(rot.mean()),
        "rotation_deg_median": float(np.median(rot)),
        "translation_mean": float(trans.mean()),
        "translation_median": float(np.median(trans)),
        "euler_mse_deg2": float(np.mean(eul**2)),
        "euler_rmse_deg": float(math.sqrt(np.mean(eul**2))),
        "euler_mae_deg": float(np.mean(eul)),
        "translation_mse": float(np.mean(tab**2)),
        "translation_rmse": float(math.sqrt(np.mean(tab**2))),
        "translation_mae": float(np.mean(tab)),
        "rotation_l1_mean": float(np.mean([e.rotation_l1 for e in errors])),
        "rotation_l2_mean": float(np.mean([e.rotation_l2 for e in errors])),
        "translation_l1_mean": float(np.mean([e.translation_l1 for e in errors])),
        "translation_l2_mean": float(np.mean([e.translation_l2 for e in errors])),
        **{f"recall_{deg:g}deg": float(np.mean(within(rot, trans, (deg, dist)))) for deg, dist in recall},
    }
