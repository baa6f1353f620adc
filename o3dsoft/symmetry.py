"""Whether a symmetric copy of the result fits as closely. Two independent samplings of a shape
with a symmetry (a vase, a box, a table) fit about as well at the shape's turned copies as at the
truth, and nothing measured on the two clouds tells them apart: the result is then ambiguous, and
its confidence is shared between the two poses (halved) rather than trusted.

The probe: the result's pose followed by a half turn of the moved source about each of its
principal axes through its centroid (the symmetries of most such shapes), each refined by ICP;
the copy that ends at least ``min_away_deg`` from the result with the lowest input Chamfer distance
(:func:`o3dsoft.metrics.input_chamfer_distance`) is compared with the result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, NamedTuple, Optional

import numpy as np

from . import search as search_stage
from .metrics import input_chamfer_distance
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
    """

    enabled: bool = True
    max_ratio: float = 1.1
    min_away_deg: float = 20.0


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
