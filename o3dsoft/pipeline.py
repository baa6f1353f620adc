"""``register``: the whole pipeline, one commented stage per line.

    clean (drop NaN/inf, duplicates; optional voxel grid) -> sample N points for the net
    -> normalise (centre, one scale) -> coarse net (TorchScript) -> map back
    -> refine (Open3D point-to-point ICP, full resolution) -> score (confidence)
    -> if flagged: search (a feature match's estimates in turn, then the nets from 39 starts,
       then the translations the feature matches vote for at the best results' rotations,
       then, optionally, every distinct start again with ICP's tight stages only), until one
       is confident; the most confident kept
    (When the clouds' profiles say partial overlap, the feature match goes before the network,
    which then runs only if the match finds nothing confident.)

Each stage is a function of its own module (:mod:`o3dsoft.preprocess`, :mod:`o3dsoft.coarse`,
:mod:`o3dsoft.refine`, :mod:`o3dsoft.confidence`, :mod:`o3dsoft.search`) and can be called alone.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Dict, List, NamedTuple, Optional, Tuple, Union

import numpy as np

from . import coarse as coarse_stage
from . import confidence as confidence_stage
from . import refine as refine_stage
from . import search as search_stage
from .errors import InputError
from .preprocess import (clean_points, denormalise_transform, normalise_pair, normalisation_for, same_profile_pvalue, sample_points,
                         voxel_downsample)
from .transforms import rigid, rotation_angle_deg

SEARCH_MODES = ("auto", "always", "off")
# Estimates are screened against RegisterConfig.max_rotation before ICP with this margin
# (degrees), since ICP can still move them into the bound; the result itself must lie within it.
PRIOR_MARGIN_DEG = 10.0
# The feature match's first round of candidates (RegisterConfig.search_feature_candidates).
FIRST_FEATURE_CANDIDATES = 20
# When nothing is confident after the search: the feature matches' translation votes
# (:meth:`o3dsoft.search.FeatureMatch.translations`) at the rotations of this many of the most
# trusted results (distinct by search.DISTINCT_DEG), this many translations each.
VOTED_ROTATIONS = 2
VOTED_TRANSLATIONS = 10
# ... and at the most trusted one turned by 180 degrees about each principal axis of the target
# and of the moved source, this many translations each.
FLIPPED_TRANSLATIONS = 3
# When nothing is confident at the end of the search, every distinct start so far is refined again
# by ICP's stages from this share of the correspondence distance on (0.3: the last two).
TIGHT_RESTART = 0.3
# ... less the starts within this many degrees and this share of the scale of an earlier one.
RESTART_DISTINCT_DEG = 2.0
RESTART_DISTINCT_SHIFT = 0.02
# ... each screened by those stages on the screen clouds (below), the most trusted this many then
# refined and scored on the work clouds.
RESTART_REFINED = 3
# The screen clouds: the work clouds voxel-downsampled to at most this many points each. On larger
# clouds each of the search's estimates is refined and scored there first, and on the work clouds
# only when the screen trusts it more than every estimate before it (and at least
# SCREEN_MIN_TRUST), or confidently.
SCREEN_POINTS = 1024
SCREEN_MIN_TRUST = 1e-3
# Below this p-value of :func:`o3dsoft.preprocess.same_profile_pvalue` the clouds are taken for a
# partial overlap, and the search's feature match runs before the network.
PARTIAL_PROFILE_PVALUE = 0.01
CloudLike = Union[np.ndarray, "open3d.geometry.PointCloud"]  # noqa: F821


@dataclass(frozen=True)
class RegisterConfig:
    """Settings of :func:`register` (dumped next to every result).

    Attributes:
        voxel: downsample both clouds on a voxel grid of this size (cloud units) after cleaning,
            which evens out the density of scans and bounds ICP's time; None: keep every point.
        num_points: points sampled from each cloud for the network.
        coarse_iterations: network passes, each on the source moved by the estimate so far.
        search: the global search (:mod:`o3dsoft.search`), for pairs with no usable initial
            guess: "auto" runs it when the first result is flagged likely failed, or first of
            all when the clouds look like a partial overlap (their distances to their centroids
            differ, :func:`o3dsoft.preprocess.same_profile_pvalue` below
            :data:`PARTIAL_PROFILE_PVALUE`; the network, trained on complete shapes, is then
            run only if the feature match finds nothing confident); "always" on every pair;
            "off" never. It tries the feature match's estimates first (if
            `search_features`), then, while no result is confident, the network from 24
            starting rotations (and the search network from 15, see `search_weights`), then (if
            `search_features`) at the rotations of the :data:`VOTED_ROTATIONS` most trusted results,
            the :data:`VOTED_TRANSLATIONS` translations most feature matches vote for, and at the
            most trusted rotation turned by 180 degrees about each principal axis of either cloud
            (:func:`o3dsoft.search.half_turns`), :data:`FLIPPED_TRANSLATIONS` each, then (with
            `refine` and `search_restart`) every distinct start so far again, by ICP from
            :data:`TIGHT_RESTART` x its distance on; the most confident result is
            returned. Without `refine`, the search's top-ranked estimate is taken as it is.
        search_restart: end the search, while nothing is confident (nothing has reached
            `search_feature_stop`, when that is higher), by refining every distinct
            start again with ICP's tight stages only (the loose one pulls a nearly right start
            of a crop towards the parts with no partner), screened on the screen clouds (at
            most :data:`SCREEN_POINTS` points each), the :data:`RESTART_REFINED` most trusted
            there then on the work clouds. Off by default: on the whole ModelNet40 test
            split, within (5 deg, 0.05) `rpmnet-crop` / `so3-crop`, 95.8 / 94.9 % without and
            96.6 / 96.0 % with it, but 38 / 45 confident wrong instead of 33 / 44 and a mean time
            per pair of 1.0 s instead of 0.7 s (README, The pipeline).
        search_points: points per cloud for the search's batch of network passes.
        search_refine: how many of the search's best-ranked estimates are polished by ICP on the
            network's samples before the best of them is refined at full resolution.
        search_weights: a second network for the search (a file or a shipped model's name;
            default "partial", trained on cropped, noisy clouds), run from 15 starts around the
            pose the clouds are given in (:func:`o3dsoft.search.local_rotations`); its estimates
            join those of the 24 starts for ranking. None: only the main network searches.
        search_features: the search starts with FPFH features matched by RANSAC
            (:class:`o3dsoft.search.FeatureMatch`), classical estimates that do not depend on
            the network's training distribution (partial scans, large rotations). Part of the
            search: unused when it does not run.
        search_feature_candidates: the feature match keeps up to this many distinct estimates,
            the best-supported first, refined and scored in turn until one is confident (the
            first 20 are picked up front, the rest only for pairs still not confident). On the
            whole ModelNet40 test split, recall at (1 deg, 0.01) `rpmnet-crop` / `so3-crop`:
            70.5 / 55.8 % with Open3D's RANSAC tried up to 3 times on the tutorial's features,
            85.6 / 71.4 % with 20 estimates on the same features, 87.8 / 86.5 % on the search's
            own (:data:`o3dsoft.search.FEATURES`; README, Results). On test pairs 300-799, with
            ICP started at RANSAC's inlier distance, 20 / 50 / 100 / 200 estimates gave 89.4 /
            91.2 / 92.6 / 92.8 % on `rpmnet-crop`, and 100 gave 91.8 % on `so3-crop` (88.8 % with
            20), with as many confident wrong results (5 and 6 of 500).
        search_feature_stop: the feature match goes on through its estimates until one reaches
            this confidence (at least 0.5, where the search would otherwise stop), so that a
            doubtful result is searched further; the most confident is kept. At 0.9, on the
            pairs of the whole ModelNet40 test split whose result was trusted at 0.5-0.9 (281
            `rpmnet-crop`, 307 `so3-crop`), 5 and 6 wrong results were mended and none lost,
            the confident wrong ones among them fell from 25 to 20 and 42 to 35, and each such
            pair took 2.5-2.8 s longer on average (0.31 s per pair over the split; one thread,
            2-core machine). Default 0.5: stop at the first confident estimate. With
            `search_restart` as well, the restart then runs on every result still below the
            stop: on `rpmnet-crop` (README, The pipeline) 96.9 % within (5 deg, 0.05) against
            95.8 % by default, for a mean time per pair about twice the default's.
        attempt_points: every estimate (the network's, the search's) is refined by ICP and
            scored on the clouds voxel-downsampled to at most this many points each; the most
            confident is then refined again, and scored, at full resolution. Clouds this small
            are used as they are. Bounds the time of the search on scans: on the bundled bunny
            pairs (30-40k points) each estimate's ICP took seconds at full resolution. On work
            clouds above :data:`SCREEN_POINTS` points, the search's feature-match and voted
            estimates are screened on a voxel grid of that size first, and refined here only
            when trusted there more than every estimate before them, or confidently.
        max_rotation: the clouds are given within this many degrees of their true relative
            rotation (a prior, e.g. from odometry or a scanner's set-up): estimates that rotate
            the source by more are not trusted (confidence 0), so the search goes on until it
            finds a confident one within the bound. The result lies within it: when nothing
            confident is found there, the most trusted estimate within it, or else the pose as
            given (refined by ICP where that stays within; else as it is, with confidence 0),
            flagged likely failed. None: any rotation.
        refine: run ICP after the network.
        icp: settings of the fine stage.
        weights: TorchScript model file, or a shipped model's name ("default", "paper"); None for
            the shipped default.
        device: torch device of the network ("cpu", "cuda", "cuda:1"...).
        seed: seed of the point sampling and of the search's RANSAC: the same input and seed
            give the same result, searched or not.
    """

    voxel: Optional[float] = None
    num_points: int = 1024
    coarse_iterations: int = 1
    search: str = "auto"
    search_restart: bool = False
    search_points: int = 256
    search_refine: int = 3
    search_weights: Optional[str] = "partial"
    search_features: bool = True
    search_feature_candidates: int = 100
    search_feature_stop: float = 0.5
    attempt_points: int = 5_000
    max_rotation: Optional[float] = None
    refine: bool = True
    icp: refine_stage.ICPConfig = field(default_factory=refine_stage.ICPConfig)
    weights: Optional[str] = None
    device: str = "cpu"
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    def validate(self, k: int) -> None:
        """Raise InputError for settings the network (neighbourhood size `k`) cannot run with."""
        if self.search not in SEARCH_MODES:
            raise InputError(f"search={self.search!r}; valid: {', '.join(SEARCH_MODES)}")
        for name in ("num_points", "search_points", "attempt_points"):
            if getattr(self, name) < k:
                raise InputError(f"{name}={getattr(self, name)} is below the network's neighbourhood size K={k}")
        if self.voxel is not None and not self.voxel > 0:
            raise InputError(f"voxel must be positive, got {self.voxel}")
        if self.search_feature_candidates < 1:
            raise InputError(f"search_feature_candidates must be at least 1, got {self.search_feature_candidates}")
        if self.max_rotation is not None and not 0 < self.max_rotation <= 180:
            raise InputError(f"max_rotation must be in (0, 180] degrees, got {self.max_rotation}")
        if not confidence_stage.LIKELY_FAILED_BELOW <= self.search_feature_stop <= 1:
            raise InputError(f"search_feature_stop must be in [{confidence_stage.LIKELY_FAILED_BELOW}, 1], got {self.search_feature_stop}")
        if self.search_refine < 1:
            raise InputError(f"search_refine must be at least 1, got {self.search_refine}")


@dataclass
class RegistrationResult:
    """The result of registering a source cloud onto a target cloud.

    Attributes:
        transformation: (4, 4) float64 T_target_source: p_target = T @ p_source.
        fitness: share of source points with a target point within `correspondence_distance`
            after the final transform (0-1, higher is better).
        inlier_rmse: RMS distance of those point pairs (cloud units, lower is better).
        coarse_transformation: (4, 4) the coarse estimate the result was refined from, before
            any ICP: the network's, or after a search one of its starts (or the feature match).
        confidence: estimated probability that the alignment is right (0-1, higher is better),
            from `consistency` (:mod:`o3dsoft.confidence`).
        likely_failed: confidence below 0.5: treat the transform as wrong.
        fitness_tight: share of source points within `tight_distance` of a target point, or of
            target points near the source when the target is much sparser (0-1).
        tight_distance: max(0.3 x correspondence_distance, 1.5 x the point spacing of the
            denser cloud).
        consistency: of the points counted by `fitness_tight` that lie within
            `correspondence_distance` of the other cloud, the share within `tight_distance` (0-1,
            higher is better; partial overlap does not lower it).
        mean_weight: mean of the network's per-point weights w_i = max_j W_ij in its first
            pass (0-1); None when the network did not run (the feature match, tried first on a
            partial overlap, found a confident result).
        correspondence_distance: the ICP / scoring distance used (cloud units).
        scale: the common scale the clouds were normalised by (cloud units).
        timings_ms: wall time of each stage in milliseconds (lower is better).
        num_source, num_target: points registered (after cleaning and the voxel grid).
        attempts: estimates refined by ICP and scored (1, or more after a search), on clouds
            of at most ``RegisterConfig.attempt_points``; the kept one again at full resolution.
        screened: estimates first refined and scored on the screen clouds (at most
            :data:`SCREEN_POINTS` points each), of which only the most trusted count among the
            `attempts`: the search's on larger clouds, and the optional restart's.
        searched: whether the global search ran.
        points_used: points per cloud (source, target) at each stage: "network" (the network's
            samples), "attempts" (the clouds every estimate is refined and scored on) and
            "final" (the kept estimate's last refinement, the registered clouds).
        network_transformation: (4, 4) the network's own estimate (its passes from the pose the
            clouds are given in), before ICP and whatever the search found; None when the
            network did not run (the feature match, tried first on a partial overlap, found a
            confident result).
        removed: rows dropped by cleaning, per cloud: {"source_non_finite": ..., ...}.
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    coarse_transformation: np.ndarray
    confidence: float
    likely_failed: bool
    fitness_tight: float
    tight_distance: float
    consistency: float
    mean_weight: Optional[float]
    correspondence_distance: float
    scale: float
    timings_ms: Dict[str, float]
    num_source: int
    num_target: int
    attempts: int
    screened: int
    searched: bool
    removed: Dict[str, int]
    network_transformation: Optional[np.ndarray] = None
    points_used: Dict[str, Tuple[int, int]] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict (arrays as nested lists)."""
        d = asdict(self)
        d["transformation"] = self.transformation.tolist()
        d["coarse_transformation"] = self.coarse_transformation.tolist()
        if self.network_transformation is not None:
            d["network_transformation"] = self.network_transformation.tolist()
        return d


class _Attempt(NamedTuple):
    """One refined and scored estimate: ICP ran from `start` (the `coarse` estimate, or its
    polish on the network's samples)."""

    trust: float
    scored: confidence_stage.Features
    fine: refine_stage.ICPResult
    coarse: np.ndarray
    start: np.ndarray


def as_points(cloud: CloudLike, name: str) -> np.ndarray:
    """An Open3D PointCloud or an (N, 3) array-like -> (N, 3) float64 array."""
    if hasattr(cloud, "points") and not isinstance(cloud, np.ndarray):
        return np.asarray(cloud.points, dtype=np.float64)
    arr = np.asarray(cloud)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected points of shape (N, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{name}: expected numeric points, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def distinct_starts(attempts: List[_Attempt], centre: np.ndarray, scale: float) -> List[_Attempt]:
    """`attempts` in order, less those whose start (4, 4) lies within :data:`RESTART_DISTINCT_DEG`
    in rotation of an earlier one's and puts the source's `centre` (3,) within
    :data:`RESTART_DISTINCT_SHIFT` x `scale` of where that one does."""
    if not attempts:
        return []
    starts = np.stack([a.start for a in attempts])
    first = search_stage.first_of_each_pose(starts, centre, scale, RESTART_DISTINCT_DEG, RESTART_DISTINCT_SHIFT)
    return [attempts[k] for k in first]


def register(
    source: CloudLike,
    target: CloudLike,
    config: RegisterConfig = RegisterConfig(),
    model: Optional[coarse_stage.CoarseModel] = None,
    search_model: Optional[coarse_stage.CoarseModel] = None,
    source_name: str = "source",
    target_name: str = "target",
) -> RegistrationResult:
    """Find T_target_source, the rigid transform that maps `source` onto `target`.

    Args:
        source: (N, 3) array or Open3D PointCloud, any units and position.
        target: (M, 3) array or Open3D PointCloud, same units as source.
        config: pipeline settings.
        model: an already loaded model (else loaded from ``config.weights``).
        search_model: an already loaded search network (else loaded from
            ``config.search_weights`` when the search needs it).
        source_name, target_name: how to call the clouds in error messages (e.g. file names).
    Returns:
        RegistrationResult.
    Raises:
        InputError: a cloud is degenerate (too few points, identical or collinear points), the
            weights file is unusable, or a setting of `config` is invalid (see its ``validate``).
    """
    timings: Dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + (now - clock) * 1000.0  # summed over attempts
        clock = now

    # Load the network (callers registering many pairs pass it in, loaded once).
    if model is None:
        model = coarse_stage.load_model(config.weights, config.device)
        lap("load_model")
    config.validate(model.config.k)
    k = model.config.k

    # Clean: drop NaN/inf rows and duplicates; reject degenerate clouds; even out the density.
    src = clean_points(as_points(source, source_name), source_name, min_points=k)
    tgt = clean_points(as_points(target, target_name), target_name, min_points=k)
    src_points, tgt_points = src.points, tgt.points
    if config.voxel is not None:
        src_points = voxel_downsample(src_points, config.voxel, source_name, min_points=k)
        tgt_points = voxel_downsample(tgt_points, config.voxel, target_name, min_points=k)
    lap("clean")

    # Sample the network's input and normalise the pair (own centroids, one common scale).
    norm = normalisation_for(src_points, tgt_points)
    distance = config.icp.distance_for(norm.scale)
    src_net = sample_points(src_points, config.num_points, seed=config.seed)
    tgt_net = sample_points(tgt_points, config.num_points, seed=config.seed + 1)
    src_norm, tgt_norm, _ = normalise_pair(src_net, tgt_net, norm)
    lap("sample_normalise")

    # Estimates are refined and scored on clouds of at most `attempt_points`; the kept one is
    # refined again at full resolution (a no-op for clouds that small).
    src_work = refine_stage.downsample(src_points, config.attempt_points)
    tgt_work = refine_stage.downsample(tgt_points, config.attempt_points)
    reduced = len(src_work) < len(src_points) or len(tgt_work) < len(tgt_points)

    def admissible(T: np.ndarray, margin: float = 0.0) -> bool:
        return config.max_rotation is None or rotation_angle_deg(T[:3, :3]) <= config.max_rotation + margin

    # One scorer per pair of clouds estimates are scored on (work, screen, full resolution), keyed
    # by the arrays' identities; each entry keeps its arrays, so that no other array takes their ids.
    scorers: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, confidence_stage.Scorer]] = {}

    def scorer(src_at: np.ndarray, tgt_at: np.ndarray) -> confidence_stage.Scorer:
        key = (id(src_at), id(tgt_at))
        if key not in scorers:
            scorers[key] = (src_at, tgt_at, confidence_stage.Scorer(src_at, tgt_at, distance, config.icp.max_points))
        return scorers[key][2]

    def finish(start: np.ndarray, T_coarse: np.ndarray, src_at: np.ndarray = src_work, tgt_at: np.ndarray = tgt_work,
               icp: refine_stage.ICPConfig = config.icp, refine: bool = config.refine) -> _Attempt:
        # Refine: point-to-point ICP from `start` (or just score it).
        if refine:
            fine = refine_stage.icp(src_at, tgt_at, start, distance, icp)
        else:
            fine = refine_stage.evaluate(src_at, tgt_at, start, distance, config.icp.max_points)
        lap("refine")
        # Score: how much to trust the result.
        scored = scorer(src_at, tgt_at)(fine.transformation)
        trust = confidence_stage.confidence(scored) if admissible(fine.transformation) else 0.0
        lap("score")
        return _Attempt(trust, scored, fine, T_coarse, start)

    attempts: List[_Attempt] = []
    screen_clouds: List[np.ndarray] = []

    def screen() -> Tuple[np.ndarray, np.ndarray]:
        # The work clouds on a voxel grid of at most SCREEN_POINTS points: an even spacing, which
        # the confidence relies on. A random sample's clumps and gaps read as misfit: on the bunny
        # scans bun000 -> bun045 at the ground truth, 0.98 on the grid, 0.19 on 1,024 random
        # points (0.996 on the work clouds). Smaller clouds whole, shuffled.
        if not screen_clouds:
            screen_clouds.extend(refine_stage.downsample(c, SCREEN_POINTS) if len(c) > SCREEN_POINTS
                                 else sample_points(c, SCREEN_POINTS, seed=config.seed + offset)
                                 for offset, c in ((4, src_work), (5, tgt_work)))
        return screen_clouds[0], screen_clouds[1]

    screening = config.refine and max(len(src_work), len(tgt_work)) > SCREEN_POINTS
    screened: List[_Attempt] = []  # the search's estimates as the screen scored them
    tight_icp = config.icp.starting_at(TIGHT_RESTART)

    def promote(s: _Attempt) -> _Attempt:
        # An estimate converged on the screen clouds, refined and scored on the work clouds: from
        # where the screen left it, by the tight stages only.
        return finish(s.fine.transformation, s.coarse, icp=tight_icp)._replace(start=s.start)

    def search_attempt(start: np.ndarray, icp: refine_stage.ICPConfig) -> None:
        # One of the search's estimates, refined and scored into `attempts`. On clouds larger than
        # the screen, first there: ICP on 5,000 points per cloud took about 0.7 s per estimate on
        # the bunny scans, and a flagged pair tries over 100.
        if not screening:
            attempts.append(finish(start, start, icp=icp))
            return
        s = finish(start, start, *screen(), icp=icp)
        record = max((a.trust for a in screened), default=0.0)
        screened.append(s)
        if (s.trust > record and s.trust >= SCREEN_MIN_TRUST) or s.trust >= confidence_stage.LIKELY_FAILED_BELOW:
            attempts.append(promote(s))

    def best_trust() -> float:
        return max((a.trust for a in attempts), default=0.0)

    def confident() -> bool:  # some attempt so far is trusted
        return best_trust() >= confidence_stage.LIKELY_FAILED_BELOW

    def settled() -> bool:  # some attempt so far is trusted enough to end the feature match
        return best_trust() >= max(config.search_feature_stop, confidence_stage.LIKELY_FAILED_BELOW)

    def network_pass() -> Tuple[coarse_stage.CoarseEstimate, np.ndarray]:
        # Coarse: the soft-alignment network, then back to the original frames.
        estimate = coarse_stage.estimate(model, src_norm, tgt_norm, config.coarse_iterations)
        lap("coarse")
        T_coarse = denormalise_transform(estimate.transform, norm)
        attempts.append(finish(T_coarse, T_coarse))
        return estimate, T_coarse

    matchers: List[search_stage.FeatureMatch] = []  # the FPFH features, computed once

    def feature_matcher() -> Tuple[search_stage.FeatureMatch, refine_stage.ICPConfig]:
        if not matchers:
            matchers.append(search_stage.FeatureMatch(src_points, tgt_points, norm.scale))
        # A candidate carries its matches to within RANSAC's inlier distance, so ICP starts there
        # rather than at its loosest stage, which pulls some right estimates of partial clouds
        # towards the parts with no partner.
        return matchers[0], config.icp.starting_at(matchers[0].inlier_distance / distance)

    def feature_match() -> None:
        # FPFH features matched by RANSAC, which keeps its best-supported distinct estimates;
        # each is refined and scored in turn until one is confident. Cheap per estimate, and on
        # partial overlap far more often right than the network's starts.
        matcher, feature_icp = feature_matcher()
        # In two rounds: most pairs have a confident estimate among the first few candidates, and
        # the rest cost only the pairs that need them.
        before, tried = len(attempts), 0
        for count in sorted({min(FIRST_FEATURE_CANDIDATES, config.search_feature_candidates), config.search_feature_candidates}):
            if tried and settled():
                break
            feature_candidates = matcher.candidates(config.seed, count)[tried:]  # each round extends the last
            tried += len(feature_candidates)
            lap("search")
            for T_features in filter(lambda T: admissible(T, PRIOR_MARGIN_DEG), feature_candidates):
                if len(attempts) > before and settled():
                    break
                search_attempt(T_features, feature_icp)

    # Partial overlap (the clouds' profiles differ): the network, trained on complete shapes, is
    # seldom confident there, so the feature match goes first and the network runs only when
    # it finds nothing confident.
    features_first = (config.search != "off" and config.search_features
                      and same_profile_pvalue(src_net, tgt_net) < PARTIAL_PROFILE_PVALUE)
    lap("sample_normalise")
    if features_first:
        feature_match()
    estimate, T_network = network_pass() if not (features_first and confident()) else (None, None)
    searched = features_first or config.search == "always" or (config.search == "auto" and not confident())
    if searched and config.search_features and not features_first:
        feature_match()
    if searched and not confident():
        # Search, last: the network from the 24 cube rotations on smaller samples; the best-ranked
        # are polished by ICP on the network's samples, and the one that fits best there is
        # refined at full resolution and scored.
        src_small = sample_points(src_norm, config.search_points, seed=config.seed + 2)
        tgt_small = sample_points(tgt_norm, config.search_points, seed=config.seed + 3)
        candidates = search_stage.network_candidates(model, src_small, tgt_small, search_stage.cube_rotations())
        if config.search_weights is not None:
            if search_model is None:
                search_model = coarse_stage.load_model(config.search_weights, config.device)
            if search_model.config.k > config.search_points:
                raise InputError(f"search_points={config.search_points} is below the search network's neighbourhood size K={search_model.config.k}")
            local = search_stage.network_candidates(search_model, src_small, tgt_small, search_stage.local_rotations())
            candidates = np.concatenate([candidates, local])
        candidates = [T for T in (denormalise_transform(T, norm) for T in candidates) if admissible(T, PRIOR_MARGIN_DEG)]
        candidates = np.stack(candidates or [np.eye(4)])  # none within the prior: the pose as given
        chosen = search_stage.select(src_net, tgt_net, candidates, distance, config.search_refine, config.icp if config.refine else None)
        lap("search")
        attempts.append(finish(chosen.polished, chosen.estimate))
    if searched and config.search_features and not confident():
        # Last: at the rotations of the most trusted results, the translations the feature
        # matches vote for (one right match suffices there), for shapes whose estimates slide
        # along a flat or repeated part at about the right rotation.
        matcher, feature_icp = feature_matcher()
        ranked = sorted(attempts, key=lambda a: (admissible(a.fine.transformation), a.trust), reverse=True)
        rotations: List[np.ndarray] = []
        for a in ranked:
            if len(rotations) >= VOTED_ROTATIONS:
                break
            R = a.fine.transformation[:3, :3]
            if admissible(a.fine.transformation) and all(rotation_angle_deg(R.T @ Q) > search_stage.DISTINCT_DEG for Q in rotations):
                rotations.append(R)
        counts = [VOTED_TRANSLATIONS] * len(rotations)
        if rotations and FLIPPED_TRANSLATIONS:
            # A shape nearly symmetric under a half turn is often aligned the other way round.
            R0 = rotations[0]
            turns = np.concatenate([search_stage.half_turns(tgt_work), search_stage.half_turns(src_work @ R0.T)])
            flipped = [F @ R0 for F in turns]
            flipped = [R for R in flipped if admissible(rigid(R, np.zeros(3)), PRIOR_MARGIN_DEG)]
            rotations += flipped
            counts += [FLIPPED_TRANSLATIONS] * len(flipped)
        voted = [T for R, count in zip(rotations, counts) for T in matcher.translations(R, count)]
        lap("search")
        for T_voted in voted:
            if confident():
                break
            search_attempt(T_voted, feature_icp)
    if searched and config.refine and config.search_restart and not settled():
        # Last: every distinct start again, with only ICP's tight stages. On partial overlap the
        # loose stage pulls a start a few degrees off towards the parts with no partner, and a
        # wrong pose ends up fitting better than the drifted right one. Each start is screened on
        # the screen clouds (all of a small cloud); only the most trusted there are
        # refined and scored on the work clouds, which bounds the cost on scans.
        starts = distinct_starts(sorted(attempts + screened, key=lambda a: a.trust, reverse=True), src_work.mean(axis=0), norm.scale)
        restarted = [finish(a.start, a.coarse, *screen(), tight_icp) for a in starts if admissible(a.start, PRIOR_MARGIN_DEG)]
        screened.extend(restarted)
        for s in sorted(restarted, key=lambda s: s.trust, reverse=True)[:RESTART_REFINED]:
            if settled():
                break
            attempts.append(promote(s))
    # The most trusted; under a rotation prior, one within the bound before any beyond it.
    best = max(attempts, key=lambda a: (admissible(a.fine.transformation), a.trust))
    if not admissible(best.fine.transformation):
        # Nothing found within the prior: the pose as given, refined if ICP keeps it there.
        best = finish(np.eye(4), np.eye(4))
        if not admissible(best.fine.transformation):
            # ICP leaves the bound from there too: the clouds disagree with the prior.
            best = finish(np.eye(4), np.eye(4), refine=False)._replace(trust=0.0)
    if reduced:
        # At full resolution, only the tight stages: the loose first one would pull the converged
        # estimate towards the parts with no partner (partial overlap) and cost the most.
        tight = replace(config.icp, schedule=config.icp.schedule[-2:])
        best = finish(best.fine.transformation, best.coarse, src_points, tgt_points, tight)
    timings["total"] = sum(timings.values())

    return RegistrationResult(
        transformation=best.fine.transformation,
        fitness=best.fine.fitness,
        inlier_rmse=best.fine.inlier_rmse,
        coarse_transformation=best.coarse,
        confidence=best.trust,
        likely_failed=best.trust < confidence_stage.LIKELY_FAILED_BELOW,
        fitness_tight=best.scored.fitness_tight,
        tight_distance=best.scored.tight_distance,
        consistency=best.scored.consistency,
        mean_weight=None if estimate is None else float(np.mean(estimate.weights)),
        correspondence_distance=distance,
        scale=norm.scale,
        timings_ms=timings,
        num_source=len(src_points),
        num_target=len(tgt_points),
        attempts=len(attempts),
        screened=len(screened),
        searched=searched,
        network_transformation=T_network,
        points_used={"network": (len(src_net), len(tgt_net)), "attempts": (len(src_work), len(tgt_work)),
                     "final": (len(src_points), len(tgt_points))},
        removed={
            "source_non_finite": src.non_finite,
            "source_duplicates": src.duplicates,
            "target_non_finite": tgt.non_finite,
            "target_duplicates": tgt.duplicates,
        },
    )
