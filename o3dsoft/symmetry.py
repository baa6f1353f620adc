"""Whether a symmetric copy of the result fits as closely. Two independent samplings of a shape
with a symmetry (a vase, a box, a table) fit about as well at the shape's turned copies as at the
truth, and nothing measured on the two clouds tells them apart: the result is then ambiguous, and
its confidence is shared between the two poses (halved) rather than trusted.

The probe: the result's pose followed by a half turn of the moved source about each of its
principal axes through its centroid (the symmetries of most such shapes), each refined by ICP;
the copy that ends at least ``min_away_deg`` from the result with the lowest input Chamfer distance
(:func:`o3dsoft.metrics.input_chamfer_distance`) is compared with the result.

Two samplings of a dense object on a voxel grid look as if they shared points (the grid's
centroids of a box lie as close at a quarter turn as at the truth), so there the probe runs where
both clouds are closed surfaces (:func:`closed_share`): complete objects, not views or scenes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, NamedTuple, Optional

import numpy as np

from . import search as search_stage
from .metrics import input_chamfer_distance
from .preprocess import point_spacing, sample_indices
from .transforms import apply_transform, rigid, rotation_angle_deg


@dataclass(frozen=True)
class SymmetryConfig:
    """Settings of :func:`probe`.

    Attributes:
        enabled: probe trusted results of two complete-looking clouds whose pose shows no shared
            point (default True).
        max_ratio: a copy whose input Chamfer distance is at most this many times the result's
            fits as closely: the result is ambiguous and its confidence halved (at least 1,
            default 1.1).
        min_away_deg: a copy that ICP brings back within this many degrees of the result is the
            result, not a copy (degrees, default 20).
        closed_from: on a voxel grid, clouds whose :func:`closed_share` is at least this are closed
            surfaces, probed whatever their spacing ratio (in (0, 1]; default 0.95: closed
            objects measure 1.0, single views of an object 0.06-0.22, indoor and street scans
            0.18-0.74).
    """

    enabled: bool = True
    max_ratio: float = 1.1
    min_away_deg: float = 20.0
    closed_from: float = 0.95


class Symmetry(NamedTuple):
    """copy: (4, 4) T_target_source, the refined copy that fits closest, or None (not probed, or
    ICP brought every copy back to the result); fit: its input Chamfer distance over the
    result's (higher is better for the result; at most ``max_ratio``: ambiguous); away_deg: the
    rotation from the result to it (degrees); reason: why the result is ambiguous, in words, or
    None."""

    copy: Optional[np.ndarray]
    fit: Optional[float]
    away_deg: Optional[float]
    reason: Optional[str] = None

    @property
    def ambiguous(self) -> bool:
        """The copy fits as closely as the result (or closer)."""
        return self.reason is not None


NOT_PROBED = Symmetry(None, None, None)


def closed_share(points: np.ndarray, normals: np.ndarray, sample: int = 300, seed: int = 0, at_least: float = 0.0) -> float:
    """The share of (at most `sample` of) the (N, 3) `points` from which the line along the point's
    (N, 3) normal (sign arbitrary) meets the cloud again: some other point lies within 1.5 point
    spacings of the line, over 3 spacings away along it. 1 for a closed surface (the line into the
    enclosed volume leaves it through the surface); near 0 for one view of an object (the line in
    leaves through the unseen back) and low for scenes (a floor's normal meets no ceiling).
    Expects an even spacing (a voxel grid). Where the share cannot reach `at_least`, counting
    stops: the share of the points counted so far, under `at_least`."""
    points = np.asarray(points, np.float64)
    if len(points) < 3:
        return 0.0
    spacing = point_spacing(points)
    chosen = sample_indices(len(points), sample, seed)
    met = np.zeros(len(chosen), dtype=bool)
    for start in range(0, len(chosen), 64):  # (64, N) distances at a time
        rows = chosen[start : start + 64]
        offsets = points[None, :, :] - points[rows, None, :]
        along = np.einsum("mnk,mk->mn", offsets, normals[rows])
        across_sq = np.einsum("mnk,mnk->mn", offsets, offsets) - along**2
        met[start : start + len(rows)] = ((across_sq < (1.5 * spacing) ** 2) & (np.abs(along) > 3.0 * spacing)).any(axis=1)
        counted = start + len(rows)
        if counted - met[:counted].sum() > (1.0 - at_least) * len(chosen):  # too many missed already
            return float(met[:counted].mean())
    return float(met.mean())


def half_turns(source: np.ndarray, transformation: np.ndarray) -> List[np.ndarray]:
    """(4, 4) poses: `transformation` followed by a half turn of the moved (N, 3) `source` about
    each of its principal axes through its centroid, largest variance first."""
    moved = apply_transform(transformation, np.asarray(source, np.float64))
    centre = moved.mean(axis=0)
    return [rigid(R, centre - R @ centre) @ transformation for R in search_stage.half_turns(moved)]


def probe(
    source: np.ndarray,
    target: np.ndarray,
    transformation: np.ndarray,
    refine: Callable[[np.ndarray], np.ndarray],
    config: SymmetryConfig = SymmetryConfig(),
    admissible: Callable[[np.ndarray], bool] = lambda T: True,
) -> Symmetry:
    """The half-turned copy of `transformation` that fits the clouds closest, and whether it fits
    as closely as the result.

    Args:
        source: (N, 3); target: (M, 3), the clouds the copies are refined and compared on.
        transformation: (4, 4) T_target_source, the result.
        refine: ICP from a (4, 4) start to a (4, 4) pose on these clouds.
        config: thresholds.
        admissible: whether a (4, 4) pose is allowed (a rotation prior); other copies are not
            counted.
    """
    base = input_chamfer_distance(source, target, transformation)
    best = NOT_PROBED
    for start in half_turns(source, transformation):
        copy = refine(start)
        away = rotation_angle_deg(copy[:3, :3] @ transformation[:3, :3].T)
        if away < config.min_away_deg or not admissible(copy):
            continue
        fit = input_chamfer_distance(source, target, copy) / max(base, 1e-300)
        if best.fit is None or fit < best.fit:
            best = Symmetry(copy, fit, away, _reason(fit, away) if fit <= config.max_ratio else None)
    return best


def _reason(fit: float, away_deg: float) -> str:
    return (
        f"a copy of the result turned {away_deg:.0f} degrees fits the clouds {'closer' if fit < 1 else 'as closely'} "
        f"(input Chamfer distance {fit:.2f} times the result's): the shape is symmetric and the two poses cannot be "
        "told apart (the other is copy_transformation; max_rotation excludes it where the turn is known to be small)"
    )
