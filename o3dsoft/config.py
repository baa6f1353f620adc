"""Settings of :func:`o3dsoft.register`: one small frozen config per stage, nested in
:class:`RegisterConfig`. Every field says its meaning, unit and default; ``validate`` rejects
values a stage cannot run with (:class:`o3dsoft.errors.InputError`).
"""

from __future__ import annotations

import math
import numbers
import os
import typing
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Optional, Tuple, Union

import numpy as np

from .confidence import ConfidenceConfig
from .degeneracy import DegeneracyConfig
from .errors import InputError, UsageError
from .refine import ICPConfig
from .search import FeatureMatchConfig
from .symmetry import SymmetryConfig

SEARCH_MODES = ("auto", "always", "off", "quick")


@dataclass(frozen=True)
class FeatureSearchConfig:
    """The search's feature match (:mod:`o3dsoft.strategies.features`).

    Attributes:
        enabled: propose the feature match's estimates (default True).
        candidates: at most this many distinct estimates, best-supported first, refined and
            scored in turn until one is confident (default 100).
        first_round: the first round picks this many up front; the rest are drawn only for pairs
            still not confident (default 20).
        stop: go on through the estimates until one reaches this confidence (0.5-1, default 0.5:
            stop at the first confident one; higher searches doubtful results further).
        match: the FPFH features and the RANSAC.
    """

    enabled: bool = True
    candidates: int = 100
    first_round: int = 20
    stop: float = 0.5
    match: FeatureMatchConfig = field(default_factory=FeatureMatchConfig)


@dataclass(frozen=True)
class StartsConfig:
    """The network from many starting rotations (:mod:`o3dsoft.strategies.starts`): the main
    network from the 24 cube rotations where the feature match is off
    (``FeatureSearchConfig.enabled``), and the search network from 15 around the pose as given.

    Attributes:
        points: points per cloud for the batch of network passes (default 256).
        refine: how many of the best-ranked estimates are polished by ICP on the network's samples
            (``num_points``) before the most confident is verified (default 3).
        weights: a second network run from 15 starts around the pose as given (a file, as text or
            a Path, or a shipped model's name; default "partial", trained on cropped, noisy clouds); None:
            only the main network's cube starts (so none after the feature match).
    """

    points: int = 256
    refine: int = 3
    weights: Optional[str] = "partial"

    def __post_init__(self) -> None:
        _weights_as_text(self)


@dataclass(frozen=True)
class VotesConfig:
    """Translation votes (:mod:`o3dsoft.strategies.votes`), the search's last resort: at the
    rotations of the most trusted results, the translations most feature matches vote for.

    Attributes:
        rotations: at the rotations of this many most trusted results (distinct by the feature
            match's ``distinct_deg``); 0: off (default 2).
        translations: this many translations each (default 10).
        flipped: at the most trusted rotation turned by 180 degrees about each principal axis of
            either cloud, this many translations each; 0: no half turns (default 3).
    """

    rotations: int = 2
    translations: int = 10
    flipped: int = 3


@dataclass(frozen=True)
class RestartConfig:
    """The optional restart (:mod:`o3dsoft.strategies.restart`): every distinct start so far
    again, with ICP's tight stages only.

    Attributes:
        enabled: run it when nothing has reached the feature match's stop (default False).
        distinct_deg, distinct_shift: starts within this many degrees and this share of the scale
            of an earlier one are skipped (default 2.0, 0.02).
        refined: the most trusted this many on the screen clouds are refined and scored on the
            work clouds (default 3).
    """

    enabled: bool = False
    distinct_deg: float = 2.0
    distinct_shift: float = 0.02
    refined: int = 3


@dataclass(frozen=True)
class ScreenConfig:
    """Screening of estimates on large clouds (:class:`o3dsoft.verify.Verifier`).

    Attributes:
        points: the screen clouds are the work clouds on a voxel grid of at most this many
            points each; on work clouds larger than that, the feature match's and the votes'
            estimates (and the restart's starts), and on scans the network's, are refined and
            scored there first (default 1024).
        min_trust: ... and on the work clouds only when the screen trusts it more than every
            estimate before it and at least this much, or confidently (default 1e-3).
        max_iterations: the screen ranks estimates with a cheaper ICP (:meth:`ICPConfig.quick`:
            without the last stage, the noise rounds and the polish), each stage at most this
            many iterations (default 20); 0: the full ICP.
        budget: at most this many estimates are screened per pair (the network's among them, on
            scans); the search's later estimates are dropped (default 20; 0: no limit). On real
            scans the right estimate, when the search finds one, is among its first few
            (docs/scans.md).
    """

    points: int = 1024
    min_trust: float = 1e-3
    max_iterations: int = 20
    budget: int = 20


@dataclass(frozen=True)
class SearchConfig:
    """The global search, for pairs with no usable initial guess.

    Attributes:
        mode: "auto" runs it when the first result is flagged, or first of all when the clouds
            look like a partial overlap; "always" on every pair; "quick" only its feature match
            where that goes first (partial overlaps), nothing after a flagged result; "off" never
            (default "auto").
        partial_pvalue: below this p-value of :func:`o3dsoft.preprocess.same_profile_pvalue` the
            clouds are taken for a partial overlap, and the feature match runs before the
            network (default 0.01).
        prior_margin_deg: under ``RegisterConfig.max_rotation``, estimates are screened against
            the bound with this margin (degrees) before ICP, which can still move them into it
            (default 10).
        kiss: on scans (``PreparedPair.scans``), KISS-Matcher's estimate is tried
            before the feature match, where the optional package ``kiss-matcher`` is installed
            (``o3dsoft[peers]``; default True).
        kiss_voxel: KISS-Matcher's voxel, as a share of the larger scene's size (default 0.01).
        kiss_normal_radius, kiss_feature_radius: its normals' and FPFH features' radii, in its
            voxels (default 2.5 and 4; KISS-Matcher's own are 3 and 5; docs/scans.md).
        replace_odds: an estimate of the search replaces the pipeline's own (the network's, and the
            feature match's where it ran first) only when its confidence's odds, p / (1 - p), are
            this many times higher (default 30; 1: the most trusted wins).
        independent_odds: the same where the clouds are two independent samplings of a complete
            shape (:meth:`o3dsoft.verify.Verifier.independent`), where the choice ranks by the
            confidence the result reports (default 5; docs/incongruent.md).
        independent_contact: there the search's estimate the strict confidence trusts most among
            those that bring at least this share as many points into close contact as the one
            that brings most still replaces that choice at ``replace_odds`` (0-1, default 0.9).
        independent_spacing: the choice takes the clouds for two independent samplings only where
            every estimate's spacing ratio is at least this (stricter than the confidence's
            ``independent_from``: right poses of noisy clouds that share their points reach 0.9,
            those of independent samplings seldom fall under 0.85; default 0.85).
        min_contact: an estimate is chosen only if it brings at least this share as many points
            into close contact (``fitness_tight``) as the estimate that brings most (0-1, default
            0.5; 0: any; docs/incongruent.md).
        partial_choice: where the clouds neither both look complete nor are scans (a partial
            overlap of small clouds, :meth:`o3dsoft.verify.Verifier.scores_choice`), the choice
            takes, among the estimates in contact, the one with the highest w . (consistency,
            overlap, spacing ratio capped at 3, fitness_tight over the most of the pair's
            estimates) instead of the most trusted: there the strict confidence trusts poses that
            fit a small part closely, and the right pose brings the most points into contact at
            the sampling's spacing. Fitted on train pairs by ``python -m benchmarks.fit_choice``
            (docs/incongruent.md); None: the most trusted.
        undetermined_gain: a trusted result that the degeneracy test flags and whose pose shows no
            shared point (not on scans) starts the second network and the search after all; what
            they find replaces it only where its input Chamfer distance on the work clouds is this
            many times lower (at least 1, default 1.5; docs/incongruent.md).
        features, starts, votes, restart: the search's steps, in the order they run (the main
            network's cube starts only where the feature match is off).
        screen: how the steps' estimates are tried first on large clouds.
    """

    mode: str = "auto"
    partial_pvalue: float = 0.01
    prior_margin_deg: float = 10.0
    kiss: bool = True
    kiss_voxel: float = 0.01
    kiss_normal_radius: float = 2.5
    kiss_feature_radius: float = 4.0
    replace_odds: float = 30.0
    independent_odds: float = 5.0
    independent_contact: float = 0.9
    independent_spacing: float = 0.85
    min_contact: float = 0.5
    partial_choice: Optional[Tuple[float, float, float, float]] = (5.57, 0.54, -10.73, 7.45)
    undetermined_gain: float = 1.5
    features: FeatureSearchConfig = field(default_factory=FeatureSearchConfig)
    starts: StartsConfig = field(default_factory=StartsConfig)
    votes: VotesConfig = field(default_factory=VotesConfig)
    restart: RestartConfig = field(default_factory=RestartConfig)
    screen: ScreenConfig = field(default_factory=ScreenConfig)

    @property
    def features_on(self) -> bool:
        """The feature match may run: the search is not off and the feature match is enabled."""
        return self.mode != "off" and self.features.enabled


@dataclass(frozen=True)
class SecondNetworkConfig:
    """A second network for clouds that share no point (two independent samplings of one surface,
    as every two scans are), run from the pose as given when the first network's result is flagged,
    before the search (:class:`o3dsoft.strategies.NetworkPass`); not after the feature match, which
    runs first on a partial overlap when the search is on (there it changed no result,
    docs/incongruent.md), nor on scans (clouds on a voxel grid or of more than 4,096 points,
    ``PreparedPair.scans``: of the 52 shared scan pairs it ran on 4 and was wrong on each, where
    the search's feature match was right; docs/scans.md). Its estimate counts as the pipeline's
    own, so the search must find one clearly better to replace it (``replace_odds``).

    Attributes:
        weights: a model file (text or a Path) or a shipped model's name (default "incongruent", trained on
            independently sampled pairs; weights/o3dsoft_incongruent.json); None: off.
        iterations: its passes, each from the estimate so far (default 3: it recovers about 60 %
            of the remaining rotation per pass, docs/incongruent.md).
        ends_search: its result ends the search (the search does not run) where both clouds look
            complete (``PreparedPair.complete``), its pose shows no shared point (spacing ratio at
            least ``search.independent_spacing``) and the complete confidence
            (:func:`~o3dsoft.confidence.complete_confidence`) is at least this (default 0.8). The
            strict confidence flags most right poses of two independent samplings, and the search
            that follows replaces some right ones with turns onto a near-symmetric copy; the
            degeneracy test still sends a pose it does not hold to the search. None: only the
            strict confidence ends the search, as for every other estimate.
        shared_check: before it ends the search, the feature match's first this many candidates
            are tried (where the feature match is on; default 10): noisy crops of one point set
            look like two independent samplings at a wrong pose, and their right pose is most
            often the first candidate, which the strict confidence trusts.
        turns: where its pose from the pose as given neither is trusted nor ends the search and
            both clouds look complete, it runs from the other 23 rotations of a cube too (one pass
            each, as one batch), and this many of them, those whose pose brings the most source
            points close to the target, get its remaining passes and are verified as the search's
            estimates (one replaces the pose as given only at ``search.independent_odds`` times
            its odds: a turn onto a symmetric copy scores as well as the right pose); the one
            chosen ends the search as above. For clouds known to share no point that may be
            turned by any rotation (4 is the measured setting; default 0: off): it is trained on
            turns of up to 45 degrees per axis, and clouds turned further otherwise leave the
            answer to the search. Noisy crops of one point set can look complete and pass for
            independent samplings at a wrong turned pose, which then ends the search
            (docs/incongruent.md).
    """

    weights: Optional[str] = "incongruent"
    iterations: int = 3
    ends_search: Optional[float] = 0.8
    shared_check: int = 10
    turns: int = 0

    def __post_init__(self) -> None:
        _weights_as_text(self)


@dataclass(frozen=True)
class RegisterConfig:
    """Settings of :func:`o3dsoft.register` (dumped next to every result).

    Attributes:
        voxel: register both clouds on a voxel grid of this size (cloud units), after cleaning;
            None: from the data (default, :func:`o3dsoft.preprocess.data_grid`); 0: keep every
            point.
        data_voxel: the grid from the data, as a share of the scene's size (the diagonal of the
            box holding 98 % of the points), where the clouds are denser than half of that: 0.01,
            i.e. 4 cm on a 4 m room, 75 cm on a 75 m street, 2 mm on a 20 cm object (default;
            point-to-plane ICP on it is as accurate as on a grid half as coarse, docs/scans.md).
            Only for clouds of more than `attempt_points`. 0: keep every point unless `voxel` is
            given.
        isolated_radius: on a voxel grid, points with fewer than two others within this many
            voxels are isolated (scattered outliers: flying pixels, dust, spurious returns) and left
            out of the registration, in clouds the grid merged to half their points or fewer
            (default 3; 0: keep them). A scattered outlier keeps a cell of its own where a
            surface shares its cells, so on the grid 2 % of scattered points in a fragment
            become 5-13 % of its points.
        isolated_spacings: off a grid (scans, a cloud of more than 4,096 points in the pair,
            registered whole or sparser than the data's grid; not with `voxel` = 0), points with fewer than two
            others within this many median point spacings are left out the same way, where they
            are 1-10 % of a cloud and lie about as far out as it does (more, or over twice as
            far from its median: it is sparse in places, as a LiDAR sweep's far returns are;
            default 6, at which randomly thinned clean scans lose none; 0: keep them).
        num_points: points sampled from each cloud for the network (default 1024).
        coarse_iterations: network passes, each on the source moved by the estimate so far
            (default 1).
        attempt_points: every estimate is refined and scored on the clouds voxel-downsampled to at
            most this many points each; the kept one is refined again at full resolution
            (``pipeline._refine_full``). Default 10,000: RGB-D fragments on the data's grid,
            5,000-9,000 points, are scored whole, so that the trust that decides whether to
            search is the full clouds'. Clouds of at most this many points get no grid from the
            data. Odometry's steps on the sequence's grid are refined and scored whole up to
            three times as many points (``pair.GRID_WORK_ATTEMPTS``): a trusted step refines one
            guess, and a second grid would double its normals, ICP and scoring.
        max_rotation: the clouds are given within this many degrees of their true relative
            rotation (a prior, e.g. from odometry): estimates beyond it get confidence 0, and the
            result lies within it; None: any rotation (default).
        sparser_moves: when the target's points are this many times sparser on its surface than
            the source's (points over the squared scene size), the target is registered onto
            the source and the result inverted, so that the sparser cloud is the one whose
            points seek partners: ICP's pairs are then a point spacing of the dense cloud apart,
            not of the sparse one (default 4, i.e. a spacing twice as wide; 0: never).
        refine: run ICP on every estimate (default True); False: the estimates as they are.
        refine_flagged: refine a result that the work clouds flag at full resolution too
            (default True); False: return it as the work clouds left it, which saves the most
            expensive ICP for callers that discard flagged results (multiway's first pass).
        weights: TorchScript model file (text or a Path), or a shipped model's name; None: the shipped default.
        device: torch device of the network ("cpu", "cuda", "cuda:1"...; default "cpu").
        seed: seed of the point sampling and of the search's RANSAC: the same input and seed
            give the same result (default 0), to the bit on one machine.
        second_network: the network for clouds that share no point, when the first is flagged.
        icp: the fine stage.
        search: the global search.
        confidence: how results are scored and flagged.
        degeneracy: when the geometry is taken not to determine the pose (the result flagged).
        symmetry: when a half-turned copy of the result fits as closely (the confidence halved).
    """

    voxel: Optional[float] = None
    data_voxel: float = 0.01
    isolated_radius: float = 3.0
    isolated_spacings: float = 6.0
    num_points: int = 1024
    coarse_iterations: int = 1
    attempt_points: int = 10_000
    max_rotation: Optional[float] = None
    sparser_moves: float = 4.0
    refine: bool = True
    refine_flagged: bool = True
    weights: Optional[str] = None
    device: str = "cpu"
    seed: int = 0
    second_network: SecondNetworkConfig = field(default_factory=SecondNetworkConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)
    degeneracy: DegeneracyConfig = field(default_factory=DegeneracyConfig)
    symmetry: SymmetryConfig = field(default_factory=SymmetryConfig)

    def __post_init__(self) -> None:
        _weights_as_text(self)

    def to_dict(self) -> dict:
        return asdict(self)

    def validate(self, k: int) -> None:
        """Raise InputError for settings the network (neighbourhood size `k`) cannot run with: every
        number finite and not negative (:func:`check_settings`), then the bounds that leaves open."""
        check_settings(self)
        search = self.search
        if search.mode not in SEARCH_MODES:
            raise InputError(f"search.mode={search.mode!r}; valid: {', '.join(SEARCH_MODES)}")
        for name, value in (("num_points", self.num_points), ("search.starts.points", search.starts.points), ("attempt_points", self.attempt_points)):
            if value < k:
                raise UsageError(f"{name}={value} is below the network's neighbourhood size K={k}")
        if self.icp.method not in ("auto", "point", "plane"):
            raise InputError(f"icp.method={self.icp.method!r}; valid: auto, point, plane")
        if not 0 <= self.data_voxel < 1:
            raise InputError(f"data_voxel must be in [0, 1), got {self.data_voxel}")
        schedule = self.icp.schedule
        if not schedule or not all(0 < factor < math.inf for factor in schedule):
            raise InputError(f"icp.schedule must hold at least one positive, finite distance factor, got {schedule}")
        for name, value in (
            ("icp.max_iterations", self.icp.max_iterations),
            ("icp.max_points", self.icp.max_points),
            ("degeneracy.max_points", self.degeneracy.max_points),
            ("search.screen.points", search.screen.points),
            ("search.starts.refine", search.starts.refine),
            ("search.features.first_round", search.features.first_round),
        ):  # counts not negative: _check_types
            if value < 1:
                raise InputError(f"{name} must be at least 1, got {value}")
        if self.icp.normal_neighbours < 3:
            raise InputError(f"icp.normal_neighbours must be at least 3 (a plane), got {self.icp.normal_neighbours}")
        if search.features.candidates < 1:
            raise InputError(f"search.features.candidates must be at least 1, got {search.features.candidates}")
        if self.max_rotation is not None and not 0 < self.max_rotation <= 180:
            raise InputError(f"max_rotation must be in (0, 180] degrees, got {self.max_rotation}")
        threshold = self.confidence.likely_failed_below
        if not 0 <= threshold <= 1:
            raise InputError(f"confidence.likely_failed_below must be in [0, 1], got {threshold}")
        if self.icp.absolute and self.icp.distance is None:
            raise InputError("icp.absolute needs icp.distance, in the clouds' units")
        if self.icp.distance is not None and not 0 < self.icp.distance < math.inf:
            raise InputError(f"icp.distance must be positive and finite, got {self.icp.distance}")
        if not threshold <= search.features.stop <= 1:
            raise InputError(
                f"search.features.stop must be in [confidence.likely_failed_below, 1] = [{threshold}, 1] (the feature match would stop at an estimate it flags), got {search.features.stop}"
            )
        for name in ("replace_odds", "independent_odds", "undetermined_gain"):
            if not getattr(search, name) >= 1:
                raise InputError(f"search.{name} must be at least 1, got {getattr(search, name)}")
        if not (self.sparser_moves == 0 or self.sparser_moves >= 1):
            raise InputError(f"sparser_moves must be 0 (never) or at least 1, got {self.sparser_moves}")
        for name in ("kiss_voxel", "kiss_normal_radius", "kiss_feature_radius"):
            if not getattr(search, name) > 0:
                raise InputError(f"search.{name} must be positive, got {getattr(search, name)}")
        for name in ("voxel", "normal_radius", "fpfh_radius", "ransac_distance"):  # Open3D's grid, neighbourhoods and inlier test
            if not getattr(search.features.match.features, name) > 0:
                raise InputError(f"search.features.match.features.{name} must be positive, got {getattr(search.features.match.features, name)}")
        if search.partial_choice is not None and len(search.partial_choice) != 4:  # finite: check_settings
            raise InputError(f"search.partial_choice must be None or 4 finite weights, got {search.partial_choice}")
        for name in ("min_contact", "independent_contact"):
            if not 0 <= getattr(search, name) <= 1:
                raise InputError(f"search.{name} must be in [0, 1], got {getattr(search, name)}")
        if self.second_network.iterations < 1:
            raise InputError(f"second_network.iterations must be at least 1, got {self.second_network.iterations}")
        ends = self.second_network.ends_search
        if ends is not None and not threshold <= ends <= 1:
            raise InputError(f"second_network.ends_search must be None or in [confidence.likely_failed_below, 1] = [{threshold}, 1], got {ends}")
        if self.second_network.shared_check < 0:
            raise InputError(f"second_network.shared_check must not be negative, got {self.second_network.shared_check}")
        if not 0 <= self.second_network.turns <= 23:
            raise InputError(f"second_network.turns must be in [0, 23] (the other rotations of a cube), got {self.second_network.turns}")
        try:
            self.confidence.validate()
        except ValueError as e:
            raise InputError(f"confidence: {e}") from None
        symmetry = self.symmetry
        if not symmetry.max_ratio >= 1 or not 0 <= symmetry.min_away_deg <= 180 or not 0 < symmetry.closed_from <= 1:
            raise InputError(
                "symmetry: max_ratio must be at least 1, min_away_deg in [0, 180] and closed_from in (0, 1]; "
                f"got {symmetry.max_ratio}, {symmetry.min_away_deg}, {symmetry.closed_from}"
            )
        degeneracy = self.degeneracy
        if (
            not 0 <= degeneracy.min_constraint < 1 or min(degeneracy.neighbours, degeneracy.line_neighbours) < 3 or not degeneracy.max_flatness > 0
        ):  # shared_below and regular_below not negative: check_settings
            raise InputError(
                "degeneracy: min_constraint must be in [0, 1), neighbours and line_neighbours at least 3 and max_flatness positive; "
                f"got {degeneracy.min_constraint}, {degeneracy.neighbours}, {degeneracy.line_neighbours}, {degeneracy.max_flatness}"
            )


def _weights_as_text(settings) -> None:
    """Set the ``weights`` field of the frozen `settings` to the text of the path it holds, where
    it holds one (``Path("run/model.pt")``), so that configs compare and write to JSON as text."""
    if isinstance(settings.weights, os.PathLike):
        object.__setattr__(settings, "weights", os.fspath(settings.weights))


def check_settings(settings) -> None:
    """Raise InputError naming the first field of the frozen dataclass `settings` (and of those
    nested in it) of the wrong type (:func:`_check_types`) or that holds a number no setting
    takes (:func:`_check_numbers`)."""
    _check_types(settings, "")
    _check_numbers(settings, "")


def _check_numbers(settings, prefix: str) -> None:
    """Raise InputError naming the first number of the frozen dataclass `settings` (and of those
    nested in it) that is NaN, infinite or negative: every setting is a count, a distance, a
    share, an angle or a threshold (only the weights of a tuple, a confidence's coefficients, may
    be negative)."""
    for f in fields(settings):
        value, name = getattr(settings, f.name), f"{prefix}{f.name}"
        if is_dataclass(value):
            _check_numbers(value, f"{name}.")
        elif isinstance(value, (tuple, list)):
            if not all(math.isfinite(v) for v in value):
                raise InputError(f"{name} must hold finite numbers, got {tuple(value)}")
        elif isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) and not (math.isfinite(value) and float(value) >= 0):
            raise InputError(f"{name} must be a finite number, at least 0, got {value}")


_TYPE_HINTS: dict = {}


def _type_hints(kind: type) -> dict:
    """The fields' types of the dataclass `kind`, evaluated once per class (the annotations are
    text: evaluating them on every call cost a few ms of each registration)."""
    if kind not in _TYPE_HINTS:
        _TYPE_HINTS[kind] = typing.get_type_hints(kind)
    return _TYPE_HINTS[kind]


def _check_types(settings, prefix: str) -> None:
    """Raise InputError naming the first field of the frozen dataclass `settings` (and of those
    nested in it) that holds something other than its declared type: a stage's config (not a
    dict), True or False, an integer count (not negative), a number, a string, a tuple of
    numbers; None only where the field is Optional."""
    hints = _type_hints(type(settings))
    for f in fields(settings):
        value, hint, name = getattr(settings, f.name), hints.get(f.name), f"{prefix}{f.name}"
        optional = typing.get_origin(hint) is Union and type(None) in typing.get_args(hint)
        kinds = tuple(k for k in typing.get_args(hint) if k is not type(None)) if typing.get_origin(hint) is Union else (hint,)
        kind = kinds[0] if len(kinds) == 1 else None
        got = f"got {value!r} ({type(value).__name__})"
        if value is None:
            if not optional and kind is not None:
                raise InputError(f"{name} must not be None")
        elif isinstance(kind, type) and is_dataclass(kind):
            if not isinstance(value, kind):
                raise InputError(f"{name} must be an o3dsoft.{kind.__name__}, {got}")
            _check_types(value, f"{name}.")
        elif kind is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise InputError(f"{name} must be True or False, {got}")
        elif kind is int:
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
                raise InputError(f"{name} must be a whole number, {got}")
            if value < 0:
                raise InputError(f"{name} must not be negative, got {value}")
        elif kind is float:
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                raise InputError(f"{name} must be a number, {got}")
        elif kind is str:
            if not isinstance(value, str):
                raise InputError(f"{name} must be a string, {got}")
        elif typing.get_origin(kind) is tuple:
            if not isinstance(value, (tuple, list)) or not all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) for v in value):
                raise InputError(f"{name} must be a tuple of numbers, {got}")
