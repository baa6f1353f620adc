import importlib
import json
import re
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

import o3dsoft
from o3dsoft.cli.main import main
from o3dsoft.errors import InputError, UsageError
from o3dsoft.odometry import OdometryConfig, _guess, _kept, _local_map, errors_against, odometry
from o3dsoft.pipeline import SIZE_RATIO_NOTE, register_on_grid
from o3dsoft.transforms import apply_transform, euler_to_matrix, rigid

from .conftest import ring_sweep

RINGS = tuple(np.arange(-15.0, 8.0, 1.5))  # 16 rings


def _sequence(count: int, seed: int = 0):
    """`count` sweeps of a sensor driving along x in the room of ring_sweep, 0.6 units and 1.5
    degrees of yaw per sweep, and their world_T_sweep (the first the identity)."""
    rng = np.random.default_rng(seed)
    step = rigid(euler_to_matrix([0.0, 0.0, 1.5]), np.array([0.6, 0.1, 0.0]))
    poses = [np.eye(4)]
    for _ in range(count - 1):
        poses.append(poses[-1] @ step)
    start = rigid(np.eye(3), np.array([-8.0, -4.0, 0.0]))  # in the room, facing the box
    return [ring_sweep(start @ P, rng, RINGS) for P in poses], poses


def test_odometry_follows_a_sequence_of_sweeps():
    sweeps, truth = _sequence(6)
    done = []
    result = o3dsoft.odometry(sweeps, o3dsoft.OdometryConfig(map_sweeps=3), progress=lambda k, total: done.append((k, total)))
    assert done == [(k, 6) for k in range(1, 7)]  # the first once all are checked, then each registered
    assert np.array_equal(result.poses[0], np.eye(4)) and result.steps[0] is None
    assert result.flagged == (False,) * 6
    for pose, true in zip(result.poses, truth):
        e = o3dsoft.pair_errors(pose, true)
        assert e.rotation_deg < 0.3 and e.translation < 0.05, e
    doc = json.loads(json.dumps(result.to_dict()))
    assert doc["world"] == "sweep0" and len(doc["sweeps"]) == 6 and "confidence" in doc["sweeps"][1] and "confidence" not in doc["sweeps"][0]


def test_odometry_gives_the_same_poses_at_every_run():
    # Each step's point-to-plane ICP sums in one order (Open3D's sums over threads gave poses that
    # differed in their last bits from run to run, and on a sequence whose frames fix no pose, by
    # metres).
    sweeps, _ = _sequence(4)
    first, second = o3dsoft.odometry(sweeps), o3dsoft.odometry(sweeps)
    assert first.steps[1].icp_method == "plane"
    assert all(np.array_equal(a, b) for a, b in zip(first.poses, second.poses))


def _record_steps(monkeypatch):
    """Record the settings and the initial guess (None: none) of each step's registration, on the
    raw clouds (``register``) or on the sequence's grid (``register_on_grid``), in order (those
    that returned a result)."""
    module = importlib.import_module("o3dsoft.odometry")
    steps = []

    def raw(source, target, settings, **kwargs):
        result = o3dsoft.register(source, target, settings, **kwargs)
        steps.append(SimpleNamespace(settings=settings, init=kwargs.get("init"), on_grid=False))
        return result

    def on_grid(source, target, settings, model, source_name, target_name, init):
        result = register_on_grid(source, target, settings, model, source_name, target_name, init)  # raises where the grid leaves too few points
        steps.append(SimpleNamespace(settings=settings, init=init, on_grid=True))
        return result

    monkeypatch.setattr(module, "register", raw)
    monkeypatch.setattr(module, "register_on_grid", on_grid)
    return steps


def test_the_first_step_is_registered_without_a_guess_and_the_later_ones_from_the_motion(monkeypatch):
    """Before any motion is known, "where the last sweep was" is no guess: ICP from the identity
    slid a room view 1.1 m off and was trusted, and every later pose kept the slide."""
    sweeps, truth = _sequence(4)
    recorded = _record_steps(monkeypatch)
    result = odometry(sweeps, OdometryConfig(map_sweeps=2))
    inits = [step.init for step in recorded]
    assert inits[0] is None and all(init is not None for init in inits[1:])
    assert o3dsoft.pair_errors(inits[2], result.steps[2].transformation).rotation_deg < 0.5  # the motion repeated
    assert all(o3dsoft.pair_errors(p, t).translation < 0.05 for p, t in zip(result.poses, truth))


@pytest.mark.parametrize(
    "config, bounds",
    [
        (OdometryConfig(map_sweeps=2), [None, 45.0, 45.0]),
        (OdometryConfig(map_sweeps=2, guess_max_rotation=10.0), [None, 10.0, 10.0]),
        (OdometryConfig(map_sweeps=2, guess_max_rotation=None), [None, None, None]),
        (OdometryConfig(map_sweeps=2, register=o3dsoft.RegisterConfig(max_rotation=20.0)), [20.0, 20.0, 20.0]),
    ],
)
def test_sweeps_registered_from_a_guess_are_held_near_it(monkeypatch, config, bounds):
    """A frame that shows too little to fix its pose (a flat wall) is searched, and the search can
    trust a pose turned far from the guess: the steps from a guess are held within 45 degrees of
    it, unless the registration's own max_rotation says otherwise (then for every step)."""
    sweeps, truth = _sequence(4)
    recorded = _record_steps(monkeypatch)
    result = odometry(sweeps, config)
    assert [step.settings.max_rotation for step in recorded] == bounds
    assert [step.settings.confidence.size_note_ratio for step in recorded] == [
        SIZE_RATIO_NOTE
    ] * 3  # every step onto a map (first included) names sizes as units differ
    assert all(o3dsoft.pair_errors(p, t).translation < 0.05 for p, t in zip(result.poses, truth))


def _map(points, poses, steps, guesses, k, size, origins=None):
    """The local map before sweep k, of the sweeps :func:`_kept` keeps."""
    return _local_map(points, poses, _kept(steps, guesses, origins or [np.zeros(3)] * len(steps), k), k, size)


def test_the_local_map_and_the_guess_leave_flagged_steps_that_fit_poorly_or_moved_far_out():
    points = [np.full((k + 1, 3), float(k)) for k in range(6)]  # sweep k has k + 1 points
    poses = [np.eye(4)] * 6
    guesses = [None] + [np.eye(4)] * 5
    # steps 2 and 4 flagged, their sweeps off the map; step 1 flagged on the map, at its guess (kept)
    steps = [None] + [SimpleNamespace(likely_failed=k in (1, 2, 4), fitness=0.9 if k == 1 else 0.2, transformation=np.eye(4), scale=10.0) for k in range(1, 6)]
    assert len(_map(points, poses, steps, guesses, 5, 3)) == 1 + 2 + 4  # sweeps 0, 1 and 3: 2 and 4 flagged
    assert len(_map(points, poses, steps, guesses, 4, 2)) == 2 + 4  # sweeps 1 and 3
    assert len(_map(points, poses, steps, guesses, 1, 5)) == 1  # the first alone
    moved = [rigid(np.eye(3), np.array([k, 0.0, 0.0])) for k in range(6)]  # world_T_sweep: in sweep k-1's frame
    assert np.array_equal(_map(points, moved, steps, guesses, 4, 1), points[3])
    assert np.allclose(_map(points, moved, steps, guesses, 4, 2)[:2], points[1] + [-2.0, 0.0, 0.0])
    # A flagged step that fits its map closely but turned far from its guess (a wide ICP distance
    # finds most of a street sweep near the map 95 degrees off), or shifted far, is left out too.
    for far in (rigid(euler_to_matrix([0.0, 0.0, 95.0]), np.zeros(3)), rigid(np.eye(3), np.array([2.0, 0.0, 0.0]))):
        turned = list(steps)
        turned[1] = SimpleNamespace(likely_failed=True, fitness=0.97, transformation=far, scale=10.0)
        assert len(_map(points, poses, turned, guesses, 4, 3)) == 1 + 4  # sweeps 0 and 3
    # Shifts are measured at each sweep's own middle: a turn of 2 degrees about the origin of a
    # georeferenced frame shifts its sweep by 140 km there, and by nothing where its points are.
    utm = np.array([5e5, 4e6, 300.0])
    about_utm = rigid(euler_to_matrix([0.0, 0.0, 2.0]), utm - euler_to_matrix([0.0, 0.0, 2.0]) @ utm)
    turned = list(steps)
    turned[1] = SimpleNamespace(likely_failed=True, fitness=0.97, transformation=about_utm, scale=10.0)
    assert len(_map(points, poses, turned, guesses, 4, 3, [np.zeros(3), utm] + [np.zeros(3)] * 4)) == 1 + 2 + 4  # sweeps 0, 1 and 3
    assert len(_map(points, poses, turned, guesses, 4, 3)) == 1 + 4  # measured at the frame's origin: left out

    # The guess: sweep 5 after the flagged step 4 is the last trusted sweep (3) carried on twice by
    # the last motion between two trusted sweeps (0 -> 1; 2 -> 3 follows a flagged one).
    velocity = rigid(euler_to_matrix([0.0, 0.0, 2.0]), np.array([1.0, 0.0, 0.0]))
    steps[1].transformation, steps[3].transformation, steps[4].transformation = velocity, np.eye(4), rigid(np.eye(3), np.array([50.0, 0, 0]))
    poses = [np.eye(4), velocity, velocity, velocity @ rigid(np.eye(3), np.array([0.0, 3.0, 0.0])), np.eye(4) * 7]
    poses[4][3, 3] = 1.0
    kept = _kept(steps, guesses, [np.zeros(3)] * 6, 5)
    guess = _guess(poses, steps, kept, 5, True)
    assert np.allclose(poses[4] @ guess, poses[3] @ velocity @ velocity)
    assert np.allclose(poses[4] @ _guess(poses, steps, kept, 5, False), poses[3])  # without constant velocity: where sweep 3 is


def test_motions_are_measured_at_the_sensor_unless_the_sweep_is_georeferenced():
    from o3dsoft.odometry import frame_point

    rng = np.random.default_rng(0)
    ahead = rng.uniform([18.0, -3.0, -2.0], [22.0, 3.0, 2.0], (500, 3))  # a narrow forward view, 20 m out
    assert not frame_point(ahead).any()  # its sensor's frame: measured at the sensor
    far = ahead + [5e5, 4e6, 300.0]
    assert np.allclose(frame_point(far), np.median(far, axis=0))


def test_georeferenced_sweeps_give_the_path_and_errors_they_give_near_the_origin():
    # The same sweeps 5e6 units from their frames' origin: each motion is the same motion about a
    # point there, so a turn of 0.01 degrees moves the frame's origin by 700 units.
    sweeps, truth = _sequence(5)
    utm = rigid(np.eye(3), np.array([5e5, 4e6, 300.0]))
    near = odometry(sweeps, OdometryConfig(map_sweeps=3))
    far = odometry([s + utm[:3, 3] for s in sweeps], OdometryConfig(map_sweeps=3))
    far_truth = [utm @ P @ np.linalg.inv(utm) for P in truth]
    assert far.flagged == near.flagged and far.mapped == near.mapped
    assert near.path == pytest.approx(4 * np.hypot(0.6, 0.1), rel=1e-3)  # the sensor's path: its frame's origin
    errors = errors_against(far, far_truth)
    assert errors.path == pytest.approx(far.path, rel=0.02) and 0.8 * near.path < far.path < 1.5 * near.path  # at the sweeps' middles
    assert errors.translation.max() < 0.05 and errors.drift.translation < 0.05 and errors.drift.rotation_deg < 0.3, errors
    assert far.last_from_first == pytest.approx(errors_against(far, far_truth).path, rel=0.1)


def test_the_odometry_command_measures_georeferenced_sweeps_against_a_rounded_reference_at_their_points(tmp_path):
    # A reference of 6-digit rotations (as published), its translations for the rounded rotations:
    # made exact about the frame's origin, 5e6 units away, it would move the sweeps by metres.
    sweeps, truth = _sequence(3, seed=1)
    utm = rigid(np.eye(3), np.array([5e5, 4e6, 300.0]))
    files, rows = [], []
    for k, (sweep, P) in enumerate(zip(sweeps, truth)):
        files.append(tmp_path / f"frame_{k}.ply")
        o3dsoft.write_points(files[-1], sweep + utm[:3, 3])
        far = utm @ P @ np.linalg.inv(utm)
        far[:3, :3] = np.round(far[:3, :3], 6)
        far[:3, 3] = utm[:3, 3] + P[:3, 3] - far[:3, :3] @ utm[:3, 3]
        rows.append(" ".join(f"{v:.17g}" for v in far[:3].reshape(-1)))
    gt = tmp_path / "gt.txt"
    gt.write_text("\n".join(rows) + "\n")
    r = CliRunner().invoke(main, ["odometry", *map(str, files), "--out", str(tmp_path / "odo"), "--gt", str(gt), "--no-progress"])
    assert r.exit_code == 0, r.output
    errors = re.search(r"the last sweep ([0-9.e+-]+) deg / ([0-9.e+-]+) units off \(([0-9.e+-]+) % of the reference path", r.output)
    assert errors is not None, r.output
    assert float(errors[1]) < 0.3 and float(errors[2]) < 0.05 and float(errors[3]) < 5.0, r.output


def test_after_the_first_step_each_sweep_is_registered_on_that_steps_grid(monkeypatch):
    """Each sweep is cleaned and gridded once, not once per map it is in: the steps after the
    first register on the first step's grid, and end where the steps on their own grids do."""
    sweeps, truth = _sequence(5)
    recorded = _record_steps(monkeypatch)
    result = odometry(sweeps, OdometryConfig(map_sweeps=3))
    assert [step.on_grid for step in recorded] == [False, True, True, True]
    assert len({step.voxel for step in result.steps[1:]}) == 1 and result.steps[1].voxel is not None
    recorded.clear()
    each = odometry(sweeps, OdometryConfig(map_sweeps=3, one_grid=False))
    assert [step.on_grid for step in recorded] == [False] * 4
    recorded.clear()
    odometry(sweeps, OdometryConfig(map_sweeps=3, register=o3dsoft.RegisterConfig(voxel=0)))  # no grid: every step raw
    assert [step.on_grid for step in recorded] == [False] * 4
    for pose, other, true in zip(result.poses, each.poses, truth):
        assert o3dsoft.pair_errors(pose, true).translation < 0.05 and o3dsoft.pair_errors(pose, other).translation < 0.02
    assert not any(result.flagged)


def test_a_sweep_the_grid_leaves_too_few_points_is_registered_on_a_grid_of_its_own(monkeypatch):
    # In kilometres among metres: the sequence's grid leaves a handful of its points.
    sweeps, truth = _sequence(6, seed=2)
    sweeps[3] = sweeps[3] / 1000.0
    recorded = _record_steps(monkeypatch)
    result = odometry(sweeps, OdometryConfig(map_sweeps=3))
    assert [step.on_grid for step in recorded] == [False, True, False, True, True]
    assert result.flagged == (False, False, False, True, False, False)
    assert result.steps[3].failure_reason.startswith("the clouds' sizes differ")
    for k in (4, 5):
        assert o3dsoft.pair_errors(result.poses[k], truth[k]).translation < 0.05, k


def test_registering_on_one_grid_is_registering_the_clouds_on_that_grid():
    """``register_on_grid`` ends where ``register`` does on the same grid, from the same guess;
    far from the origin it registers about the target's median."""
    from o3dsoft.coarse import cached_model
    from o3dsoft.pair import PreparedPair, on_grid
    from o3dsoft.preprocess import clean_points

    sweeps, truth = _sequence(2)
    config, model = o3dsoft.RegisterConfig(voxel=0.4), cached_model(None, "cpu")
    guess = rigid(euler_to_matrix([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]))
    plain = o3dsoft.register(sweeps[1], sweeps[0], config, model=model, init=guess)
    for shift in (np.zeros(3), np.array([5e5, 4e6, 300.0])):  # georeferenced: UTM metres
        moved = rigid(np.eye(3), shift)
        init = moved @ guess @ np.linalg.inv(moved)
        source, target = (
            on_grid(clean_points(c), 0.4, config, model.config.k, n)
            for c, n in ((apply_transform(init, sweeps[1] + shift), "sweep"), (sweeps[0] + shift, "map"))
        )
        result = register_on_grid(source, target, config, model, init=init)
        assert result.voxel == 0.4 and not result.likely_failed and result.estimate_from == plain.estimate_from == "initial guess"
        back = np.linalg.inv(moved) @ result.transformation @ moved
        assert o3dsoft.pair_errors(back, truth[1]).translation < 0.05
        assert o3dsoft.pair_errors(back, plain.transformation).translation < 0.005, shift
        assert abs(result.num_source - plain.num_source) <= 0.02 * plain.num_source
    with pytest.raises(ValueError, match="two GridClouds of the same voxel"):
        PreparedPair(target, target._replace(voxel=0.5), config, model.config.k)
    with pytest.raises(ValueError, match="two GridClouds of the same voxel"):
        PreparedPair(target, sweeps[1], config, model.config.k)


def test_a_step_on_the_grid_is_refined_and_scored_on_its_whole_clouds_once(monkeypatch):
    """A pair already on its registration grid (a sweep onto its map) refines its guess on every
    grid point: no second, coarser grid for the attempts, so no second ICP, normals and scoring
    at full resolution after them."""
    import o3dsoft.pair as pair_module
    from o3dsoft.coarse import cached_model
    from o3dsoft.pair import on_grid
    from o3dsoft.preprocess import clean_points

    estimated = []  # the sizes of the target clouds whose normals the pair estimates
    normals = pair_module.refine_stage.normals
    monkeypatch.setattr(pair_module.refine_stage, "normals", lambda points, *a, **k: estimated.append(len(points)) or normals(points, *a, **k))

    sweeps, truth = _sequence(2)
    model = cached_model(None, "cpu")
    config = o3dsoft.RegisterConfig(voxel=0.2, attempt_points=2500)  # fewer than either grid cloud holds
    source, target = (on_grid(clean_points(c), 0.2, config, model.config.k, n) for c, n in ((sweeps[1], "sweep"), (sweeps[0], "map")))
    assert 2 * config.attempt_points < min(len(source.points), len(target.points)) <= max(len(source.points), len(target.points)) <= 3 * config.attempt_points
    result = register_on_grid(source, target, config, model, init=np.eye(4))
    assert result.points_used["attempts"] == result.points_used["final"] == (len(source.points), len(target.points))
    assert estimated.count(len(target.points)) == 1  # once, for every ICP and the scoring
    assert not result.likely_failed and o3dsoft.pair_errors(result.transformation, truth[1]).translation < 0.05
    plain = o3dsoft.register(sweeps[1], sweeps[0], config, model=model, init=np.eye(4))  # clouds as given: attempts on a coarser grid
    assert plain.points_used["attempts"][1] < plain.points_used["final"][1]
    larger = register_on_grid(
        source, target, replace(config, attempt_points=1000), model, init=np.eye(4)
    )  # over GRID_WORK_ATTEMPTS times it: a searched step would refine every estimate on them
    assert larger.points_used["attempts"][1] < larger.points_used["final"][1] == len(target.points)


def test_a_step_on_the_grid_grids_the_sweep_where_its_guess_puts_it_and_the_map_from_half_grids():
    """The sweep is gridded in the map's axes (its own give other cells, whose centroids lie in
    another pattern on each surface), the map is its sweeps' half grids on the grid, and the
    counts of what cleaning removed are the map's sweeps' together."""
    from o3dsoft.odometry import _checked_sweeps, _SweepGrids
    from o3dsoft.pair import on_grid
    from o3dsoft.preprocess import CleanReport, clean_points, voxel_downsample

    sweeps, poses = _sequence(4)
    sweeps[0] = np.vstack([sweeps[0], np.full((3, 3), np.nan)])  # 3 rows of NaN
    sweeps[1] = np.vstack([sweeps[1], sweeps[1][:5]])  # 5 duplicates
    config, k = o3dsoft.RegisterConfig(), 16
    grids = _SweepGrids(*_checked_sweeps(sweeps, ["a", "b", "c", "d"], k), 0.4, config, k)
    turned = rigid(euler_to_matrix([0.0, 0.0, 30.0]), np.array([0.5, 0.0, 0.0]))
    clean = [clean_points(c).points for c in sweeps]

    def fresh_map(in_map, at):
        into = np.linalg.inv(poses[at - 1])
        halves = np.concatenate([apply_transform(into @ poses[j], voxel_downsample(clean[j], 0.2)) for j in in_map])
        return on_grid(CleanReport(halves, 0, 0), 0.4, config, k, "map").points

    source, local_map = grids.pair(poses, [0, 1], 2, turned, "map")
    where_guessed, own = (on_grid(clean_points(c), 0.4, config, k, "s").points for c in (apply_transform(turned, sweeps[2]), sweeps[2]))
    assert np.array_equal(source.points, where_guessed) and len(own) != len(where_guessed)
    assert np.array_equal(local_map.points, fresh_map([0, 1], 2))
    assert (local_map.cleaned.non_finite, local_map.cleaned.duplicates) == (3, 5)
    _, later = grids.pair(poses, [1, 2], 3, turned, "map")  # sweep 0 out of the window: never needed again
    assert np.array_equal(later.points, fresh_map([1, 2], 3)) and (later.cleaned.non_finite, later.cleaned.duplicates) == (0, 5)
    assert sorted(grids._halves) == [1, 2, 3]
    result = odometry(sweeps, OdometryConfig(map_sweeps=2))
    assert result.steps[2].removed["target_non_finite"] == 3 and result.steps[2].removed["target_duplicates"] == 5
    assert result.steps[2].timings_ms["map"] > 0 and result.steps[2].timings_ms["total"] >= result.steps[2].timings_ms["map"]


@pytest.mark.parametrize("size", [1, 3])
def test_a_sweep_in_other_units_is_flagged_and_the_next_ones_stay_right(size):
    # Its step flagged and off the map, it stays out of the next map and its motion out of the next guess.
    sweeps, truth = _sequence(6, seed=2)
    sweeps[3] = 1000.0 * sweeps[3]  # millimetres among metres
    result = o3dsoft.odometry(sweeps, o3dsoft.OdometryConfig(map_sweeps=size))
    assert result.flagged == (False, False, False, True, False, False)
    assert result.mapped == (True, True, True, False, True, True)
    assert result.steps[3].failure_reason.startswith("the clouds' sizes differ")  # are they in the same units?
    assert [entry.get("in_map") for entry in result.to_dict()["sweeps"]] == [None, True, True, False, True, True]
    for k in (4, 5):
        e = o3dsoft.pair_errors(result.poses[k], truth[k])
        assert e.rotation_deg < 0.3 and e.translation < 0.05, (k, e)


def test_two_sweeps_in_other_units_in_a_row_are_both_named():
    """The second is compared with the sweeps of its map (in metres), not with the first (in
    millimetres too)."""
    sweeps, _ = _sequence(6, seed=2)
    sweeps[3], sweeps[4] = 1000.0 * sweeps[3], 1000.0 * sweeps[4]
    result = o3dsoft.odometry(sweeps, o3dsoft.OdometryConfig(map_sweeps=3))
    for k in (3, 4):
        assert result.flagged[k] and result.steps[k].failure_reason.startswith("the clouds' sizes differ"), k


def test_odometry_refuses_what_it_cannot_use(monkeypatch):
    sweeps, _ = _sequence(2)
    with pytest.raises(UsageError, match="map_sweeps must be a whole number of at least 1"):
        odometry(sweeps, OdometryConfig(map_sweeps=0))
    with pytest.raises(InputError, match="at least two sweeps, got 1"):
        odometry(sweeps[:1])
    with pytest.raises(InputError, match="3 names for 2 sweeps"):
        odometry(sweeps, names=["a", "b", "c"])
    with pytest.raises(UsageError, match="config must be an o3dsoft.OdometryConfig"):
        odometry(sweeps, o3dsoft.RegisterConfig())
    with pytest.raises(UsageError, match="map_sweeps must be a whole number"):
        odometry(sweeps, OdometryConfig(map_sweeps=True))
    with pytest.raises(UsageError, match="constant_velocity must be True or False, got 'no'"):
        odometry(sweeps, OdometryConfig(constant_velocity="no"))  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="one_grid must be True or False, got 1"):
        odometry(sweeps, OdometryConfig(one_grid=1))  # type: ignore[arg-type]
    for bound in (0, 200.0, True, "45"):
        with pytest.raises(UsageError, match=r"guess_max_rotation must be in \(0, 180\] degrees or None"):
            odometry(sweeps, OdometryConfig(guess_max_rotation=bound))  # type: ignore[arg-type]
    OdometryConfig(map_sweeps=np.int64(3)).validate()
    # A bad sweep anywhere fails before the first is registered.
    registered = []
    monkeypatch.setattr(importlib.import_module("o3dsoft.odometry"), "register", lambda *a, **k: registered.append(1))
    with pytest.raises(InputError, match="sweep2: 1 distinct finite points"):
        odometry(iter([sweeps[0], sweeps[1], np.zeros((50, 3))]))  # any iterable
    assert not registered


def test_odometry_command_writes_poses_multiway_reads(tmp_path):
    sweeps, truth = _sequence(4, seed=1)
    files = []
    for k, sweep in enumerate(sweeps):
        files.append(tmp_path / f"frame_{k:03d}.ply")
        o3dsoft.write_points(files[-1], sweep)
    gt = tmp_path / "gt.txt"
    gt.write_text("".join(" ".join(f"{v:.12g}" for v in P[:3].reshape(-1)) + "\n" for P in truth))
    out = tmp_path / "odo"
    r = CliRunner().invoke(main, ["odometry", *map(str, files), "--out", str(out), "--gt", str(gt), "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "o3dsoft odometry 4 sweeps" in r.output and "Steps flagged likely failed: 0 of 3." in r.output
    assert "Against --gt (lower is better): step errors median" in r.output
    rows = (out / "poses.txt").read_text().splitlines()
    assert len(rows) == 4 and all(len(row.split()) == 12 for row in rows)
    poses = o3dsoft.read_poses(out / "poses.txt", [str(f) for f in files])  # multiway --init's reader
    doc = json.loads((out / "poses.json").read_text())
    for pose, entry, true in zip(poses, doc["sweeps"], truth):
        assert np.allclose(pose, entry["world_T_sweep"], atol=1e-8)
        assert o3dsoft.pair_errors(pose, true).translation < 0.05
    assert "% of the reference path" in r.output
    # its poses.json is read as --gt (and by multiway --init) as its poses.txt is
    again = o3dsoft.read_poses(out / "poses.json", [str(f) for f in files])
    assert all(np.allclose(a, b, atol=1e-8) for a, b in zip(again, poses))
    # sweeps numbered without leading zeros, in a shell glob's order: said
    named = [tmp_path / name for name in ("f0.ply", "f1.ply", "f10.ply", "f2.ply")]
    for src, dst in zip(files, named):
        dst.write_bytes(src.read_bytes())
    r = CliRunner().invoke(main, ["odometry", *map(str, named), "--out", str(tmp_path / "glob"), "--no-progress"])
    assert r.exit_code == 0 and f"so {named[2]} comes before {named[3]}: give them in the order taken" in r.output
    # bad input: a sweep that cannot be registered, one sweep, a reference with a pose too few
    np.save(tmp_path / "empty.npy", np.full((40, 3), np.nan))
    r = CliRunner().invoke(main, ["odometry", *map(str, files), str(tmp_path / "empty.npy"), "--out", str(tmp_path / "late")])
    assert r.exit_code == 1 and "empty.npy: 0 distinct finite points" in r.output and not (tmp_path / "late").exists()
    r = CliRunner().invoke(main, ["odometry", str(files[0]), "--out", str(tmp_path / "one")])
    assert r.exit_code == 2 and "odometry needs at least two" in r.output and not (tmp_path / "one").exists()
    gt.write_text("".join(gt.read_text().splitlines(keepends=True)[:3]))
    r = CliRunner().invoke(main, ["odometry", *map(str, files), "--out", str(tmp_path / "bad"), "--gt", str(gt)])
    assert r.exit_code == 1 and "gt.txt: 3 poses for 4 sweeps" in r.output and "Traceback" not in r.output and not (tmp_path / "bad").exists()


def test_the_odometry_command_registers_every_step_on_a_grid_of_its_own_where_asked(tmp_path, monkeypatch):
    files = []
    for k, sweep in enumerate(_sequence(3)[0]):
        files.append(tmp_path / f"frame_{k}.ply")
        o3dsoft.write_points(files[-1], sweep)
    seen = []
    module = importlib.import_module("o3dsoft.odometry")
    real = module.odometry
    monkeypatch.setattr(module, "odometry", lambda clouds, config, **kwargs: seen.append(config.one_grid) or real(clouds, config, **kwargs))
    for flags in ([], ["--grid-per-step"]):
        r = CliRunner().invoke(main, ["odometry", *map(str, files), "--out", str(tmp_path / "odo"), "--no-progress", *flags])
        assert r.exit_code == 0, r.output
    assert seen == [True, False]


def test_the_odometry_warning_says_whether_a_flagged_step_stayed_in_the_map(tmp_path):
    sweeps, _ = _sequence(4, seed=2)
    sweeps[2] = 1000.0 * sweeps[2]  # millimetres among metres: flagged, and off the map
    files = []
    for k, sweep in enumerate(sweeps):
        files.append(tmp_path / f"frame_{k}.ply")
        o3dsoft.write_points(files[-1], sweep)
    r = CliRunner().invoke(main, ["odometry", *map(str, files), "--out", str(tmp_path / "odo"), "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "Warning: 1 step(s) flagged likely failed" in r.output and "frame_2.ply (confidence" in r.output and "left out of the map)" in r.output
    doc = json.loads((tmp_path / "odo" / "poses.json").read_text())
    assert [entry.get("in_map") for entry in doc["sweeps"]] == [None, True, False, True]


def test_odometry_command_names_a_pattern_that_matched_no_file(tmp_path):
    # The shell passes a pattern that matches nothing on as written: one path, which is no file.
    r = CliRunner().invoke(main, ["odometry", str(tmp_path / "frame_*.ply"), "--out", str(tmp_path / "odo"), "--no-progress"])
    assert r.exit_code == 2 and "frame_*.ply: no such file (a pattern that matched no file)" in r.output, r.output
    assert not (tmp_path / "odo").exists()


def test_a_flagged_step_names_different_sizes_only_where_the_sweep_and_its_map_differ_as_units_do():
    """Frames of one sensor differ in size with what they see, and the local map is larger than
    one (a depth camera close up to a wall: 4.4 times): "are they in the same units?" belongs to
    sweeps that differ from their map as units do (1000-fold; feet among metres go unnamed)."""
    from o3dsoft.confidence import ConfidenceConfig
    from o3dsoft.odometry import _onto_a_map

    assert _onto_a_map(o3dsoft.RegisterConfig()).confidence.size_note_ratio == SIZE_RATIO_NOTE
    wider = o3dsoft.RegisterConfig(confidence=ConfidenceConfig(size_note_ratio=50.0), voxel=0.5)
    assert _onto_a_map(wider) == wider  # a user's wider bound stands, and nothing else changes
    sweeps, _ = _sequence(2)
    for factor, named in ((4.4, False), (1000.0, True)):
        step = o3dsoft.register(factor * sweeps[1], sweeps[0], _onto_a_map(o3dsoft.RegisterConfig()))
        assert step.likely_failed and step.failure_reason.startswith("the clouds' sizes differ") == named, (factor, step.failure_reason)
