"""``register``: the whole pipeline, one commented call per stage.

    (a target much sparser than the source: the roles swapped, the result inverted; an initial
    guess: the source moved by it first, the result composed with it)
    prepare the pair (clean, voxel grid, samples for the network, normalisation, work clouds)
    -> propose estimates (ICP from the initial guess, where one is given, which ends the proposals
       where it is trusted; the network; when flagged, a second network trained on clouds that share
       no point, except on scans, from the pose as given and, on two complete-looking clouds, from
       the other rotations of a cube; when still flagged, the search's strategies in turn, unless the
       second network's pose of two complete-looking clouds shows no shared point and the complete
       confidence trusts it, and the feature match's first candidates find no shared point either)
    -> verify each (ICP on the work clouds, confidence)
    -> select the most trusted (within the rotation prior, if any; among those bringing at least
       half as many points into contact as the one that brings most)
    -> refine it again at full resolution when the work clouds were reduced (ICP's last stage
       with point-to-plane ICP, its tight stages with point-to-point)
    -> test whether the geometry determines the pose; where it does not and the pose shows no
       shared point (not on scans), a result no flag had sent to the search goes there now (the
       second network, the search), and what they find replaces it where it fits clearly closer
    -> on two complete-looking clouds whose trusted pose shows no shared point, test whether a
       half-turned copy fits as closely (a symmetric shape): then the confidence is halved.

Where each stage lives: :class:`o3dsoft.pair.PreparedPair`, :mod:`o3dsoft.strategies`,
:class:`o3dsoft.verify.Verifier`, :mod:`o3dsoft.refine`, :mod:`o3dsoft.confidence`. The settings
are :class:`o3dsoft.config.RegisterConfig`, one nested config per stage.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from typing import Any, Callable, Dict, Optional, Tuple, Union

import numpy as np

from . import coarse as coarse_stage
from . import confidence as confidence_stage
from . import degeneracy as degeneracy_stage
from . import refine as refine_stage
from . import symmetry as symmetry_stage
from ._open3d import quietly
from .clock import StageClock
from .config import SEARCH_MODES, RegisterConfig, check_settings
from .errors import InputError, UsageError
from .io import as_rigid, check_rigid
from .metrics import input_chamfer_distance
from .pair import CloudLike, Clouds, GridCloud, PreparedPair, as_points
from .preprocess import CleanReport, local_origin, point_spacing, sample_median, scene_size
from .strategies import (
    FeatureMatchProposals,
    InitialGuess,
    KissMatcherProposal,
    NetworkPass,
    NetworkStarts,
    Restart,
    TranslationVotes,
    TurnedPasses,
    kiss_available,
)
from .transforms import apply_transform, in_frame_at, nearest_rigid, rotation_angle_deg
from .verify import Attempt, Verifier, choice_applies

# Scenes whose sizes differ more than this are named in a warning (multiway) and in a flagged
# odometry step's reason: most often one is in millimetres and the other in metres.
SIZE_RATIO_NOTE = 20.0

__all__ = ["register", "RegisterConfig", "RegistrationResult", "SEARCH_MODES", "as_points"]


@dataclass(frozen=True, eq=False)  # arrays have no single truth value: results compare (and hash) by identity
class RegistrationResult:
    """The result of registering a source cloud onto a target cloud. Frozen, its transforms
    read-only arrays (``np.array(result.transformation)`` gives a copy to change); two results
    compare equal only when they are the same object (compare ``transformation`` with
    ``np.allclose``).

    Attributes:
        transformation: (4, 4) float64 T_target_source: p_target = T @ p_source.
        fitness: share of source points with a target point within `correspondence_distance`
            after the final transform (0-1, higher is better).
        inlier_rmse: RMS distance of those point pairs (cloud units, lower is better).
        coarse_transformation: (4, 4) the estimate the result was refined from, before any ICP:
            the network's, or one the search proposed.
        estimate_from: what proposed that estimate: "initial guess" (``register(init=...)``),
            "network", "second network", "second network, turned" (from a rotation of a cube),
            "KISS-Matcher", "feature match", "network starts", "translation votes" or "pose as
            given".
        confidence: trust in the alignment (0-1, higher is better; on scans lowered to the
            strict function seen from the target's side where that flags it, `target_consistency`); on
            two complete-looking clouds whose pose shows no shared point, the larger of the strict
            function and :func:`~o3dsoft.confidence.complete_confidence`, on scans the larger of
            the strict function and :func:`~o3dsoft.confidence.scan_confidence`, on other partial
            overlaps whose pose shows no shared point the larger of the strict function and
            :func:`~o3dsoft.confidence.partial_confidence` (fits, each on its
            own data: a score to rank and threshold by, not a calibrated probability).
        likely_failed: confidence below the threshold (0.5): treat the transform as wrong.
        failure_reason: why it is flagged, in words; None when it is not.
        fitness_tight: share of source points within `tight_distance` of a target point, or of
            target points near the source when the target is much sparser (0-1, higher is better).
        tight_distance: max(0.3 x the confidence's distance d (``confidence.distance`` x `scale`,
            `correspondence_distance` by default), 1.5 x the point spacing of the cloud compared
            with) (cloud units).
        consistency: of the points counted by `fitness_tight` that lie within d of the other
            cloud, the share within `tight_distance` (0-1, higher is better; partial overlap does
            not lower it).
        mean_weight: mean of the network's per-point weights w_i = max_j W_ij in its first pass
            (between 1/M and 1 for M target points in the network's sample; 1/M where the soft
            assignment is uniform); None when the network did not run.
        correspondence_distance: the ICP / scoring distance used (cloud units).
        scale: the common scale the clouds were normalised by (cloud units).
        timings_ms: wall time of each stage in milliseconds (lower is better).
        num_source, num_target: points registered (after cleaning, the voxel grid and the
            isolated points left out; the work
            clouds' for a flagged result left unrefined, ``refine_flagged=False``).
        voxel: the voxel grid the clouds were registered on (cloud units): the config's, or one
            from the data (:func:`o3dsoft.preprocess.data_grid`); None: every point.
        icp_method: "point" (point-to-point) or "plane" (point-to-plane), as ICP ran.
        attempts: estimates refined and scored on the work clouds.
        screened: estimates refined and scored on the screen clouds first.
        searched: whether the global search ran (not counting the feature match's first candidates
            tried before the second network's pose ends it, ``second_network.shared_check``).
        search_reason: why it ran, in words (None where it did not): the clouds look like a
            partial overlap, the search mode is "always", no estimate was trusted, the trusted estimate
            was not trusted at full resolution, or the trusted pose is not fixed by the geometry.
        removed: rows dropped by cleaning, per cloud: {"source_non_finite", "source_duplicates",
            "source_strays" (points over ``preprocess.STRAY_REACH`` times the cloud's reach from
            its median), "source_isolated" (points left out of the registration as scattered
            outliers, ``RegisterConfig.isolated_radius`` and ``isolated_spacings``), and the
            target's}.
        network_transformation: (4, 4) the network's own estimate from the pose as given, before
            ICP; None when the network did not run (a feature match tried first was confident).
        points_used: points per cloud (source, target) at each stage: "network", "attempts"
            (the work clouds) and "final" (the registered clouds).
        constraint: how firmly the geometry fixes the pose: smallest over largest eigenvalue of
            the point-to-plane normal equations at the result (0-1, higher is better; below
            ``degeneracy.min_constraint`` the result is flagged with confidence 0). None where the
            clouds share their points (spacing ratio under ``degeneracy.shared_below``, on clouds
            that are not evenly spaced grids): their points fix the pose, and it is not measured.
        flatness: how well the clouds still fit with the source turned 30 degrees, over the
            result's fit (0-1, lower is better; from ``degeneracy.max_flatness`` = 0.85 the result
            is flagged with confidence 0). None where the clouds share their points.
        copy_transformation: (4, 4) where both clouds look complete and the trusted pose shows no
            shared point: the result followed by a half turn of the source about one of its
            axes, refined by ICP, that fits the clouds closest (:mod:`o3dsoft.symmetry`); or,
            where the surfaces hold a trusted pose loosely (``degeneracy.probe_below``), a pose
            ICP reached from it moved along the motion they hold least that fits about as
            closely; None where not probed or every copy came back to the result.
        copy_fit: its input Chamfer distance over the result's (higher is better for the
            result; at most ``symmetry.max_ratio`` = 1.1: the two fit as closely, the shape is
            symmetric, and the confidence is halved).
        agreeing: how many of the attempts reached the result's pose (within
            ``confidence.agree_deg`` and ``agree_shift``; at least 1): on a partial overlap whose
            pose shows no shared point the confidence weighs it
            (:func:`~o3dsoft.confidence.partial_confidence`).
        target_consistency: on scans whose result the strict confidence alone trusts: the
            consistency seen from the target's side (the target onto the source by the inverse
            pose; 0-1, higher is better); where the strict confidence flags it from there, so is
            the result. None where not measured (also where one cloud's points are over 1.5 times
            sparser: both sides would count the same cloud's).
        sparser_moved: the target was much sparser than the source (``sparser_moves``), so it was
            registered onto the source and the result inverted; every field still speaks of the
            source onto the target.
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
    constraint: Optional[float] = None
    flatness: Optional[float] = None
    failure_reason: Optional[str] = None
    voxel: Optional[float] = None
    icp_method: str = "point"
    estimate_from: str = "network"
    sparser_moved: bool = False
    copy_transformation: Optional[np.ndarray] = None
    copy_fit: Optional[float] = None
    agreeing: int = 1
    search_reason: Optional[str] = None
    target_consistency: Optional[float] = None

    def __post_init__(self) -> None:
        # A read-only float64 copy of each transform: a caller scaling its own copy in place
        # cannot change the result, nor another result that shares the array.
        for name in TRANSFORM_FIELDS:
            value = getattr(self, name)
            if value is not None:
                frozen = np.array(value, dtype=np.float64)
                frozen.flags.writeable = False
                object.__setattr__(self, name, frozen)

    def __setstate__(self, state: Dict[str, Any]) -> None:
        # Unpickled (a worker pool's result) or deep-copied: read-only again.
        self.__dict__.update(state)
        self.__post_init__()

    def __repr__(self) -> str:
        """A few lines: the verdict, the main scores (with units) and the transform."""
        verdict = f"likely failed: {self.failure_reason}" if self.likely_failed else "trusted"
        matrix = np.array2string(np.asarray(self.transformation), precision=6, suppress_small=True, max_line_width=100)
        return (
            f"RegistrationResult({verdict}; confidence {self.confidence:.3f} (0-1, higher is better), "
            f"fitness {self.fitness:.3f} (higher is better), inlier_rmse {self.inlier_rmse:.4g} cloud units (lower is better), "
            f"from {self.estimate_from}, {self.num_source:,} / {self.num_target:,} points)\ntransformation (T_target_source):\n{matrix}"
        )

    def to_dict(self) -> dict:
        """JSON-ready dict (arrays as nested lists); :meth:`from_dict` reads it back."""
        d = asdict(self)
        for name in TRANSFORM_FIELDS:
            if d[name] is not None:
                d[name] = np.asarray(d[name]).tolist()
        return d

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "RegistrationResult":
        """The result :meth:`to_dict` gave (or ``register --json`` printed: its other keys, such as
        source, target, model, init and errors, are left aside), with (4, 4) float64 arrays.

        Raises:
            InputError: `d` lacks a field the result needs, a transform is not a rigid (4, 4)
                one, a field holds another type than its own (a string for True or False, None
                where the field is not optional), or ``confidence`` or ``fitness`` lies outside
                [0, 1].
        """
        from .config import _check_types

        if not isinstance(d, dict):
            raise InputError(f"not a registration result: expected a dict, got {type(d).__name__}")
        names = [f.name for f in fields(cls)]
        needed = [f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING]
        missing = [name for name in needed if name not in d]
        if missing:
            raise InputError(f"not a registration result: no {', '.join(missing)}")
        values = {name: d[name] for name in names if name in d}
        for name in TRANSFORM_FIELDS:
            if values.get(name) is not None:
                T = np.array(values[name], dtype=np.float64)
                if T.shape != (4, 4):
                    raise InputError(f"{name}: expected a 4x4 transform, got shape {T.shape}")
                check_rigid(T, name)  # a scaled, sheared or non-finite one: refused by name
                values[name] = T
        for name in ("timings_ms", "removed", "points_used"):
            if name in values and not isinstance(values[name], dict):
                raise InputError(f"{name} must be a mapping, got {values[name]!r}")
        values["points_used"] = {stage: tuple(counts) for stage, counts in values.get("points_used", {}).items()}
        result = cls(**values)
        _check_types(result, "")  # "false" would read as true
        for name in ("confidence", "fitness"):
            if not 0 <= getattr(result, name) <= 1:
                raise InputError(f"{name} must be in [0, 1], got {getattr(result, name)}")
        return result


# The result's (4, 4) T_target_source fields (the last two may be None).
TRANSFORM_FIELDS = ("transformation", "coarse_transformation", "network_transformation", "copy_transformation")


def _each_transform(result: RegistrationResult, change: Callable[[np.ndarray], np.ndarray]) -> RegistrationResult:
    """`result` with `change` applied to each of its :data:`TRANSFORM_FIELDS` that is set."""
    changed: Dict[str, Any] = {name: change(getattr(result, name)) for name in TRANSFORM_FIELDS if getattr(result, name) is not None}
    return replace(result, **changed)


@quietly
def register(
    source: CloudLike,
    target: CloudLike,
    config: Optional[RegisterConfig] = None,
    model: Optional[coarse_stage.CoarseModel] = None,
    search_model: Optional[coarse_stage.CoarseModel] = None,
    source_name: str = "source",
    target_name: str = "target",
    init: Optional[np.ndarray] = None,
) -> RegistrationResult:
    """Find T_target_source, the rigid transform that maps `source` onto `target`.

    Args:
        source: (N, 3) array, torch tensor or Open3D PointCloud (legacy or tensor), any units and
            position. Only the positions are read: a cloud's normals and colours are not used
            (ICP estimates the normals it needs on the clouds it registers).
        target: (M, 3), the same kinds, in the same units as source.
        config: pipeline settings (None: the defaults, ``RegisterConfig()``).
        model: an already loaded model (else loaded from ``config.weights``).
        search_model: an already loaded search network (else loaded from
            ``config.search.starts.weights`` when the search needs it).
        The networks this call loads itself (``config.weights``, the search's and
        ``config.second_network``'s) are loaded once per process
        (:func:`o3dsoft.coarse.cached_model`).
        source_name, target_name: how to call the clouds in error messages (e.g. file names).
        init: (4, 4) an initial guess of T_target_source (odometry, a previous frame's pose): the
            source starts there, ICP from it is the first estimate tried, and where it is trusted
            neither the feature match nor the network runs; ``config.max_rotation`` then bounds
            the turn away from it. The result is still T_target_source of the clouds as given.
    Returns:
        RegistrationResult.
    Raises:
        InputError: a cloud is degenerate (too few points, identical or collinear points), the
            weights file is unusable, `init` is not a rigid 4x4 transform, or a setting of
            `config` is invalid (see its ``validate``).
        UsageError: what cannot run as asked: a missing weights file, an unknown device,
            ``num_points`` below the network's neighbourhood size. Both are
            :class:`o3dsoft.O3dsoftError` (and ``ValueError``).
    """
    config = _checked(config, model, search_model)
    src, tgt = as_points(source, source_name), as_points(target, target_name)
    return _register_as_given(src, tgt, config, model, search_model, source_name, target_name, init)


@quietly
def register_cleaned(
    source: CleanReport,
    target: CleanReport,
    config: RegisterConfig,
    model: coarse_stage.CoarseModel,
    source_name: str = "source",
    target_name: str = "target",
    init: Optional[np.ndarray] = None,
) -> RegistrationResult:
    """:func:`register` for two clouds the caller cleaned (``clean_points(points, name,
    min_points=model.config.k)``, or :func:`o3dsoft.preprocess.clean_each` and ``Cleaning.of``):
    multiway cleans each scan once, not once per pair it is in.

    Args:
        source: the (N, 3) cleaned source and what cleaning removed of it; target: the (M, 3) same.
        config, model, init: as ``register``'s (the model loaded already; the search network is
            loaded from the config where the search needs it).
    As ``register``, with ``removed`` counting what the caller's cleaning removed, and the test
    of which cloud is sparser made on the cleaned clouds (``register`` makes it on the clouds as
    given, where a cloud of many duplicate points reads as dense).

    Raises:
        UsageError: `source` or `target` is not a CleanReport.
        InputError: a cloud holds fewer points than the network's K.
    """
    for cloud, name in ((source, source_name), (target, target_name)):
        if not isinstance(cloud, CleanReport):
            raise UsageError(
                f"{name}: register_cleaned takes o3dsoft.preprocess.CleanReport clouds (clean_points, or Cleaning.of(points)), got {type(cloud).__name__}"
            )
        if len(cloud.points) < model.config.k:
            raise InputError(f"{name}: {len(cloud.points)} distinct finite points; at least {model.config.k} are needed")
    return _register_as_given(source, target, _checked(config, model, None), model, None, source_name, target_name, init)


def _checked(config: Optional[RegisterConfig], model: Optional[coarse_stage.CoarseModel], search_model: Optional[coarse_stage.CoarseModel]) -> RegisterConfig:
    """`config` (None: the defaults) once every setting, the networks passed in and the weights
    files to be loaded are checked, before any stage reads them (the network's own limits:
    ``config.validate``)."""
    config = RegisterConfig() if config is None else config
    if not isinstance(config, RegisterConfig):
        raise UsageError(f"config must be an o3dsoft.RegisterConfig, got {type(config).__name__}")
    check_settings(config)
    coarse_stage.torch_runs()
    coarse_stage.check_loaded(model, "model", "RegisterConfig(weights=...)")
    coarse_stage.check_loaded(search_model, "search_model", "RegisterConfig(search=SearchConfig(starts=StartsConfig(weights=...)))")
    _check_weights(config, model is None, search_model is None)
    return config


def _register_as_given(
    src: Union[np.ndarray, CleanReport],
    tgt: Union[np.ndarray, CleanReport],
    config: RegisterConfig,
    model: Optional[coarse_stage.CoarseModel],
    search_model: Optional[coarse_stage.CoarseModel],
    source_name: str,
    target_name: str,
    init: Optional[np.ndarray],
) -> RegistrationResult:
    """:func:`register`'s work on the (N, 3) and (M, 3) clouds as given, raw or cleaned already."""
    centre = sample_median(_points_of(src))  # a point in the source's middle: a stray point does not move it
    if init is not None:
        init = as_rigid(init, "init")
        src = _moved(src, lambda p: apply_transform(init, p))
    # Far from the origin (georeferenced scans), both clouds are registered about the target's
    # median: point-to-plane ICP linearises the rotation about the origin, and KISS-Matcher hashes
    # integer voxel coordinates.
    origin = local_origin(_points_of(tgt))
    if origin.any():
        src, tgt = _moved(src, lambda p: p - origin), _moved(tgt, lambda p: p - origin)
    guess = init is not None
    if _sparser(_points_of(tgt), _points_of(src), config.sparser_moves):
        # The sparser cloud moves: register the target onto the source, and answer the question asked.
        swapped, (moved, fixed) = _register(tgt, src, config, model, search_model, target_name, source_name, guess)
        result = _inverted(swapped, fixed, moved)
    else:
        result = _register(src, tgt, config, model, search_model, source_name, target_name, guess)[0]
    return _as_given(result, origin, init, centre)


def _points_of(cloud: Union[np.ndarray, CleanReport]) -> np.ndarray:
    """The (N, 3) points of a raw or a cleaned cloud."""
    return cloud.points if isinstance(cloud, CleanReport) else cloud


def _moved(cloud: Union[np.ndarray, CleanReport], move: Callable[[np.ndarray], np.ndarray]) -> Union[np.ndarray, CleanReport]:
    """A raw or a cleaned cloud with its (N, 3) points moved by `move`."""
    return cloud._replace(points=move(cloud.points)) if isinstance(cloud, CleanReport) else move(cloud)


@quietly
def register_on_grid(
    source: GridCloud,
    target: GridCloud,
    config: RegisterConfig,
    model: coarse_stage.CoarseModel,
    source_name: str = "source",
    target_name: str = "target",
    init: Optional[np.ndarray] = None,
) -> RegistrationResult:
    """:func:`register` for two clouds the caller cleaned and put on one grid
    (:func:`o3dsoft.pair.on_grid`): odometry prepares each sweep once, not once per map it is in.

    Args:
        source: (N, 3) on the grid where `init` moves it (gridded in the target's frame, as
            ``register`` grids both clouds: two grids turned against each other leave the
            centroids of one surface in two patterns, and ICP ends further off; docs/multiway.md).
        target: (M, 3) on the same grid.
        config: the pipeline's settings, checked by the caller.
        init: (4, 4) the rigid transform that moved the source (None: none); the result is
            T_target_source of the source before it, as ``register``'s from an initial guess.
    As ``register``, but: every estimate is refined and scored on the whole grid clouds (up to
    :data:`~o3dsoft.pair.GRID_WORK_ATTEMPTS` times ``attempt_points`` each; no coarser grid); a flagged reason's size ratio is
    the grids'; ``removed`` counts what the caller's cleaning removed; the sparser cloud is never
    the one moved (on one grid both are spaced alike down to a cell).
    """
    centre = sample_median(source.points)
    if init is not None:  # a point in the middle of the source as given
        centre = apply_transform(np.linalg.inv(init), centre[None])[0]
    origin = local_origin(target.points)  # as register: far from the origin, about the target's median
    if origin.any():
        shift = np.eye(4)
        shift[:3, 3] = -origin
        source, target = source.moved(shift), target.moved(shift)
    result = _register(source, target, config, model, None, source_name, target_name, init is not None)[0]
    return _as_given(result, origin, init, centre)


def _as_given(result: RegistrationResult, origin: np.ndarray, init: Optional[np.ndarray], centre: np.ndarray) -> RegistrationResult:
    """A result registered about the (3,) `origin` from the (4, 4) `init` (None: none) turned into
    the result for the clouds as given. Rotations made of float32 network passes are orthonormal
    to about 1e-7: made rigid to float64 precision, each transform taking the source's (3,)
    middle point `centre` where it did."""
    result = _started_at(_moved_back(result, origin), init)
    return _each_transform(result, lambda T: nearest_rigid(T, centre))


def _check_weights(config: RegisterConfig, main: bool, search: bool) -> None:
    """Raise UsageError naming the setting whose model file does not exist (nor names a shipped
    model): every network the pipeline may load (the main and the search network only where
    `main` and `search`: not passed in; the search network not with the search off), before any runs, so that a mistyped name fails on the
    first pair rather than on the first pair hard enough to reach its stage."""
    for name, weights, loaded in (
        ("weights", config.weights, main),
        ("second_network.weights", config.second_network.weights, True),
        ("search.starts.weights", config.search.starts.weights, search and config.search.mode != "off"),
    ):
        if loaded and (weights is not None or name == "weights"):
            try:
                coarse_stage.weights_file(weights)
            except UsageError as e:
                raise UsageError(f"{name}: {e}") from None


def _started_at(result: RegistrationResult, init: Optional[np.ndarray]) -> RegistrationResult:
    """A result for the source moved by (4, 4) `init` turned into the result for the source as
    given: each transform T becomes T @ init."""
    if init is None:
        return result
    return _each_transform(result, lambda T: T @ init)


def _moved_back(result: RegistrationResult, origin: np.ndarray) -> RegistrationResult:
    """A result for the clouds less (3,) `origin` turned into the result for the clouds as given,
    whose frame's origin lies at -origin of the frame registered in: each transform's rotation
    unchanged, its translation t' + origin - R origin."""
    if not origin.any():
        return result
    return _each_transform(result, lambda T: in_frame_at(T, -origin))


def _register(
    source: Union[np.ndarray, CleanReport, GridCloud],
    target: Union[np.ndarray, CleanReport, GridCloud],
    config: RegisterConfig,
    model: Optional[coarse_stage.CoarseModel],
    search_model: Optional[coarse_stage.CoarseModel],
    source_name: str,
    target_name: str,
    guess: bool = False,
) -> Tuple[RegistrationResult, Clouds]:
    """:func:`register` with the roles as given (raw clouds, two cleaned already, or two
    :class:`~o3dsoft.pair.GridCloud` prepared already); also the (source, target) clouds the result was registered on (cleaned, on
    the grid). `guess`: the pose as given is the caller's initial guess, tried first."""
    clock = StageClock()
    if model is None:  # loaded once per process; callers may pass it in
        model = coarse_stage.cached_model(config.weights, config.device)
        clock.lap("load_model")
    config.validate(model.config.k)
    search = config.search

    # Prepare: clean, voxel grid, the network's normalised samples, the work clouds.
    pair = PreparedPair(source, target, config, model.config.k, (source_name, target_name), clock)
    verifier = Verifier(pair, clock)
    network = NetworkPass(model, config.coarse_iterations)

    # Propose: on a partial overlap the feature match first (the network, trained on complete
    # shapes, is seldom confident there); then the network, unless that was confident; then, while
    # nothing is and the feature match did not go first, the second network (the first matches
    # points; two samplings of a surface share none). Not on scans (``pair.scans``): the search's
    # feature match solves those the first network leaves, and the second was never right there
    # (docs/scans.md).
    clock.lap("sample_normalise")
    if guess:  # the caller's initial guess first; trusted, it ends the proposals
        InitialGuess().propose(pair, verifier)
    guessed = guess and verifier.confident()
    features_first = search.features_on and pair.looks_partial and not guessed
    if features_first:
        _match_features(pair, verifier)
    if not ((features_first or guessed) and verifier.confident()):
        network.propose(pair, verifier)
    second_pending = config.second_network.weights is not None and not features_first and not guessed and not pair.scans
    second_ends = False
    if second_pending and not verifier.confident():
        second_ends = _second_network(pair, verifier)
        second_pending = False
        if second_ends:
            _check_shared_points(pair, verifier)

    # Search while nothing is confident (and the second network's pose of two complete-looking
    # clouds is not trusted by the complete confidence): feature match, networks from many starts,
    # votes, restart.
    search_reason: Optional[str] = None  # why the search ran; None while it has not
    if features_first:
        search_reason = "the clouds look like a partial overlap: the feature match goes first"
    elif search.mode == "always":
        search_reason = "the search mode is 'always'"
    elif search.mode == "auto" and not verifier.confident() and not second_ends:
        search_reason = "no estimate was trusted"
    if search_reason and search.mode != "quick":  # "quick": the feature match that went first is all of it
        _search(pair, verifier, model, search_model, features_done=features_first)

    # Select the most trusted, then refine it at full resolution, where it is trusted or not.
    chosen = _select(verifier)
    unrefined = not config.refine_flagged and verifier.reported(chosen).trust < config.confidence.likely_failed_below  # left as the work clouds gave it
    best = chosen if unrefined else _refine_full(pair, verifier, chosen)
    if search.mode == "auto" and not search_reason and verifier.reported(best).trust < config.confidence.likely_failed_below:
        # Trusted on the work clouds, not on the clouds it is the answer for: search after all.
        verifier.distrust(chosen, best.trust)
        search_reason = "the estimate trusted on the work clouds was not trusted at full resolution"
        _search(pair, verifier, model, search_model, features_done=False)
        best = _refine_full(pair, verifier, _select(verifier))
    # Report: where both clouds look complete and the pose shows no shared point, the confidence
    # that weighs the overlap too; on scans, the one of the overlap on the other scan's surface;
    # on other partial overlaps, the one of how many attempts reached the pose (the search ran by
    # the strict one).
    best = verifier.reported(best)
    level = _scored_level(pair, unrefined)
    target_side = _target_side(pair, best, level)
    clock.lap("score")
    geometry = _assess(pair, best)
    clock.lap("degeneracy")
    closer, alike = _probe_loosest(pair, verifier, best, geometry)
    if closer is not None:  # along the motion the surfaces hold least, ICP found a pose that fits clearly closer
        best, geometry = closer, _assess(pair, closer)
        target_side = _target_side(pair, best, level)
    clock.lap("degeneracy")
    if search.mode == "auto" and not search_reason and geometry.reason and (guess or not pair.scans) and verifier.shares_no_point(best):
        # Trusted, but the pose does not hold and shows no shared point: on two independent
        # samplings a wrong pose that fits a part closely is trusted strictly and fits as well
        # turned. (A symmetric shape's right pose shows the points noisy clouds share; on scans
        # the test flags surfaces that slide, but from a caller's guess nothing else was tried:
        # a guess turned 90 degrees on a street scan ends there.) What a flag starts runs now, the flagged estimate
        # out of the choice; what it finds replaces the flagged result only where it fits the
        # clouds clearly closer (a turn of a symmetric shape fits as well, and stays flagged).
        verifier.distrust(chosen, 0.0)
        if second_pending:
            _second_network(pair, verifier)
        search_reason = "the trusted pose is not fixed by the geometry and shows no shared point"
        _search(pair, verifier, model, search_model, features_done=False)
        found = verifier.reported(_refine_full(pair, verifier, _select(verifier)))
        if _fits_closer(pair, found, best, search.undetermined_gain):
            held = _assess(pair, found)
            # From the caller's guess, a pose the geometry does not fix either is no better answer: the guess's stays.
            if not (guess and held.reason):
                best, geometry = found, held
        clock.lap("degeneracy")
    settings = pair.config.degeneracy
    if guess and settings.held_from > 0 and geometry.constraint is not None and geometry.constraint < settings.min_constraint:
        # Along what the surfaces leave free (a corridor's length), ICP slides on noise: the guess is the better answer there.
        best = _held_by_surfaces(pair, best, level)
        kept = (
            "the initial guess is kept"
            if np.array_equal(best.fine.transformation, np.eye(4))
            else "along the motions the surfaces leave free, the initial guess is kept"
        )
        geometry = geometry._replace(reason=f"{geometry.reason}; {kept}")
        clock.lap("degeneracy")
    # Whether a symmetric copy fits as closely: nothing measured on the clouds tells the two apart.
    copy = _probe_symmetry(pair, verifier, best, geometry)
    if copy.reason is None and alike.reason is not None:
        copy = alike
    clock.lap("symmetry")
    clock.timings_ms["total"] = sum(clock.timings_ms.values())
    return _result(best, pair, verifier, network, search_reason, geometry, copy, target_side, clock.timings_ms, level), pair.clouds(level)


def _held_by_surfaces(pair: PreparedPair, best: Attempt, level: str) -> Attempt:
    """`best` with its motion from the caller's guess (the identity here) kept only along the
    directions the surfaces hold (:func:`o3dsoft.degeneracy.held_motion`), scored again on the
    clouds at `level`."""
    src, tgt = pair.clouds(level)
    T = degeneracy_stage.held_motion(src, tgt, best.fine.transformation, pair.distance, pair.config.degeneracy)
    return best._replace(fine=refine_stage.evaluate(src, tgt, T, pair.distance))


def _scored_level(pair: PreparedPair, unrefined: bool) -> str:
    """The clouds the kept estimate was last refined and scored on: "full" where it was refined
    again at full resolution (:func:`_refine_full`), "work" otherwise (the same clouds where the
    work clouds are not reduced)."""
    return "full" if pair.config.refine and pair.reduced and not unrefined else "work"


def _assess(pair: PreparedPair, best: Attempt) -> degeneracy_stage.Degeneracy:
    """Whether the geometry determines `best`'s pose, on the screen clouds (evenly spaced, at most
    search.screen.points): a test that can only flag, and off a grid only clouds that share no
    point (theirs fix the pose otherwise). On a grid no point is shared (each cloud's cells
    average its own points), though the cells' centroids of two dense scans lie as close as
    shared points would: a tunnel's two stations are assessed whatever their spacing ratio."""
    return degeneracy_stage.assess(
        *pair.clouds("screen"),
        best.fine.transformation,
        pair.distance,
        pair.norm.scale,
        best.scored.spacing_ratio if pair.voxel is None else math.inf,
        pair.config.degeneracy,
        lambda: pair.scorer("screen"),
    )


def _target_side(pair: PreparedPair, best: Attempt, level: str) -> Optional[confidence_stage.Features]:
    """On scans whose result the strict confidence alone trusts (not the scan confidence): the
    alignment scored from the target's side, the target onto the source by the inverse pose, on
    the clouds at `level` (where `best` was scored); None where not measured. ICP and the choice
    tune a pose to the source's side, and on noisy scans that overlap little a wrong pose can fit
    that side closely (noise thickens the surfaces); a right one fits from both (docs/scans.md).
    Not measured where one cloud is over ``confidence.spacings`` times sparser: the scorer counts
    the sparser cloud's points from either side, so the two sides would be one."""
    c = pair.config.confidence
    if not pair.scans or best.trust < c.likely_failed_below or confidence_stage.scan_confidence(best.scored, c) >= c.likely_failed_below:
        return None
    forward, reverse = pair.scorer(level), pair.scorer(level, reverse=True)
    if forward.swapped or reverse.swapped:
        return None
    return reverse(np.linalg.inv(best.fine.transformation))


def _probe_symmetry(pair: PreparedPair, verifier: Verifier, best: Attempt, geometry: degeneracy_stage.Degeneracy) -> symmetry_stage.Symmetry:
    """The half-turned copy of a trusted result that fits the work clouds closest
    (:func:`o3dsoft.symmetry.probe`), where the geometry determines the pose and either both
    clouds look complete and the pose shows no shared point, or both scans are closed surfaces
    (complete objects on a grid, whose centroids look like shared points); otherwise not probed.
    (Clouds that share points fix the pose by them; on views, scenes and partial overlaps a turned
    copy seldom fits.)"""
    config = pair.config
    probed = config.symmetry.enabled and config.refine and geometry.reason is None and best.trust >= config.confidence.likely_failed_below
    # Off a grid, a pose that shows shared points is fixed by them; on one, the cells' centroids
    # look like shared points at any pose.
    sampled_apart = verifier.shares_no_point(best) or pair.voxel is not None
    if not (probed and sampled_apart and (pair.complete or _closed_objects(pair))):
        return symmetry_stage.NOT_PROBED
    work = pair.clouds("work")
    normals, tree = pair.target_normals("work"), pair.target_tree("work")  # estimated once for every copy
    icp = lambda T: refine_stage.icp(*work, T, pair.distance, config.icp, normals, tree).transformation  # noqa: E731 - ICP alone: the copies are not scored
    return symmetry_stage.probe(*work, best.fine.transformation, icp, config.symmetry, verifier.admissible)


def _probe_loosest(
    pair: PreparedPair, verifier: Verifier, best: Attempt, geometry: degeneracy_stage.Degeneracy
) -> Tuple[Optional[Attempt], symmetry_stage.Symmetry]:
    """Where a trusted result's pose of two scans is held loosely (``constraint`` under
    ``degeneracy.probe_below``), ICP from the pose moved along the motion its surfaces hold least
    (:func:`o3dsoft.degeneracy.probe_starts`), on the screen clouds. A part that fits closely (a
    mug's body) can hold a pose that leaves the part that fixes it (the handle) without partners;
    the right pose then fits both clouds clearly closer. Of the poses reached away from the result
    that the reported confidence trusts, the one that fits the screen clouds closest is refined and
    scored on the work clouds; returns it where it fits them ``search.undetermined_gain`` times
    closer (input Chamfer distance; else None), and, where it fits within ``symmetry.max_ratio``
    of the result, that pose as a copy that fits as closely (its reason says so; else
    :data:`~o3dsoft.symmetry.NOT_PROBED`)."""
    config = pair.config
    settings = config.degeneracy
    none = (None, symmetry_stage.NOT_PROBED)
    loose = geometry.constraint is not None and geometry.constraint < settings.probe_below
    # Scans only: on small clouds (not scans) a pose a few degrees away fits as closely, and complete shapes have the symmetry probe.
    if not (pair.scans and config.refine and loose and geometry.reason is None and geometry.loosest is not None and geometry.centre is not None):
        return none
    if best.trust < config.confidence.likely_failed_below:  # `best` carries the reported confidence
        return none
    T0 = best.fine.transformation
    screen = pair.clouds("screen")
    reached = []
    for start in degeneracy_stage.probe_starts(T0, geometry.loosest, geometry.centre, pair.norm.scale, settings.probe_steps):
        s = verifier.refine(start, start, "screen", by=best.by)
        if not verifier.same_pose(s.fine.transformation, T0) and verifier.reported(s).trust >= config.confidence.likely_failed_below:
            reached.append((input_chamfer_distance(*screen, s.fine.transformation), s))
    if not reached:
        return none
    found = min(reached, key=lambda r: r[0])[1]
    found = verifier.reported(verifier.refine(found.fine.transformation, found.coarse, icp=config.icp.tight(), by=best.by))
    T = found.fine.transformation
    if verifier.same_pose(T, T0) or found.trust < config.confidence.likely_failed_below:
        return none
    work = pair.clouds("work")
    ratio = input_chamfer_distance(*work, T) / max(input_chamfer_distance(*work, T0), 1e-300)
    if ratio * config.search.undetermined_gain <= 1.0:
        return verifier.reported(_refine_full(pair, verifier, found)), symmetry_stage.NOT_PROBED
    if ratio > config.symmetry.max_ratio:
        return none
    turn = rotation_angle_deg(T[:3, :3] @ T0[:3, :3].T)
    reason = (
        f"the surfaces hold the pose loosely (constraint {geometry.constraint:.1e}): moved along the motion they hold least, ICP finds a pose "
        f"{turn:.0f} degrees away that fits the clouds {'closer' if ratio < 1 else 'as closely'} (input Chamfer distance {ratio:.2f} times "
        "the result's), and nothing measured on the clouds tells the two apart"
    )
    return None, symmetry_stage.Symmetry(T, ratio, turn, reason)


def _closed_objects(pair: PreparedPair) -> bool:
    """Both clouds are scans of one closed surface each (:func:`o3dsoft.symmetry.closed_share` on
    the screen clouds at least ``symmetry.closed_from``) with the same profile of distances to
    their centroids: two complete scans of an object."""
    if not pair.scans or pair.looks_partial:
        return False
    neighbours, closed = pair.config.icp.normal_neighbours, pair.config.symmetry.closed_from
    return all(symmetry_stage.closed_share(c, refine_stage.normals(c, neighbours), at_least=closed) >= closed for c in pair.clouds("screen"))


def _fits_closer(pair: PreparedPair, new: Attempt, old: Attempt, gain: float) -> bool:
    """`new`'s pose fits the work clouds `gain` times closer than `old`'s: input Chamfer distance
    (:func:`o3dsoft.metrics.input_chamfer_distance`) at most the old one over `gain`."""
    work = pair.clouds("work")
    return gain * input_chamfer_distance(*work, new.fine.transformation) <= input_chamfer_distance(*work, old.fine.transformation)


def _sparser(target: np.ndarray, source: np.ndarray, factor: float) -> bool:
    """The (M, 3) target's points are over `factor` times sparser on its surface than the (N, 3)
    source's (finite rows only): its point spacing over sqrt(`factor`) times the source's. Points
    per squared :func:`~o3dsoft.preprocess.scene_size` screen for it first, so that the spacings
    (a KD-tree per cloud) are measured only where the counts already suggest it."""
    if factor == 0:
        return False
    target, source = (_finite_rows(c) for c in (target, source))
    if min(len(target), len(source)) < 2:
        return False
    with np.errstate(all="ignore"):  # absurd coordinates are cleaning's to report, by name
        size_t, size_s = scene_size(target), scene_size(source)
        if not (np.isfinite([size_t, size_s]).all() and min(size_t, size_s) > 0):
            return False
        # factor x density(target) < density(source), density = points / size^2, in logarithms
        if np.log(factor * len(target)) + 2 * np.log(size_s) >= np.log(len(source)) + 2 * np.log(size_t):
            return False
        return bool(point_spacing(target) > np.sqrt(factor) * point_spacing(source))


def _finite_rows(points: np.ndarray) -> np.ndarray:
    """The (N, 3) points' finite rows: the points themselves where all are (cleaned clouds: no copy)."""
    finite = np.isfinite(points).all(axis=1)
    return points if finite.all() else points[finite]


def _inverted(result: RegistrationResult, source: np.ndarray, target: np.ndarray) -> RegistrationResult:
    """A result of registering `target` onto `source` turned into the result for `source` onto
    `target`: transforms inverted, per-cloud counts swapped, fitness and RMSE measured again from
    the source's side, on the (N, 3) and (M, 3) clouds the registration used."""
    result = _each_transform(result, np.linalg.inv)
    scored = refine_stage.evaluate(source, target, result.transformation, result.correspondence_distance)
    removed = {f"{'target' if key.startswith('source') else 'source'}{key[key.index('_') :]}": n for key, n in result.removed.items()}
    return replace(
        result,
        fitness=scored.fitness,
        inlier_rmse=scored.inlier_rmse,
        num_source=result.num_target,
        num_target=result.num_source,
        points_used={stage: (n_t, n_s) for stage, (n_s, n_t) in result.points_used.items()},
        removed=removed,
        sparser_moved=True,
        # measured with the roles swapped: the target's side of the registration is the source's here
        consistency=result.consistency if result.target_consistency is None else result.target_consistency,
        target_consistency=None if result.target_consistency is None else result.consistency,
    )


def _search(pair: PreparedPair, verifier: Verifier, model, search_model, features_done: bool) -> None:
    """The global search's strategies in turn, each while nothing is confident: the feature match
    (unless done), the networks from many starts (after the feature match, only the search
    network's around the pose as given), translation votes, and the optional restart."""
    config = pair.config
    verifier.begin_search()
    if config.search.features_on and not features_done:
        _match_features(pair, verifier)
    if not verifier.confident():
        NetworkStarts(model, search_model, cube=not config.search.features_on).propose(pair, verifier)
    if config.search.features_on and not verifier.confident():
        TranslationVotes().propose(pair, verifier)
    if config.refine and config.search.restart.enabled and not verifier.settled():
        Restart().propose(pair, verifier)


def _second_network(pair: PreparedPair, verifier: Verifier) -> bool:
    """The second network's passes from the pose as given (skipped on samples smaller than its
    neighbourhood size K, which only a network with a larger K than the first one meets); where
    that pose neither is trusted nor ends the search and both clouds look complete, its passes
    from the other rotations of a cube (``second_network.turns``), counted as the search's
    estimates. Returns whether its result ends the search: both clouds look complete, its pose
    shows no shared point and the complete confidence reaches ``second_network.ends_search``; a
    turned estimate ends it only where the choice takes it over the pose as given."""
    settings = pair.config.second_network
    model = coarse_stage.cached_model(settings.weights, pair.config.device)
    if min(len(pair.net[0]), len(pair.net[1])) < model.config.k:
        return False

    def ends(attempt: Attempt) -> bool:
        return (
            settings.ends_search is not None
            and pair.complete
            and verifier.shares_no_point(attempt)
            and verifier.reported(attempt).trust >= settings.ends_search
        )

    NetworkPass(model, settings.iterations, stage="second_network", name="second network").propose(pair, verifier)
    if ends(verifier.attempts[-1]):
        return True
    if settings.turns == 0 or not pair.complete or verifier.confident():
        return False
    # Counted as the search's: on a symmetric shape a turned copy scores as well as the right pose
    # as given, so a turned estimate replaces it only at the search's odds.
    verifier.begin_search()
    turned = TurnedPasses(model, settings.iterations, settings.turns)
    turned.propose(pair, verifier)
    chosen = verifier.most_trusted()
    return any(a is chosen for a in turned.attempts) and ends(chosen)


def _check_shared_points(pair: PreparedPair, verifier: Verifier) -> None:
    """Before the second network's pose ends the search: the feature match's first
    ``second_network.shared_check`` candidates, as the search's estimates. Clouds that share
    points look like two independent samplings at a wrong pose; their right pose is most often
    among these, the strict confidence trusts it, and the choice takes it."""
    count = pair.config.second_network.shared_check
    if pair.config.search.features_on and count > 0:
        verifier.begin_search()
        FeatureMatchProposals(limit=count).propose(pair, verifier)


def _match_features(pair: PreparedPair, verifier: Verifier) -> None:
    """The search's matching strategies: KISS-Matcher's estimate on scans (where installed), then
    FPFH + RANSAC's while none is trusted enough to end the feature match."""
    kiss = pair.config.search.kiss and pair.scans and kiss_available()
    if kiss:
        KissMatcherProposal().propose(pair, verifier)
    if not (kiss and verifier.settled()):
        FeatureMatchProposals().propose(pair, verifier)


def _refine_full(pair: PreparedPair, verifier: Verifier, best: Attempt) -> Attempt:
    """The kept estimate refined again and scored at full resolution when the work clouds were
    reduced (as it is otherwise: its ICP ended on these clouds): with point-to-plane ICP (scans),
    by ICP's last stage only (:meth:`~o3dsoft.refine.ICPConfig.final`: it has converged through
    the whole schedule on the work clouds, and the wider stages would pull it towards the parts
    with no partner); with point-to-point ICP, by the tight stages (their noise rounds keep a noisy
    pair's true partners)."""
    if not pair.config.refine or not pair.reduced:
        return best
    icp = pair.config.icp.final() if pair.config.icp.method == "plane" else pair.config.icp.tight()
    return verifier.refine(best.fine.transformation, best.coarse, "full", icp, by=best.by)


def _select(verifier: Verifier) -> Attempt:
    """The most trusted attempt (:meth:`Verifier.most_trusted`); under a rotation prior, when none
    is within the bound, the pose as given (refined if ICP keeps it within)."""
    best = verifier.most_trusted()
    if verifier.admissible(best.fine.transformation):
        return best
    identity = np.eye(4)
    best = verifier.refine(identity, identity, by="pose as given")
    if verifier.admissible(best.fine.transformation):
        return best
    # ICP leaves the bound from there too: the clouds disagree with the prior.
    return verifier.refine(identity, identity, refine=False, by="pose as given")._replace(trust=0.0)


# The close of a flagged result's reason where the search ran.
_SEARCHED = "; the global search found nothing clearly better"


def _apart_reason(best: Attempt, config: RegisterConfig) -> Optional[str]:
    """Why a flagged pose does not bring the clouds into contact, in words: the rotation prior
    (``max_rotation``) turned it away or left it as given, or the clouds barely touch; None where
    it does (or the pose is trusted)."""
    if best.trust >= config.confidence.likely_failed_below:
        return None
    bound = config.max_rotation
    turn = rotation_angle_deg(best.fine.transformation[:3, :3])
    if bound is not None and turn > bound:
        return f"it rotates the source by {turn:.1f} degrees, beyond the {bound:g} degrees of max_rotation (--max-rotation)"
    if bound is not None and best.trust == 0.0 and best.scored.overlap >= config.confidence.min_overlap:
        return f"ICP leaves the {bound:g} degrees of max_rotation (--max-rotation) from every estimate, so the pose as given is returned unrefined"
    if best.scored.overlap < config.confidence.min_overlap:
        return f"the clouds barely touch: the points near the other cloud are {100 * best.scored.overlap:.0f} % of the smaller one"
    return None


def _failure_reason(best: Attempt, config: RegisterConfig, searched: bool, complete: bool = False, agreeing: Optional[Tuple[int, int]] = None) -> Optional[str]:
    """Why a result is flagged likely failed, in words (None when it is not). `complete`: both
    clouds look complete (:attr:`PreparedPair.complete`), so the share of them near each other
    counts too. `agreeing`: (attempts that reached the pose, attempts), where the partial
    confidence weighed it."""
    if best.trust >= config.confidence.likely_failed_below:
        return None
    why = _apart_reason(best, config)
    if why is None:
        why = f"of the points near the other cloud, only {100 * best.scored.consistency:.0f} % lie within {best.scored.tight_distance:.3g} units of it"
        if best.scored.planar >= 0:  # measured (scans)
            on = config.confidence.planar_tolerance * best.scored.tight_distance
            why += f" and {100 * best.scored.planar:.0f} % within {on:.3g} units of its surface"
        full_overlap = best.scored._replace(overlap=1.0)  # would the pose be trusted with a partner for every point?
        if complete and confidence_stage.complete_confidence(full_overlap, config.confidence) >= config.confidence.likely_failed_below:
            why += f", and both clouds look complete but those points are only {100 * best.scored.overlap:.0f} % of the smaller one"
        if agreeing is not None:
            needed = confidence_stage.agreeing_trusted_from(config.confidence)
            why += f", and {agreeing[0]} of the {agreeing[1]} estimates reached this pose" + (f" (trusted from {needed})" if needed else "")
    return why + (_SEARCHED if searched else "")


def _result(
    best: Attempt,
    pair: PreparedPair,
    verifier: Verifier,
    network: NetworkPass,
    search_reason: Optional[str],
    geometry: degeneracy_stage.Degeneracy,
    copy: symmetry_stage.Symmetry,
    target_side: Optional[confidence_stage.Features],
    timings_ms: Dict[str, float],
    level: str,
) -> RegistrationResult:
    config = pair.config
    (src, tgt), (src_report, tgt_report) = pair.clouds(level), pair.cleaned
    trust = 0.0 if geometry.reason else best.trust  # however well it fits, the pose is not determined
    agreeing = verifier.agreeing(best)
    partial = choice_applies(pair) and confidence_stage.partial_confidence(best.scored, agreeing, config.confidence) > 0
    fit = _failure_reason(best, config, search_reason is not None, pair.complete, (agreeing, len(verifier.attempts)) if partial else None)
    # The geometry's test says how firmly a pose that fits is held: not why one apart fails.
    reason = fit if _apart_reason(best, config) else geometry.reason or fit
    if copy.reason:  # two poses fit as closely: the confidence is shared between them
        trust, reason = best.trust / 2, copy.reason
    back = 1.0 if target_side is None else confidence_stage.confidence(target_side, config.confidence)
    if target_side is not None and back < config.confidence.likely_failed_below and not geometry.reason:  # trusted from one side only
        trust = max(back, confidence_stage.scan_confidence(best.scored, config.confidence))
        if target_side.overlap < config.confidence.min_overlap:
            seen = f"the target's points near the source are only {100 * target_side.overlap:.0f} % of the smaller cloud"
        else:
            seen = f"of the target's points near the source, {100 * target_side.consistency:.0f} % lie within {target_side.tight_distance:.3g} units of it"
        reason = (
            f"it fits from the source's side only: {seen} (of the source's, {100 * best.scored.consistency:.0f} %), where a right alignment "
            "of two scans fits from both sides" + (_SEARCHED if search_reason is not None else "")
        )
    fewest, enough = min(len(src), len(tgt)), config.confidence.min_points
    if fewest < enough:
        few = f"the smaller cloud has only {fewest} points: under {enough}, a wrong alignment fits as closely as the right one and scores as high"
        cap = config.confidence.likely_failed_below * fewest / enough
        if trust >= cap:
            trust, reason = cap, few
        else:  # flagged for another reason too: both are said
            reason = f"{few}; also, {reason}" if reason else few
    if reason and search_reason is not None and pair.scans and config.search.kiss and not kiss_available():
        reason += "; KISS-Matcher, which the search tries first on scans, is not installed: pip install 'o3dsoft[peers]'"
    if reason and pair.size_ratio > config.confidence.size_note_ratio:
        fold = f"{pair.size_ratio:.1f}" if pair.size_ratio < 10 else f"{pair.size_ratio:.0f}"
        reason = f"the clouds' sizes differ {fold}-fold (are they in the same units? o3dsoft does not search a large scene for a small part of it); {reason}"
    return RegistrationResult(
        transformation=best.fine.transformation,
        fitness=best.fine.fitness,
        inlier_rmse=best.fine.inlier_rmse,
        coarse_transformation=best.coarse,
        estimate_from=best.by,
        confidence=trust,
        likely_failed=trust < config.confidence.likely_failed_below,
        failure_reason=reason,
        fitness_tight=best.scored.fitness_tight,
        tight_distance=best.scored.tight_distance,
        consistency=best.scored.consistency,
        mean_weight=None if network.estimate is None else float(np.mean(network.estimate.weights)),
        correspondence_distance=pair.distance,
        scale=pair.norm.scale,
        timings_ms=timings_ms,
        num_source=len(src),
        num_target=len(tgt),
        attempts=len(verifier.attempts),
        screened=len(verifier.screened),
        searched=search_reason is not None,
        search_reason=search_reason,
        network_transformation=network.transformation,
        points_used={"network": (len(pair.net[0]), len(pair.net[1])), "attempts": (len(pair.work[0]), len(pair.work[1])), "final": (len(src), len(tgt))},
        constraint=geometry.constraint,
        flatness=geometry.flatness,
        copy_transformation=copy.copy,
        copy_fit=copy.fit,
        agreeing=agreeing,
        target_consistency=None if target_side is None else target_side.consistency,
        voxel=pair.voxel,
        icp_method=pair.config.icp.method,
        removed={
            "source_non_finite": src_report.non_finite,
            "source_duplicates": src_report.duplicates,
            "target_non_finite": tgt_report.non_finite,
            "target_duplicates": tgt_report.duplicates,
            "source_strays": src_report.strays,
            "target_strays": tgt_report.strays,
            "source_isolated": pair.isolated[0],
            "target_isolated": pair.isolated[1],
        },
    )
