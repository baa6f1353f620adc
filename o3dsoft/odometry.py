"""``odometry``: the poses of a sequence of sweeps (LiDAR, depth frames), one after another.

    every sweep cleaned once
    for each sweep after the first:
    -> a local map: the last few sweeps (not those flagged that fit it poorly or moved far from
       their guess), in the previous sweep's frame, on the voxel grid the first step chose
    -> register the sweep onto it (:func:`o3dsoft.register`) from a constant-velocity guess (the
       last motion again; where ICP from it is trusted, nothing else runs)
    -> its pose: the previous pose followed by the motion found.

Registering onto several sweeps instead of the last one alone (the scheme of KISS-ICP) gives ICP
denser surfaces to slide against: sparse sweeps of few rings drift less (docs/multiway.md). The
poses are those of the sweeps' own frames in the first sweep's frame; nothing closes loops (for
that, ``multiway --init`` from these poses).
"""

from __future__ import annotations

import numbers
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from ._modules import callable_as_its_function
from .config import RegisterConfig
from .errors import InputError, UsageError
from .metrics import PairErrors, pair_errors
from .pair import CloudLike, GridCloud, as_points, named_clouds, on_grid
from .pipeline import SIZE_RATIO_NOTE, RegistrationResult, register, register_on_grid
from .preprocess import Cleaning, CleanReport, clean_each, local_origin, scene_size, voxel_downsample
from .transforms import apply_transform, in_frame_at

# A flagged step whose sweep has at least this share of its points within ICP's distance of the
# map stays in it: on sparse sweeps the confidence flags right steps, and a map without them loses
# its way (docs/multiway.md) ...
MAP_MIN_FITNESS = 0.5
# ... where it lies within this turn (degrees) and this shift (a share of the pair's scale) of the
# motion guessed for it: a wide ICP distance finds most points of a sweep near the map at a pose
# turned far from the right one, and sweeps registered onto that would follow it.
MAP_MAX_TURN = 10.0
MAP_MAX_SHIFT = 0.1


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of :func:`odometry`.

    Attributes:
        map_sweeps: how many of the last sweeps make the local map each sweep is registered onto
            (1: the previous sweep alone, frame to frame); a sweep whose step was flagged and
            fits the map poorly (:data:`MAP_MIN_FITNESS`) or moved far from the motion guessed
            (:data:`MAP_MAX_TURN`, :data:`MAP_MAX_SHIFT`) is left out of it (it reaches back past).
        constant_velocity: start each sweep at the last motion repeated (else where the previous
            sweep is); after a step left out of the map, from the last kept sweep's pose and motion.
        one_grid: every sweep is cleaned once, and the steps after the first register on that
            step's voxel grid (:func:`~o3dsoft.pipeline.register_on_grid`): each map is made of
            its sweeps on half the grid, each made once, instead of every step cleaning and
            gridding its raw sweep and ten raw sweeps again. Steps take about half the time, and
            the grid stays the same along the sequence, as in KISS-ICP. Where the first step used
            no grid, or the grid leaves a cloud too few points, steps register the raw clouds as
            with False.
        guess_max_rotation: a sweep registered from its guess (every sweep after the second) is
            held within this many degrees of it (``RegisterConfig.max_rotation``, where `register`
            sets none), as multiway holds pairs near their initial poses: a sensor seldom turns
            that far between frames, and where a frame shows too little to fix its pose (a flat
            wall) the search can find and trust a pose turned far from the guess; None: no bound.
        register: the registration's settings (the same for every sweep).
    """

    map_sweeps: int = 10
    constant_velocity: bool = True
    one_grid: bool = True
    guess_max_rotation: Optional[float] = 45.0
    register: RegisterConfig = field(default_factory=RegisterConfig)

    def validate(self) -> None:
        if isinstance(self.map_sweeps, bool) or not isinstance(self.map_sweeps, numbers.Integral) or self.map_sweeps < 1:
            raise UsageError(f"map_sweeps must be a whole number of at least 1, got {self.map_sweeps!r}")
        for name in ("constant_velocity", "one_grid"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise UsageError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if not isinstance(self.register, RegisterConfig):
            raise UsageError(f"register must be an o3dsoft.RegisterConfig, got {type(self.register).__name__}")
        bound = self.guess_max_rotation
        if bound is not None and (isinstance(bound, bool) or not isinstance(bound, numbers.Real) or not 0 < bound <= 180):
            raise UsageError(f"guess_max_rotation must be in (0, 180] degrees or None, got {bound!r}")


@dataclass(frozen=True, eq=False)  # compared by identity: arrays have no single truth value
class OdometryResult:
    """Poses of a sequence of sweeps.

    Attributes:
        names: the sweeps' names, in order.
        poses: (4, 4) world_T_sweep per sweep (maps the sweep's points into the first sweep's
            frame; the first is the identity).
        steps: per sweep, its registration onto its local map (None for the first), whose
            ``transformation`` is the motion previous_T_sweep from the previous sweep's pose as
            found (poses[k] = poses[k-1] @ steps[k].transformation).
        timings_s: "total" (s, lower is better).
        mapped: per sweep, whether the local maps of the sweeps after it hold it (the first and
            every trusted sweep; a flagged one only where it fits its map and lies near the motion
            guessed for it).
        origins: per sweep, the (3,) point of its frame about which its motions are measured
            (:func:`frame_point`): the sensor's, zeros, unless its coordinates are georeferenced.
    """

    names: Tuple[str, ...]
    poses: Tuple[np.ndarray, ...]
    steps: Tuple[Optional[RegistrationResult], ...]
    timings_s: Dict[str, float]
    mapped: Tuple[bool, ...] = ()
    origins: Tuple[np.ndarray, ...] = ()

    @property
    def path(self) -> float:
        """The length of the path (sweep units): each step's motion measured at its sweep's
        ``origins`` point (the sensor's, for sweeps in their sensor's frame), summed."""
        return sum(_moved(step.transformation, origin) for step, origin in zip(self.steps[1:], self._origins[1:]))  # type: ignore[union-attr]

    @property
    def last_from_first(self) -> float:
        """How far (sweep units) the last sweep's pose moves its ``origins`` point from where the
        first sweep's frame has it: the distance between the ends of the path."""
        return _moved(self.poses[-1], self._origins[-1])

    @property
    def _origins(self) -> Tuple[np.ndarray, ...]:
        return self.origins or tuple(np.zeros(3) for _ in self.names)

    @property
    def flagged(self) -> Tuple[bool, ...]:
        """Per sweep: its registration is flagged likely failed (its pose may be off; unless it is
        ``mapped``, the sweeps after it are registered without it)."""
        return tuple(step is not None and step.likely_failed for step in self.steps)

    def to_dict(self) -> dict:
        """JSON-ready dict: per sweep its pose, and its step's confidence, flag and reason."""

        def sweep(name: str, pose: np.ndarray, step: Optional[RegistrationResult], mapped: bool) -> dict:
            entry: dict = {"name": name, "world_T_sweep": pose.tolist()}
            if step is not None:
                entry.update(
                    confidence=step.confidence,
                    likely_failed=step.likely_failed,
                    failure_reason=step.failure_reason,
                    estimate_from=step.estimate_from,
                    in_map=mapped,
                    seconds=round(step.timings_ms.get("total", 0.0) / 1000.0, 4),
                )
            return entry

        return {
            "world": self.names[0],
            "sweeps": [sweep(n, p, s, m) for n, p, s, m in zip(self.names, self.poses, self.steps, self.mapped or (True,) * len(self.steps))],
            "timings_s": self.timings_s,
        }


def odometry(
    sweeps: Sequence[CloudLike],
    config: Optional[OdometryConfig] = None,
    names: Optional[Sequence[str]] = None,
    model=None,
    progress: Optional[Callable[[int, int], None]] = None,
) -> OdometryResult:
    """The pose of every sweep of a sequence in the first sweep's frame.

    Args:
        sweeps: the sweeps in the order they were taken, (N_i, 3) arrays or Open3D point clouds,
            each in its sensor's frame, all in the same units.
        config: the settings (None: the defaults).
        names: how to call the sweeps (file names); default sweep0, sweep1, ...
        model: an already loaded network (else loaded once from ``config.register.weights``).
        progress: called as progress(sweeps done, sweeps in all) once every sweep is checked
            (1: the first, which needs no registration), then after each sweep.
    Returns:
        OdometryResult.
    Raises:
        InputError: fewer than two sweeps, or a sweep that cannot be registered (too few
            distinct points, degenerate): every sweep is checked before the first is registered.
        UsageError: `config` is not an OdometryConfig, or a setting is invalid.
    """
    from .coarse import cached_model, check_loaded

    config = OdometryConfig() if config is None else config
    if not isinstance(config, OdometryConfig):
        raise UsageError(f"config must be an o3dsoft.OdometryConfig (its register field holds a RegisterConfig), got {type(config).__name__}")
    config.validate()
    check_loaded(model, "model", "OdometryConfig(register=RegisterConfig(weights=...))")
    sweeps, names = named_clouds(sweeps, names, "sweep", "odometry")
    model = model if model is not None else cached_model(config.register.weights, config.register.device)
    points, cleaning = _checked_sweeps(sweeps, names, model.config.k)
    if progress is not None:
        progress(1, len(points))
    start = time.perf_counter()
    poses: List[np.ndarray] = [np.eye(4)]
    steps: List[Optional[RegistrationResult]] = [None]
    guesses: List[Optional[np.ndarray]] = [None]
    origins = tuple(frame_point(p) for p in points)
    first = _onto_a_map(config.register)
    settings = first  # for the sweeps registered from a guess
    if settings.max_rotation is None and config.guess_max_rotation is not None:
        settings = replace(settings, max_rotation=config.guess_max_rotation)
    grids: Optional[_SweepGrids] = None  # from the first step's grid on (one_grid)
    for k in range(1, len(points)):
        kept = _kept(steps, guesses, origins, k)
        guess = _guess(poses, steps, kept, k, config.constant_velocity)
        map_name = f"the map before {names[k]}"
        built = time.perf_counter()
        gridded = None if grids is None else grids.pair(poses, kept[-config.map_sweeps :], k, guess, map_name)
        if gridded is not None:
            map_ms = 1000.0 * (time.perf_counter() - built)
            step = register_on_grid(*gridded, settings, model, names[k], map_name, guess)
        else:
            local_map = _local_map(points, poses, kept, k, config.map_sweeps)
            map_ms = 1000.0 * (time.perf_counter() - built)
            # Before any motion is known the guess is only "where the last sweep was": the first
            # step is registered as any pair is (ICP from the identity slid a room view 1.1 m off, trusted).
            step = register(
                points[k], local_map, settings if k > 1 else first, model=model, source_name=names[k], target_name=map_name, init=guess if k > 1 else None
            )
            if k == 1 and config.one_grid and step.voxel is not None:
                grids = _SweepGrids(points, cleaning, step.voxel, config.register, model.config.k)
        step = replace(step, timings_ms={**step.timings_ms, "map": map_ms, "total": step.timings_ms["total"] + map_ms})
        poses.append(poses[-1] @ step.transformation)
        steps.append(step)
        guesses.append(guess)
        if progress is not None:
            progress(k + 1, len(points))
    in_map = set(_kept(steps, guesses, origins, len(points)))
    mapped = tuple(j in in_map for j in range(len(points)))
    return OdometryResult(names, tuple(poses), tuple(steps), {"total": round(time.perf_counter() - start, 3)}, mapped, origins)


class OdometryErrors(NamedTuple):
    """An odometry result against reference poses (lower is better in every field).

    rotation_deg, translation: (K-1,) each step's motion previous_T_sweep against the reference's
        (degrees, sweep units).
    drift: the last sweep's pose against the reference's (:class:`~o3dsoft.metrics.PairErrors`).
    path: the reference's path, its motions measured at the result's ``origins`` summed (sweep units).
    """

    rotation_deg: np.ndarray
    translation: np.ndarray
    drift: PairErrors
    path: float


def errors_against(result: OdometryResult, reference: Sequence[np.ndarray]) -> OdometryErrors:
    """`result` against (4, 4) reference poses world_T_sweep per sweep, in any world frame (taken
    relative to the first sweep's, as the result's are); translations measured at each sweep's
    ``result.origins`` point."""
    base = np.linalg.inv(reference[0])
    truth = [base @ P for P in reference]
    origins = result._origins
    motions = [np.linalg.inv(truth[k]) @ truth[k + 1] for k in range(len(truth) - 1)]
    steps = [pair_errors(step.transformation, motions[k], origins[k + 1]) for k, step in enumerate(result.steps[1:])]  # type: ignore[union-attr]
    path = sum(_moved(T, origins[k + 1]) for k, T in enumerate(motions))
    drift = pair_errors(result.poses[-1], truth[-1], origins[-1])
    return OdometryErrors(np.array([e.rotation_deg for e in steps]), np.array([e.translation for e in steps]), drift, path)


def _moved(T: np.ndarray, origin: np.ndarray) -> float:
    """How far (4, 4) `T` moves the (3,) point `origin`."""
    return float(np.linalg.norm(in_frame_at(T, origin)[:3, 3]))


# A sweep whose points lie this many times their size from its frame's origin is georeferenced:
# no sensor sees that far (a narrow forward view's median lies about twice its size out).
GEOREFERENCED_BEYOND = 1000.0


def frame_point(points: np.ndarray) -> np.ndarray:
    """(3,) the point of a sweep's frame at which its motions are measured: the frame's origin
    (zeros: the sensor, for a sweep in its sensor's frame), or, for (N, 3) `points` more than
    :data:`GEOREFERENCED_BEYOND` times their :func:`~o3dsoft.preprocess.scene_size` from it
    (georeferenced coordinates: a turn of 0.1 degrees about an origin 4e6 m away moves the
    sweep 7 km), their median (:func:`~o3dsoft.preprocess.local_origin`)."""
    centre = local_origin(points)
    if not centre.any():
        return centre
    return centre if np.linalg.norm(centre) > GEOREFERENCED_BEYOND * scene_size(points[np.isfinite(points).all(axis=1)]) else np.zeros(3)


def _checked_sweeps(sweeps: Sequence[CloudLike], names: Sequence[str], min_points: int) -> Tuple[List[np.ndarray], List[Cleaning]]:
    """The (N_i, 3) points of each sweep, and what cleaning keeps of each (:func:`o3dsoft.preprocess.clean_each`:
    a bad sweep late in a long sequence fails before the first is registered)."""
    points = [as_points(s, str(n)) for s, n in zip(sweeps, names)]
    return points, clean_each(points, names, min_points)


class _SweepGrids:
    """The clouds of the steps on one grid (``OdometryConfig.one_grid``): each sweep, cleaned, on
    the grid where its guess puts it; each map made of its sweeps on half the grid (made once per
    sweep, kept while the sweep is in a map), put on the grid. Its cells average about what the
    sweeps' raw points would give; the sweeps' own grids, put on another grid, merge neighbouring
    cells and blur it."""

    def __init__(self, points: Sequence[np.ndarray], cleaning: Sequence[Cleaning], voxel: float, config: RegisterConfig, min_points: int) -> None:
        self.points, self.cleaning, self.voxel, self.config, self.min_points = points, cleaning, voxel, config, min_points
        self._halves: Dict[int, np.ndarray] = {}

    def pair(self, poses: Sequence[np.ndarray], in_map: Sequence[int], k: int, guess: np.ndarray, map_name: str) -> Optional[Tuple[GridCloud, GridCloud]]:
        """Sweep k moved by the (4, 4) `guess` and its map of the sweeps `in_map` at their `poses`,
        both on the grid in sweep k-1's frame; None where the grid leaves one of them fewer points
        than the network's K (the step registers the raw clouds)."""
        cleaned = self.cleaning[k].of(self.points[k])
        try:
            source = on_grid(cleaned._replace(points=apply_transform(guess, cleaned.points)), self.voxel, self.config, self.min_points, f"sweep {k}")
            local_map = self._local_map(poses, in_map, k, map_name)
        except InputError:
            return None
        self._half(k, cleaned.points)  # for the maps after it, while its cleaned points are at hand
        return source, local_map

    def _local_map(self, poses: Sequence[np.ndarray], in_map: Sequence[int], k: int, name: str) -> GridCloud:
        halves = {j: self._half(j) for j in in_map}
        points = _local_map(halves, poses, in_map, k, len(in_map))
        self._halves = halves  # a sweep out of this map is in no later one
        counts = [self.cleaning[j] for j in in_map]
        removed = CleanReport(
            points, non_finite=sum(c.non_finite for c in counts), duplicates=sum(c.duplicates for c in counts), strays=sum(c.strays for c in counts)
        )
        return on_grid(removed, self.voxel, self.config, self.min_points, name)

    def _half(self, j: int, cleaned: Optional[np.ndarray] = None) -> np.ndarray:
        """(N, 3) sweep j on half the grid, in its own frame, made once (from its `cleaned` points
        where the caller has them)."""
        if j not in self._halves:
            points = self.cleaning[j].of(self.points[j]).points if cleaned is None else cleaned
            self._halves[j] = voxel_downsample(points, 0.5 * self.voxel)
        return self._halves[j]


def _kept(steps: Sequence[Optional[RegistrationResult]], guesses: Sequence[Optional[np.ndarray]], origins: Sequence[np.ndarray], k: int) -> List[int]:
    """The sweeps before k that the map keeps (the first always): those whose step was trusted,
    or flagged with at least :data:`MAP_MIN_FITNESS` of its points on the map it was registered
    onto (on sparse sweeps the confidence flags right steps) and within :data:`MAP_MAX_TURN` and
    :data:`MAP_MAX_SHIFT` of the (4, 4) motion guessed for it, `guesses[j]` (the shift measured
    at its sweep's (3,) point `origins[j]`)."""

    def keeps(step: Optional[RegistrationResult], guess: Optional[np.ndarray], origin: np.ndarray) -> bool:
        if step is None or not step.likely_failed:
            return True
        if step.fitness < MAP_MIN_FITNESS or guess is None:
            return False
        off = pair_errors(step.transformation, guess, origin)
        return off.rotation_deg <= MAP_MAX_TURN and off.translation <= MAP_MAX_SHIFT * step.scale

    return [j for j in range(k) if keeps(steps[j], guesses[j], origins[j])]


def _local_map(
    points: Union[Mapping[int, np.ndarray], Sequence[np.ndarray]], poses: Sequence[np.ndarray], kept: Sequence[int], k: int, size: int
) -> np.ndarray:
    """(M, 3) the last `size` of the sweeps `kept` before sweep k (:func:`_kept`), in sweep k-1's
    frame (its pose's: the motion found from there composes back to the right pose whatever
    that pose is); `points[j]`: sweep j's (N_j, 3) points in its own frame (raw, or on a grid)."""
    into = np.linalg.inv(poses[k - 1])
    return np.concatenate([apply_transform(into @ poses[j], points[j]) for j in kept[-size:]])


def _onto_a_map(config: RegisterConfig) -> RegisterConfig:
    """`config` for registering a sweep onto its local map: a flagged step names the sizes of the
    sweep and the map (are they in the same units?) only where they differ over
    :data:`~o3dsoft.pipeline.SIZE_RATIO_NOTE` times (millimetres among metres; feet among metres
    go unnamed), as the map holds several sweeps and the frames of one sensor differ in size with
    what they see (a depth camera's frame of a wall close up against its map: 4.4-fold)."""
    confidence = config.confidence
    return replace(config, confidence=replace(confidence, size_note_ratio=max(confidence.size_note_ratio, SIZE_RATIO_NOTE)))


def _guess(poses: Sequence[np.ndarray], steps: Sequence[Optional[RegistrationResult]], kept: Sequence[int], k: int, constant_velocity: bool) -> np.ndarray:
    """(4, 4) the guess of sweep k-1 _T_ sweep k: the last of the sweeps `kept` before k
    (:func:`_kept`) at its pose, carried on, once per sweep since, by the last motion between two
    kept sweeps (constant velocity; the identity without it or before any): a step left out of
    the map is not repeated."""
    velocity = np.eye(4)
    if constant_velocity:
        moves = [j for j in kept if j >= 1 and (j - 1) in kept]
        if moves:
            velocity = steps[moves[-1]].transformation  # type: ignore[union-attr]
    last = kept[-1]
    return np.linalg.inv(poses[k - 1]) @ poses[last] @ np.linalg.matrix_power(velocity, k - last)


callable_as_its_function(__name__)
