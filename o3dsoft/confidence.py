"""How much to trust a registration: a confidence in [0, 1] and a ``likely_failed`` flag.

A wrong alignment (ICP stuck in a local minimum, a flipped shape, two unrelated clouds) still has
many source points near *some* target point at ICP's loose distance d, but fewer of them close at
a tight one; a right alignment of two partial clouds has points with no partner at all (far from
the target), while those in the overlap are close. The confidence is a logistic function of one
scale-free measurement of the final alignment that overlap does not change:

``consistency``: of the source points with a target point within d, the share with one within the
tight distance max(0.3 d, 1.5 s), where d is the ICP correspondence distance (0.1 x the pair's
scale by default) and s the target's median point spacing (distance to the nearest other target
point). A point whose nearest target point has a source point over three times closer is not
counted either way: it lies beyond the target's edge, where the target's last points are already
matched (partial overlap). On a wrong alignment the surfaces lie apart both ways, so no such
closer partner exists and the point counts against it. When the target is much sparser than the
source (spacing over 1.5 times the source's), the roles swap: target points near the source are
counted, so that a sparse cloud does not read as a failure (a dense cloud's points cannot all be
close to a sparse cloud's).

Measurements used before read partial overlap as failure: ``fitness_tight`` (the share of *all*
source points within the tight distance, still reported) had a ROC AUC of 0.773 on the first 300
`rpmnet-crop` test pairs, against 0.991 for the consistency without the edge rule. That version
still counted the band of points just beyond the other cloud's edge: right alignments of real
scans, whose overlap has long edges, scored 0.70-0.88 and were flagged (in a bench run on 38
bunny scan pairs, 23 of o3dsoft's 30 right alignments). With the edge rule, on the same 76 alignments (o3dsoft's and FPFH +
RANSAC + ICP's), the right ones score 0.94-1.0 and the wrong ones at most 0.77, but for four
near misses 1.9-2.3 degrees off (0.93).

An alignment that leaves the clouds barely touching (the counted points fewer than
``MIN_OVERLAP`` = 10 % of the smaller cloud) gets confidence 0: a handful of close points at the
rim of two unrelated clouds would otherwise read as a consistent fit. At 5 %, on the bunny scans
chin -> bun270, a voted translation at a half-turned rotation left 5.2 % of the points (on the
5,000-point work clouds) touching, was trusted at 0.99 over the right result (0.44), and came out
173 degrees off. Right alignments count far more: at least 0.18 on the 90 ordered bunny scan
pairs at their ground truth (all of them, also those under 30 % overlap), and at least 0.58 on
the right results of `rpmnet-crop` and `so3-crop` (benchcrop8).

The coefficients were fitted by logistic regression on ModelNet40 *train* pairs of the protocols
dcp, so3, rpmnet-crop and so3-crop, plus pairs of unrelated shapes, sparse targets and small parts
of a shape (60 pairs per group, the shipped model + ICP); success there means a rotation error
below 5 degrees and a translation error below 0.05 x scale. On the held-out half (210 pairs) the
area under the ROC curve was 0.998 and 98.1 % of pairs were flagged correctly (all 30 unrelated
pairs). The confidence reads as the estimated probability that the alignment is right; below 0.5
(consistency below 0.905) the result is flagged ``likely_failed``.

Two independent samplings of one surface (every pair of real scans) cannot reach a consistency of
1 at the right pose: a point's nearest partner in the other sampling lies about one point spacing
away, over 1.5 spacings for about a fifth of the points. On sparse clouds, whose spacing is close
to d, right alignments score about 0.85 and are flagged. ``spacing_ratio`` measures such pairs on
any density; it enters the logistic with weight 0 (``python -m benchmarks.fit_confidence`` fits
both weights; docs/incongruent.md says why that fit is not used).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from scipy.spatial import cKDTree

from . import refine as refine_stage
from .transforms import apply_transform

# The measurements the confidence is a logistic function of, and their coefficients (intercept
# first), fitted by benchmarks/fit_confidence.py (see the module docstring for the data).
FEATURE_NAMES = ("consistency", "spacing_ratio")
COEFFICIENTS = (-52.98, 58.54, 0.0)
# The spacing ratio enters the logistic capped here (no partner at all reads as this far apart).
RATIO_CAP = 5.0
# The spacing ratio looks for partners within this many point spacings when that reaches beyond d.
WIDE_SPACINGS = 3.0
TIGHT = 0.3
CLAIMED = 0.3
SPACINGS = 1.5
LIKELY_FAILED_BELOW = 0.5
# Fewer counted points than this share of the smaller cloud are too few to measure: an alignment
# that leaves the clouds barely touching (a few points each) is not trusted however close those are.
MIN_OVERLAP = 0.1


class Features(NamedTuple):
    """fitness_tight: share of the (denser) source's points within `tight_distance` of a target
    point, or of a much sparser target's points near the source (0-1, higher is better);
    tight_distance: max(0.3 d, 1.5 x the point spacing of the cloud they are compared with);
    consistency: of the same points within d of the other cloud, the share within the tight
    distance (0-1, higher is better; 0 when none is within d);
    overlap: the points the consistency counts, as a share of the smaller cloud (capped at 1;
    below :data:`MIN_OVERLAP` the confidence is 0);
    spacing_ratio: the median distance from a point to its nearest partner over the other
    cloud's median point spacing s (lower is better), over the points within max(d, 3 s) of the
    other cloud less those beyond its edge (as for the consistency): about 1 for two independent
    samplings of one surface at the right pose, 0 for identical point sets, above 1 when the
    surfaces lie apart. Unlike the consistency it keeps its meaning on sparse clouds, whose
    spacing is close to d (two independent samplings' nearest points lie about s apart)."""

    fitness_tight: float
    tight_distance: float
    consistency: float
    overlap: float
    spacing_ratio: float = 0.0


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest other point of the same (N, 3) cloud."""
    return float(np.median(np.asarray(refine_stage.to_open3d(points).compute_nearest_neighbor_distance())))


class Scorer:
    """:func:`features` of any number of alignments of one pair of clouds. What an alignment does
    not change (the downsampled clouds, their point spacings, which cloud is compared with which
    and its KD-tree) is computed once: the search scores up to a hundred estimates of a pair.

    Args:
        source: (N, 3); target: (M, 3).
        distance: d, the correspondence distance of the fine stage (cloud units).
        max_points: clouds above this size are voxel-downsampled first, as in ICP.
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, distance: float,
                 max_points: int = refine_stage.ICPConfig.max_points) -> None:
        source = refine_stage.downsample(np.asarray(source, dtype=np.float64), max_points)
        target = refine_stage.downsample(np.asarray(target, dtype=np.float64), max_points)
        s_source, s_target = point_spacing(source), point_spacing(target)
        # A sparse target: ask which target points the source covers.
        self.swapped = bool(s_target > SPACINGS * s_source)
        self.tight = max(TIGHT * distance, SPACINGS * (s_source if self.swapped else s_target))
        self.near, self.far = (target, source) if self.swapped else (source, target)
        self.far_tree = cKDTree(self.far)
        self.far_spacing = max(s_source if self.swapped else s_target, 1e-12)
        self.reach = max(distance, self.tight)
        self.wide_reach = max(self.reach, WIDE_SPACINGS * self.far_spacing)

    def __call__(self, transformation: np.ndarray) -> Features:
        """Features of the alignment by `transformation`, (4, 4) T_target_source."""
        T = np.linalg.inv(transformation) if self.swapped else transformation
        moved = apply_transform(T, self.near)
        dist, j = self.far_tree.query(moved, distance_upper_bound=self.wide_reach)
        reached = np.isfinite(dist)
        within = dist <= self.reach
        close = dist <= self.tight
        # A point whose nearest partner has a point of its own cloud over three times closer lies
        # beyond the other cloud's edge (partial overlap): it has no partner and is not counted. On a
        # wrong alignment the surfaces lie apart both ways, and no partner is claimed so.
        # Only the points reached but not close can go uncounted so; the others need no query.
        doubtful = reached & ~close
        claimed = np.zeros(len(moved), dtype=bool)
        if doubtful.any():
            claimed[doubtful] = cKDTree(moved).query(self.far[j[doubtful]])[0] <= CLAIMED * dist[doubtful]
        counted = close | (within & ~claimed)
        ratio_counted = close | (reached & ~claimed)
        spacing_ratio = float(np.median(dist[ratio_counted]) / self.far_spacing) if ratio_counted.any() else math.inf
        if not counted.any():
            return Features(float(close.mean()), self.tight, 0.0, 0.0, spacing_ratio)
        consistency = float(close.sum() / counted.sum())
        overlap = min(1.0, float(counted.sum()) / min(len(moved), len(self.far)))
        return Features(float(close.mean()), self.tight, consistency, overlap, spacing_ratio)


def features(source: np.ndarray, target: np.ndarray, transformation: np.ndarray, distance: float,
             max_points: int = refine_stage.ICPConfig.max_points) -> Features:
    """The measurement of an alignment that the confidence is built from (for several alignments
    of one pair, :class:`Scorer` computes what they share once).

    Args:
        source: (N, 3); target: (M, 3); transformation: (4, 4) T_target_source.
        distance: d, the correspondence distance of the fine stage (cloud units).
        max_points: clouds above this size are voxel-downsampled first, as in ICP.
    """
    return Scorer(source, target, distance, max_points)(transformation)


def feature_vector(f: Features) -> np.ndarray:
    """The measurements of :data:`FEATURE_NAMES` as the logistic function takes them: (2,)."""
    return np.array([f.consistency, min(f.spacing_ratio, RATIO_CAP)])


def confidence(f: Features) -> float:
    """Estimated probability (0-1, higher is better) that the alignment is right."""
    if f.overlap < MIN_OVERLAP:
        return 0.0
    z = COEFFICIENTS[0] + float(np.dot(COEFFICIENTS[1:], feature_vector(f)))
    return 1.0 / (1.0 + math.exp(-min(max(z, -700.0), 700.0)))
