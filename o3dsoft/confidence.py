"""How much to trust a registration: a confidence in [0, 1] and a ``likely_failed`` flag.

A wrong alignment (ICP stuck in a local minimum, a flipped shape, two unrelated clouds) still has
many source points near *some* target point at ICP's loose distance d, but fewer of them close at
a tight one; a right alignment of two partial clouds has points with no partner at all, while
those in the overlap are close. The confidence is a logistic function of scale-free measurements
of the final alignment that overlap does not change (:class:`Features`):

- ``consistency``: of the source points with a target point within d, the share within the tight
  distance max(0.3 d, 1.5 s), s the target's median point spacing. A point whose nearest target
  point has a source point over three times closer lies beyond the target's edge (partial
  overlap) and is not counted either way; on a wrong alignment no such closer partner exists. When
  the target is much sparser than the source, the roles swap. Where the counted cloud is much
  sparser than the other (a scan the user downsampled), its points lie too far apart to be three
  times closer, and a partner that lies on its surface (near its tangent plane, among its points)
  is taken as claimed too.
- ``spacing_ratio``: the median distance to the nearest partner over the other cloud's spacing,
  about 1 for two independent samplings of one surface at the right pose, 0 for identical points.

That function is strict: a right alignment of two independent samplings of a surface (no shared
point) has about a fifth of its points beyond the tight distance, and scores low. Where both clouds
look like complete samplings of one shape (not scans, no partial overlap) and the pose shows no
shared point (spacing ratio at least ``independent_from``), :func:`complete_confidence` judges it
too, by a second logistic function that also weighs the ``overlap``: on complete shapes a right
pose leaves few points without a partner, and a wrong one that fits a part closely leaves many.
The pipeline searches by the strict function, and reports the larger of the two; it chooses by
the larger too where no estimate of the pair has a spacing ratio under 0.85
(:meth:`o3dsoft.verify.Verifier.independent`).

On scans the strict function also flags some right alignments: where the overlap's edges curl or
are seen at grazing angles, about one in eight of the nearby points lies off the other scan.
:func:`scan_confidence` judges those by the ``planar`` share: how much of the overlap lies on the
other scan's surface (its tangent planes, from point-to-plane ICP's normals). It is fitted with a
wrong pose weighing a hundred right ones, and the result reports the larger of the two too.

On other partial overlaps (crops of small clouds) whose pose shows no shared point, no
measurement of the alignment tells the right pose from a wrong one that fits a part as closely;
what does is how many of the pair's estimates reached it (``agreeing``: the search's feature
match, networks and votes start from many poses, and more of them end at the right one).
:func:`partial_confidence` is a logistic function of its logarithm, fitted with a wrong pose
weighing ten right ones, and the result reports the larger of the two.

An alignment that leaves the clouds barely touching (counted points under ``min_overlap`` of the
smaller cloud) gets confidence 0. The coefficients are fitted by logistic regression
(``python -m benchmarks.fit_confidence``, ``fit_complete_confidence``, ``fit_scan_confidence``,
``fit_partial_confidence``);
the data, the measurements and the rejected alternatives are in docs/pipeline.md (The
confidence). Below 0.5 a result is flagged ``likely_failed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Optional, Tuple

import numpy as np
from scipy.spatial import cKDTree

from . import refine as refine_stage
from .transforms import apply_transform

# The measurements the confidence is a logistic function of, in the order of its coefficients.
FEATURE_NAMES = ("consistency", "spacing_ratio")
# ... and those of :func:`complete_confidence`.
COMPLETE_FEATURE_NAMES = ("consistency", "overlap", "spacing_ratio")
# ... and those of :func:`scan_confidence`.
SCAN_FEATURE_NAMES = ("planar",)
# ... and those of :func:`partial_confidence`.
PARTIAL_FEATURE_NAMES = ("log_agreeing",)
# The edge test on a much sparser counted cloud (:meth:`Scorer.on_sparse_surface`): the neighbours
# of its tangent planes, how many of its points around a partner are averaged, and how far from
# the partner along the plane (in its point spacings) their mean may lie.
EDGE_NEIGHBOURS = 10
EDGE_AROUND = 6
EDGE_INSIDE = 0.5


@dataclass(frozen=True)
class ConfidenceConfig:
    """Settings of the confidence (:class:`Scorer`, :func:`confidence`, :func:`complete_confidence`).

    Attributes:
        distance: d, as a share of the pair's scale (the larger radius): the pipeline measures at
            the distance the coefficients were fitted at, whatever ICP's distance
            (``--icp-distance``, ``--icp-absolute``): a wider one would widen the tight distance
            with it and trust wrong alignments (docs/scans.md).
        coefficients: the logistic function's intercept, then one weight per name of
            :data:`FEATURE_NAMES` (fitted by ``python -m benchmarks.fit_confidence``).
        likely_failed_below: results less confident than this are flagged likely failed (0-1).
        tight: the tight distance is at least this share of d (the ICP distance).
        spacings: ... and at least this many point spacings of the cloud compared with; a target
            whose spacing exceeds the source's this many times is the one whose points are counted.
        claimed: a point whose nearest partner has a point of its own cloud within this share of
            their distance lies beyond the other cloud's edge, and is not counted. Where the
            counted cloud's spacing exceeds the other's `spacings` times, so does a point whose
            partner lies within this share of their distance of the counted cloud's tangent plane
            and among its points (:meth:`Scorer.on_sparse_surface`).
        min_overlap: alignments whose counted points are fewer than this share of the smaller
            cloud get confidence 0 (too few to measure).
        min_points: on clouds the smaller of which holds fewer points, the pipeline caps the
            reported confidence at likely_failed_below x points / min_points (flagged): there the
            tight distance (1.5 point spacings) is so wide that wrong alignments fit as closely
            as the right one and score as high (docs/scans.md, "Clouds of a few hundred points").
        ratio_cap: the spacing ratio enters the logistic capped at this value.
        wide_spacings: the spacing ratio looks for partners within this many point spacings when
            that reaches beyond d.
        complete_coefficients: intercept, then one weight per name of
            :data:`COMPLETE_FEATURE_NAMES`: :func:`complete_confidence` (fitted by
            ``python -m benchmarks.fit_complete_confidence``).
        independent_from: a pose whose spacing ratio is at least this shows no shared point:
            :func:`complete_confidence` judges it where both clouds look complete.
        planar_tolerance: ``Features.planar`` counts the points within this share of the tight
            distance of their partner's tangent plane.
        scan_coefficients: intercept, then one weight per name of :data:`SCAN_FEATURE_NAMES`:
            :func:`scan_confidence` (fitted by ``python -m benchmarks.fit_scan_confidence``).
        partial_coefficients: intercept, then one weight per name of
            :data:`PARTIAL_FEATURE_NAMES`: :func:`partial_confidence` (fitted by
            ``python -m benchmarks.fit_partial_confidence``); None: not used.
        agree_deg, agree_shift: two estimates agree (reach one pose) when their rotations lie
            within `agree_deg` degrees and they put the source's centre within `agree_shift` x
            the pair's scale of each other.
        size_note_ratio: a flagged result's reason opens by naming the clouds' sizes (are they
            in the same units?) where the larger cleaned cloud is over this many times the
            smaller (:func:`~o3dsoft.preprocess.scene_size`): feet and metres differ 3.3-fold,
            inches and centimetres 2.5, where two scans of one scene differ at most 1.2-fold and
            the literature's crops of a ModelNet40 shape 2.1.
    """

    distance: float = 0.1
    coefficients: Tuple[float, ...] = (-52.98, 58.54, 0.0)
    likely_failed_below: float = 0.5
    tight: float = 0.3
    spacings: float = 1.5
    claimed: float = 0.3
    min_overlap: float = 0.1
    min_points: int = 200
    ratio_cap: float = 5.0
    wide_spacings: float = 3.0
    complete_coefficients: Tuple[float, ...] = (-20.95, 12.52, 18.19, -5.11)
    independent_from: float = 0.6
    planar_tolerance: float = 0.1
    scan_coefficients: Tuple[float, ...] = (-10.02, 19.68)
    partial_coefficients: Optional[Tuple[float, ...]] = (-3.52, 0.94)
    agree_deg: float = 5.0
    agree_shift: float = 0.05
    size_note_ratio: float = 2.2

    def validate(self) -> None:
        for name, coefficients, names in (
            ("coefficients", self.coefficients, FEATURE_NAMES),
            ("complete_coefficients", self.complete_coefficients, COMPLETE_FEATURE_NAMES),
            ("scan_coefficients", self.scan_coefficients, SCAN_FEATURE_NAMES),
            ("partial_coefficients", self.partial_coefficients or (0.0,) * (len(PARTIAL_FEATURE_NAMES) + 1), PARTIAL_FEATURE_NAMES),
        ):
            if len(coefficients) != len(names) + 1:
                raise ValueError(f"{name}: expected {len(names) + 1} (intercept, {', '.join(names)}), got {len(coefficients)}")
        if not self.distance > 0:
            raise ValueError(f"distance must be positive, got {self.distance}")
        if not 0 < self.planar_tolerance <= 1:
            raise ValueError(f"planar_tolerance must be in (0, 1], got {self.planar_tolerance}")
        if not self.min_points >= 0:
            raise ValueError(f"min_points must be at least 0, got {self.min_points}")
        if not self.independent_from >= 0:
            raise ValueError(f"independent_from must be at least 0, got {self.independent_from}")
        if not (self.agree_deg > 0 and self.agree_shift > 0):
            raise ValueError(f"agree_deg and agree_shift must be positive, got {self.agree_deg} and {self.agree_shift}")
        if not 0 < self.likely_failed_below < 1:
            raise ValueError(f"likely_failed_below must be in (0, 1), got {self.likely_failed_below}")
        if not self.size_note_ratio >= 1:
            raise ValueError(f"size_note_ratio must be at least 1, got {self.size_note_ratio}")


class Features(NamedTuple):
    """fitness_tight: share of the (denser) source's points within `tight_distance` of a target
    point, or of a much sparser target's points near the source (0-1, higher is better);
    tight_distance: max(0.3 d, 1.5 x the point spacing of the cloud they are compared with);
    consistency: of the same points within d of the other cloud, the share within the tight
    distance (0-1, higher is better; 0 when none is within d);
    overlap: the points the consistency counts, as a share of the smaller cloud (capped at 1;
    below ``ConfidenceConfig.min_overlap`` the confidence is 0);
    spacing_ratio: the median distance from a point to its nearest partner over the other
    cloud's median point spacing s (lower is better), over the points within max(d, 3 s) of the
    other cloud less those beyond its edge (as for the consistency): about 1 for two independent
    samplings of one surface at the right pose, 0 for identical point sets, above 1 when the
    surfaces lie apart. Unlike the consistency it keeps its meaning on sparse clouds, whose
    spacing is close to d (two independent samplings' nearest points lie about s apart);
    planar: of the points the consistency counts, the share within ``planar_tolerance`` of the
    tight distance of their partner's tangent plane (0-1, higher is better): on two samplings of
    one surface the distance along the surface is the sampling's, across it the scanner's noise
    (NaN where the scorer has no normals of the cloud compared with)."""

    fitness_tight: float
    tight_distance: float
    consistency: float
    overlap: float
    spacing_ratio: float = 0.0
    planar: float = math.nan


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
        config: the confidence's settings.
        target_normals: (M, 3) unit normals of `target` (e.g. point-to-plane ICP's), for
            ``Features.planar``; not used where the target is downsampled first or is the much
            sparser cloud (then planar is NaN).
    """

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        distance: float,
        max_points: int = refine_stage.ICPConfig.max_points,
        config: ConfidenceConfig = ConfidenceConfig(),
        target_normals: Optional[np.ndarray] = None,
    ) -> None:
        self.config = config
        given = len(target)
        source = refine_stage.downsample(np.asarray(source, dtype=np.float64), max_points)
        target = refine_stage.downsample(np.asarray(target, dtype=np.float64), max_points)
        s_source, s_target = point_spacing(source), point_spacing(target)
        # A sparse target: ask which target points the source covers.
        self.swapped = bool(s_target > config.spacings * s_source)
        self.tight = max(config.tight * distance, config.spacings * (s_source if self.swapped else s_target))
        self.near, self.far = (target, source) if self.swapped else (source, target)
        self.far_tree = cKDTree(self.far)
        self.near_tree = cKDTree(self.near)  # for the edge test: distances do not change under T
        self.far_spacing = max(s_source if self.swapped else s_target, 1e-12)
        self.near_spacing = s_target if self.swapped else s_source
        sparse_near = self.near_spacing > config.spacings * self.far_spacing and len(self.near) >= max(EDGE_NEIGHBOURS, EDGE_AROUND)
        self.near_normals = refine_stage.normals(self.near, EDGE_NEIGHBOURS) if sparse_near else None
        self.reach = max(distance, self.tight)
        self.wide_reach = max(self.reach, config.wide_spacings * self.far_spacing)
        usable = target_normals is not None and not self.swapped and given <= max_points and len(target_normals) == given
        self.far_normals = np.asarray(target_normals, dtype=np.float64) if usable else None

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
            partners = apply_transform(np.linalg.inv(T), self.far[j[doubtful]])  # into the near cloud's frame
            gap, nearest = self.near_tree.query(partners)
            reach = self.config.claimed * dist[doubtful]
            claimed[doubtful] = gap <= reach
            claimed[doubtful] |= self.on_sparse_surface(partners, nearest, reach)
        counted = close | (within & ~claimed)
        ratio_counted = close | (reached & ~claimed)
        spacing_ratio = float(np.median(dist[ratio_counted]) / self.far_spacing) if ratio_counted.any() else math.inf
        if not counted.any():
            return Features(float(close.mean()), self.tight, 0.0, 0.0, spacing_ratio, 0.0 if self.far_normals is not None else math.nan)
        consistency = float(close.sum() / counted.sum())
        overlap = min(1.0, float(counted.sum()) / min(len(moved), len(self.far)))
        return Features(float(close.mean()), self.tight, consistency, overlap, spacing_ratio, self._planar(moved, j, counted))

    def on_sparse_surface(self, partners: np.ndarray, nearest: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """(K,) bool: which of the (K, 3) `partners` (in the counted cloud's frame) lie on the much
        sparser counted cloud's surface: within `reach` (K,) of its tangent plane at their nearest
        point (indices `nearest`, (K,)), and among its points: the mean of their
        :data:`EDGE_AROUND` nearest points lies within :data:`EDGE_INSIDE` point spacings of them
        along that plane (beyond the cloud's edge their mean lies inwards, on the cloud's side). A
        plane alone would reach past the cloud's last points, where a wrong alignment's partners lie."""
        if self.near_normals is None:  # not much sparser: its points tell
            return np.zeros(len(partners), dtype=bool)
        normals = self.near_normals[nearest]
        across = np.abs(np.einsum("ij,ij->i", partners - self.near[nearest], normals))
        _, around = self.near_tree.query(partners, k=EDGE_AROUND)
        offset = partners - self.near[around].mean(axis=1)
        along = offset - np.einsum("ij,ij->i", offset, normals)[:, None] * normals
        return (across <= reach) & (np.linalg.norm(along, axis=1) <= EDGE_INSIDE * self.near_spacing)

    def _planar(self, moved: np.ndarray, j: np.ndarray, counted: np.ndarray) -> float:
        """``Features.planar`` of the (N, 3) moved points, whose nearest partners are far[j],
        over the `counted` ones; NaN without normals."""
        if self.far_normals is None:
            return math.nan
        partners = j[counted]
        across = np.abs(np.einsum("ij,ij->i", moved[counted] - self.far[partners], self.far_normals[partners]))
        return float(np.mean(across <= self.config.planar_tolerance * self.tight))


def features(
    source: np.ndarray,
    target: np.ndarray,
    transformation: np.ndarray,
    distance: float,
    max_points: int = refine_stage.ICPConfig.max_points,
    config: ConfidenceConfig = ConfidenceConfig(),
) -> Features:
    """The measurement of an alignment that the confidence is built from (for several alignments
    of one pair, :class:`Scorer` computes what they share once).

    Args:
        source: (N, 3); target: (M, 3); transformation: (4, 4) T_target_source.
        distance: d, the correspondence distance of the fine stage (cloud units).
        max_points: clouds above this size are voxel-downsampled first, as in ICP.
        config: the confidence's settings.
    """
    return Scorer(source, target, distance, max_points, config)(transformation)


def feature_vector(f: Features, config: ConfidenceConfig = ConfidenceConfig()) -> np.ndarray:
    """The measurements of :data:`FEATURE_NAMES` as the logistic function takes them: (2,)."""
    return np.array([f.consistency, min(f.spacing_ratio, config.ratio_cap)])


def confidence(f: Features, config: ConfidenceConfig = ConfidenceConfig()) -> float:
    """Estimated probability (0-1, higher is better) that the alignment is right: the strict
    function, which any kind of pair may be judged by."""
    if f.overlap < config.min_overlap:
        return 0.0
    return _logistic(config.coefficients, feature_vector(f, config))


def complete_confidence(f: Features, config: ConfidenceConfig = ConfidenceConfig()) -> float:
    """Estimated probability (0-1, higher is better) that an alignment of two clouds that both
    look like complete samplings of one shape is right, weighing how much of them has a partner
    (``overlap``). 0 where the pose shows shared points (spacing ratio under ``independent_from``:
    the strict :func:`confidence` judges those) or the clouds barely touch."""
    if f.overlap < config.min_overlap or not f.spacing_ratio >= config.independent_from:  # NaN: not judged
        return 0.0
    return _logistic(config.complete_coefficients, complete_feature_vector(f, config))


def scan_confidence(f: Features, config: ConfidenceConfig = ConfidenceConfig()) -> float:
    """Estimated probability (0-1, higher is better) that an alignment of two scans is right, from
    how much of the overlap lies on the other scan's surface (``planar``): the strict
    :func:`confidence` flags right alignments of scans whose overlap's edges curl or graze
    (docs/scans.md). 0 where planar is not measured (NaN) or the clouds barely touch."""
    if f.overlap < config.min_overlap or not f.planar >= 0:  # NaN: not measured
        return 0.0
    return _logistic(config.scan_coefficients, np.array([f.planar]))


def partial_confidence(f: Features, agreeing: int, config: ConfidenceConfig = ConfidenceConfig()) -> float:
    """Estimated probability (0-1, higher is better) that an alignment of two partial clouds
    (neither both complete-looking nor scans) whose pose shows no shared point is right, from how
    many of the pair's estimates reached that pose (`agreeing`, itself included): on such crops
    a wrong pose that fits a part closely scores as well by every measurement of the alignment as
    the right one, but fewer estimates from other starts end there. 0 where the pose shows shared
    points (spacing ratio under ``independent_from``: the strict :func:`confidence` judges those),
    the clouds barely touch, or ``partial_coefficients`` is None."""
    if config.partial_coefficients is None or f.overlap < config.min_overlap or not f.spacing_ratio >= config.independent_from:
        return 0.0
    return _logistic(config.partial_coefficients, np.array([math.log(max(agreeing, 1))]))


def agreeing_trusted_from(config: ConfidenceConfig = ConfidenceConfig()) -> Optional[int]:
    """The fewest agreeing estimates whose :func:`partial_confidence` reaches
    ``likely_failed_below`` (None where no count does)."""
    if config.partial_coefficients is None or config.partial_coefficients[1] <= 0:
        return None
    intercept, slope = config.partial_coefficients
    t = config.likely_failed_below
    return max(1, math.ceil(math.exp((math.log(t / (1.0 - t)) - intercept) / slope) - 1e-9))


def complete_feature_vector(f: Features, config: ConfidenceConfig = ConfidenceConfig()) -> np.ndarray:
    """The measurements of :data:`COMPLETE_FEATURE_NAMES` as :func:`complete_confidence` takes
    them: (3,)."""
    return np.array([f.consistency, f.overlap, min(f.spacing_ratio, config.ratio_cap)])


def _logistic(coefficients: Tuple[float, ...], x: np.ndarray) -> float:
    z = coefficients[0] + float(np.dot(coefficients[1:], x))
    return 1.0 / (1.0 + math.exp(-min(max(z, -700.0), 700.0)))
