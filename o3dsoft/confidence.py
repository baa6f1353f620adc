"""How much to trust a registration: a confidence in [0, 1] and a ``likely_failed`` flag.

A wrong alignment (ICP stuck in a local minimum, a flipped shape, two unrelated clouds) still has
many source points near *some* target point at ICP's loose distance d, but fewer of them close at
a tight one; a right alignment of two partial clouds has points with no partner at all (far from
the target), while those in the overlap are close. The confidence is a logistic function of one
scale-free measurement of the final alignment that overlap does not change:

``consistency``: of the source points with a target point within d, the share with one within the
tight distance max(0.3 d, 1.5 s), where d is the ICP correspondence distance (0.1 x the pair's
scale by default) and s the target's median point spacing (distance to the nearest other target
point). When the target is much sparser than the source (spacing over 1.5 times the source's),
the roles swap: target points near the source are counted, so that a sparse cloud does not read
as a failure (a dense cloud's points cannot all be close to a sparse cloud's).

The measurement used before, ``fitness_tight`` (the share of *all* source points within the tight
distance, still reported), confused overlap with failure: on the first 300 `rpmnet-crop` test
pairs its area under the ROC curve was 0.773, against 0.991 for ``consistency`` (0.834 and 0.985
on `so3-crop`), measured on the same final alignments.

The coefficients were fitted by ``python -m benchmarks.fit_confidence`` (logistic regression) on
ModelNet40 *train* pairs of the protocols dcp, so3, rpmnet-crop and so3-crop, plus pairs of
unrelated shapes, sparse targets and small parts of a shape (60 pairs per group, the shipped
model + ICP); success there means a rotation error below 5 degrees and a translation error below
0.05 x scale. On the held-out half (210 pairs) the area under the ROC curve was 0.999 and 99.0 %
of pairs were flagged correctly. The confidence reads as the estimated probability that the
alignment is right; below 0.5 (consistency below 0.87) the result is flagged ``likely_failed``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import refine as refine_stage

# Fitted by benchmarks/fit_confidence.py (see the module docstring for the data).
INTERCEPT = -41.92
SLOPE = 48.20
TIGHT = 0.3
SPACINGS = 1.5
LIKELY_FAILED_BELOW = 0.5


class Features(NamedTuple):
    """fitness_tight: share of the (denser) source's points within `tight_distance` of a target
    point, or of a much sparser target's points near the source (0-1, higher is better);
    tight_distance: max(0.3 d, 1.5 x the point spacing of the cloud they are compared with);
    consistency: of the same points within d of the other cloud, the share within the tight
    distance (0-1, higher is better; 0 when none is within d)."""

    fitness_tight: float
    tight_distance: float
    consistency: float


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest other point of the same (N, 3) cloud."""
    return float(np.median(np.asarray(refine_stage.to_open3d(points).compute_nearest_neighbor_distance())))


def features(source: np.ndarray, target: np.ndarray, transformation: np.ndarray, distance: float,
             max_points: int = refine_stage.ICPConfig.max_points) -> Features:
    """The measurement of an alignment that the confidence is built from.

    Args:
        source: (N, 3); target: (M, 3); transformation: (4, 4) T_target_source.
        distance: d, the correspondence distance of the fine stage (cloud units).
        max_points: clouds above this size are voxel-downsampled first, as in ICP.
    """
    source = refine_stage.downsample(np.asarray(source, dtype=np.float64), max_points)
    target = refine_stage.downsample(np.asarray(target, dtype=np.float64), max_points)
    s_source, s_target = point_spacing(source), point_spacing(target)
    if s_target > SPACINGS * s_source:  # sparse target: ask which target points the source covers
        tight = max(TIGHT * distance, SPACINGS * s_source)
        near, far, T = target, source, np.linalg.inv(transformation)
    else:
        tight = max(TIGHT * distance, SPACINGS * s_target)
        near, far, T = source, target, transformation
    scored = refine_stage.evaluate(near, far, T, tight, max_points)
    loose = refine_stage.evaluate(near, far, T, max(distance, tight), max_points)
    return Features(scored.fitness, tight, scored.fitness / loose.fitness if loose.fitness > 0 else 0.0)


def confidence(f: Features) -> float:
    """Estimated probability (0-1, higher is better) that the alignment is right."""
    return 1.0 / (1.0 + math.exp(-(INTERCEPT + SLOPE * f.consistency)))
