from types import SimpleNamespace

import numpy as np
import pytest

import o3dsoft
from o3dsoft import refine
from o3dsoft.config import RegisterConfig
from o3dsoft.metrics import rotation_error_deg
from o3dsoft.pipeline import register
from o3dsoft.refine import ICPConfig, downsample, icp
from o3dsoft.transforms import euler_to_matrix, rigid

from .conftest import blob, random_transform, ring_sweep
from .fakes import record_open3d_icp


def test_downsample_bounds_large_clouds():
    pts = np.random.default_rng(0).uniform(-1, 1, size=(300_000, 3)) * [1, 1, 0.01]
    down = downsample(pts, 50_000)
    assert 10_000 < len(down) <= 50_000
    assert downsample(pts[:1000], 50_000) is not None and len(downsample(pts[:1000], 50_000)) == 1000


def test_icp_ends_at_the_least_squares_optimum(modelnet_root):
    from o3dsoft.data import get_protocol, load_pairs
    from o3dsoft.refine import polish

    # The first `paper` test pair (identical points, shuffled) from the shipped network's estimate:
    # there Open3D's ICP stopped at 1.7e-5 degrees; the float64 step reaches the optimum (~4e-8).
    pair = load_pairs(modelnet_root, "test", get_protocol("paper"), 0)[0]
    source, target = pair.source.astype(np.float64), pair.target.astype(np.float64)
    start = register(source, target, RegisterConfig(refine=False)).coarse_transformation
    T = icp(source, target, start, 0.1).transformation
    assert rotation_error_deg(T[:3, :3], pair.transform[:3, :3]) < 1e-6
    # Never worse: from a transform off by more than the distance, it is returned unchanged.
    far = np.eye(4)
    far[:3, 3] = [5.0, 0, 0]
    assert np.array_equal(polish(source, target, far, 0.1), far)


def test_only_icps_last_stage_needs_to_converge_tightly(modelnet_root, monkeypatch):
    from o3dsoft.data import get_protocol, load_pairs

    # Stages before the last stop at a relative change of 1e-4 (ICPConfig.early_relative): from 8
    # degrees off, the first `paper` pairs (identical points) still end at the optimum, where
    # every stage run to 1e-7 ends too.
    pairs = load_pairs(modelnet_root, "test", get_protocol("paper"), 0)
    rng = np.random.default_rng(0)
    for pair in (pairs[i] for i in range(8)):
        source, target = pair.source.astype(np.float64), pair.target.astype(np.float64)
        start = random_transform(rng, max_angle=8.0, max_t=0.02) @ pair.transform
        for config in (ICPConfig(), ICPConfig(early_relative=1e-7)):
            T = icp(source, target, start, 0.1, config).transformation
            assert rotation_error_deg(T[:3, :3], pair.transform[:3, :3]) < 1e-6
    # The criteria as Open3D receives them: loose in the stages before the last, tight in it.
    calls = record_open3d_icp(monkeypatch)
    icp(source, target, start, 0.1, ICPConfig(schedule=(1.0, 0.3, 0.1), noise_factor=0.0))
    assert [criterion for _, criterion in calls] == [1e-4, 1e-4, 1e-7]


def test_icp_keeps_the_true_pairs_of_noisy_partial_clouds(modelnet_root):
    from o3dsoft.data import get_protocol, load_pairs
    from o3dsoft.preprocess import normalisation_for
    from o3dsoft.refine import ICPConfig, icp

    # rpmnet-crop pairs (independent crops, noise of 0.01 per cloud) started at the ground truth:
    # with the schedule's last distance (0.01 x scale, below the noise) ICP drifts away; with
    # that distance raised to 2.5x the residual it stays closer.
    pairs = load_pairs(modelnet_root, "test", get_protocol("rpmnet-crop"), 0)
    errors = {0.0: [], 2.5: []}
    for i in range(20):
        pair = pairs[i]
        source, target = pair.source.astype(np.float64), pair.target.astype(np.float64)
        distance = 0.1 * normalisation_for(source, target).scale
        for factor in errors:
            T = icp(source, target, pair.transform, distance, ICPConfig(noise_factor=factor)).transformation
            errors[factor].append(rotation_error_deg(T[:3, :3], pair.transform[:3, :3]))
    assert np.median(errors[2.5]) < 0.7 * np.median(errors[0.0])


def test_the_noise_aware_stage_tightens_as_the_fit_does(bunny_root, monkeypatch):
    from o3dsoft import refine
    from o3dsoft.preprocess import normalisation_for
    from o3dsoft.scans import read_conf, relative_pose

    # Two real scans that overlap by 39 %, ICP started at the ground truth. After the loose
    # stages the residual is mostly misalignment, not noise: a last stage at 2.5x that residual
    # alone stays 2.3 degrees off; tightened while the residual shrinks, it comes back.
    source = o3dsoft.read_points(bunny_root / "bun090.ply")
    target = o3dsoft.read_points(bunny_root / "bun180.ply")
    truth = relative_pose(read_conf(bunny_root / "bun.conf"), "bun090.ply", "bun180.ply")
    distance = 0.1 * normalisation_for(source, target).scale
    T = refine.icp(source, target, truth, distance).transformation
    assert rotation_error_deg(T[:3, :3], truth[:3, :3]) < 1.0
    T = refine.icp(source, target, truth, distance, refine.ICPConfig(noise_rounds=1)).transformation
    assert rotation_error_deg(T[:3, :3], truth[:3, :3]) > 1.5


def test_point_to_plane_icp_runs_no_noise_rounds(bunny_root, monkeypatch):
    from o3dsoft import refine
    from o3dsoft.preprocess import normalisation_for
    from o3dsoft.scans import read_conf, relative_pose
    from o3dsoft.transforms import euler_to_matrix, rigid

    # Two scans placed 5 degrees off: after the loose stages the point-to-point residual puts
    # point-to-point ICP's last stage above the schedule's distance; point-to-plane ICP's last
    # stage stays at it.
    source = o3dsoft.read_points(bunny_root / "bun090.ply")[::4]
    target = o3dsoft.read_points(bunny_root / "bun180.ply")[::4]
    truth = relative_pose(read_conf(bunny_root / "bun.conf"), "bun090.ply", "bun180.ply")
    start = truth @ rigid(euler_to_matrix([5.0, 0.0, 0.0]), np.zeros(3))
    distance = 0.1 * normalisation_for(source, target).scale
    calls = record_open3d_icp(monkeypatch)
    refine.icp(source, target, start, distance, refine.ICPConfig(method="point"))
    assert len(calls) >= 3 and calls[2][0] > 0.1 * distance  # a noise round, wider than the schedule's last
    calls.clear()
    refine.icp(source, target, start, distance, refine.ICPConfig(method="plane"))
    assert [d for d, _ in calls] == pytest.approx([distance, 0.3 * distance, 0.1 * distance])


def test_residual_is_the_noise_level():
    from scipy.spatial import cKDTree

    from o3dsoft.refine import residual

    rng = np.random.default_rng(0)
    target = blob(rng, 2000)
    tree = cKDTree(target)
    assert residual(target, tree, np.eye(4), 0.5) == 0.0  # identical point sets
    noisy = target + rng.normal(scale=0.01, size=target.shape)
    # The nearest-neighbour distance of 3-D Gaussian noise of sigma 0.01 has a median of ~0.015.
    assert 0.008 < residual(noisy, tree, np.eye(4), 0.5) < 0.02
    assert residual(target + 10.0, tree, np.eye(4), 0.5) == 0.0  # no pair within the distance


def test_a_schedule_starts_where_the_estimate_is_known_to_be():
    config = ICPConfig()  # stages at 1.0, 0.3 and 0.1 of the distance
    assert config.starting_at(0.75).schedule == (0.75, 0.3, 0.1)
    assert config.starting_at(0.2).schedule == (0.2, 0.1)
    assert config.starting_at(1.5) is config  # never looser than the schedule's own start


def test_the_final_icp_runs_the_last_stage_only(bunny_root, monkeypatch):
    assert ICPConfig().final().schedule == (0.1,) and ICPConfig(schedule=(0.5,)).final().schedule == (0.5,)
    # One Open3D call: a single stage has no noise rounds, whose floor (a point-to-point residual)
    # independent samplings' spacing would set.
    points = o3dsoft.read_points(bunny_root / "bun000.ply")[::4]
    calls = record_open3d_icp(monkeypatch)
    icp(points, points, np.eye(4), 0.01, ICPConfig(method="plane").final())
    assert [distance for distance, _ in calls] == [pytest.approx(0.001)]


def test_point_to_plane_stops_at_its_own_tolerance(bunny_root, monkeypatch):
    # It converges in a few iterations; at 1e-7 the pairs that flicker at the tight distance keep
    # it going up to max_iterations. Point-to-point keeps the tighter tolerance its polish needs.
    points = o3dsoft.read_points(bunny_root / "bun000.ply")[::8]
    calls = record_open3d_icp(monkeypatch)
    for method in ("plane", "point"):
        icp(points, points, np.eye(4), 0.01, ICPConfig(method=method, noise_factor=0.0))
    assert [criterion for _, criterion in calls] == [pytest.approx(1e-4)] * 2 + [pytest.approx(1e-5)] + [pytest.approx(1e-4)] * 2 + [pytest.approx(1e-7)]


def test_the_quick_icp_ranks_with_the_loose_stages_only():
    quick = ICPConfig().quick(20)
    assert quick.schedule == (1.0, 0.3) and not quick.polish and quick.noise_factor == 0 and quick.max_iterations == 20
    assert ICPConfig(schedule=(0.5,)).quick(5).schedule == (0.5,)


def test_point_to_plane_with_the_normals_given_once_is_the_same_icp():
    from o3dsoft.refine import normals

    rng = np.random.default_rng(9)
    src = blob(rng, 3_000)
    T = random_transform(rng, 5.0, 0.05)
    tgt = src @ T[:3, :3].T + T[:3, 3]
    config = ICPConfig(method="plane")
    inside = icp(src, tgt, np.eye(4), 0.3, config)
    given = icp(src, tgt, np.eye(4), 0.3, config, normals(tgt, config.normal_neighbours, config.normal_within))
    assert np.allclose(inside.transformation, given.transformation, rtol=0, atol=1e-12)
    assert rotation_error_deg(given.transformation[:3, :3], T[:3, :3]) < 0.01


def _ground_strip_beside_a_wall() -> tuple:
    """(ground, wall): two rows of ground 0.1 apart with a point every 0.3 (z = 0), and a wall of
    spacing 0.1 at 0.6 from them (x, 0.7, z). As on a LiDAR frame on a coarse grid, the nearest
    20 points of a ground point reach the wall; within 5 spacings (0.5) lie only ground points."""
    ground = np.array([(a, b, 0.0) for a in np.arange(0, 3.01, 0.3) for b in (0.0, 0.1)])
    wall = np.array([(a, 0.7, c) for a in np.arange(0, 3.01, 0.1) for c in np.arange(0, 1.01, 0.1)])
    return ground, wall


def _tilt_deg(n: np.ndarray, axis: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(n @ axis), 0, 1)))


def test_normals_stay_on_the_points_own_surface():
    from o3dsoft.refine import normals

    ground, wall = _ground_strip_beside_a_wall()
    cloud = np.vstack([ground, wall])
    up = np.array([0.0, 0.0, 1.0])
    bounded = _tilt_deg(normals(cloud, 20, within=ICPConfig().normal_within)[: len(ground)], up)
    nearest = _tilt_deg(normals(cloud, 20, within=0.0)[: len(ground)], up)
    assert bounded.max() < 0.1
    assert np.median(nearest) > 2.0  # the nearest 20, however far, take in the wall


def test_a_point_with_few_neighbours_within_takes_its_nearest_plane():
    """Open3D gives (0, 0, 1) to a point with fewer than 3 neighbours within the radius: such
    points get the plane through their nearest points instead."""
    from o3dsoft.refine import normals
    from o3dsoft.transforms import apply_transform

    rng = np.random.default_rng(4)
    u, v = np.meshgrid(np.arange(0, 3, 0.1), np.arange(0, 3, 0.1))
    plane = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    far = np.array([[3 + 0.8 * k, 1.5 + 0.1 * (k % 2), 0.0] for k in range(6)])  # sparse, on the same plane
    T = random_transform(rng, 60.0, 0.0)  # off the axes: (0, 0, 1) is wrong there
    cloud = apply_transform(T, np.vstack([plane, far]))
    n = normals(cloud, 20, within=ICPConfig().normal_within)
    assert _tilt_deg(n, T[:3, 2]).max() < 1.0


def test_points_whose_neighbours_within_follow_a_line_take_their_nearest_plane():
    """A sparse LiDAR sweep's rings: along each line of a tilted plane the points are 0.1 apart,
    the lines 0.6 apart. Within 5 spacings (0.5) lie only a point's own line, whose plane turns
    freely about it; the nearest 20 reach the next lines and fix the plane."""
    from o3dsoft.refine import normals
    from o3dsoft.transforms import apply_transform

    rng = np.random.default_rng(5)
    lines = np.array([(a, b, 0.0) for b in np.arange(0, 3.01, 0.6) for a in np.arange(0, 6.01, 0.1)])
    lines += rng.normal(0.0, 1e-4, lines.shape)  # a sensor's noise, far below the spacing
    T = random_transform(rng, 60.0, 0.0)
    n = normals(apply_transform(T, lines), 20, within=ICPConfig().normal_within)
    assert _tilt_deg(n, T[:3, 2]).max() < 1.0


def test_point_to_plane_icp_keeps_a_sparse_sweeps_rings_apart():
    """On a sweep of few rings the nearest 20 points of a point lie along its ring, whose plane
    turns freely about it: with such normals ICP from the truth slid one sweep's rings onto the
    other's, the whole 1.3 m the sensor moved. Widened until they span a plane, they hold."""
    from o3dsoft.metrics import pair_errors

    rng = np.random.default_rng(3)
    moved = rigid(euler_to_matrix(np.array([0.0, 0.0, 4.0])), np.array([1.3, 0.2, 0.0]))
    source, target = ring_sweep(moved, rng), ring_sweep(np.eye(4), rng)
    result = icp(source, target, moved, 3.0, ICPConfig(method="plane"))
    errors = pair_errors(result.transformation, moved)
    assert errors.rotation_deg < 0.5 and errors.translation < 0.1


def test_the_normals_are_bounded_on_a_voxel_grid_only():
    """A random sample spaces its points unevenly (within 5 median spacings of a point on a
    surface lie about 17 others on average, far fewer where it is sparse): its normals take the
    nearest 20, however far."""
    from o3dsoft.pair import PreparedPair

    rng = np.random.default_rng(2)
    sphere = rng.normal(size=(40_000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)  # a dense surface: a grid from the data
    on_grid = PreparedPair(sphere, sphere + 1e-3, RegisterConfig(), k=8)
    as_given = PreparedPair(sphere[:6_000], sphere[:6_000] + 1e-3, RegisterConfig(), k=8)
    assert on_grid.voxel is not None and on_grid.config.icp.normal_within == ICPConfig().normal_within > 0
    assert as_given.voxel is None and as_given.config.icp.normal_within == 0.0
    tight = PreparedPair(sphere, sphere + 1e-3, RegisterConfig(icp=ICPConfig(normal_within=1.0)), k=8)  # within 1 spacing: few
    assert np.array_equal(tight.target_normals("full"), refine.normals(tight.full[1], 20, 1.0))
    assert not np.array_equal(tight.target_normals("full"), refine.normals(tight.full[1], 20, 0.0))


@pytest.mark.parametrize("method", ["point", "plane"])
def test_icp_that_runs_off_every_partner_keeps_its_start(monkeypatch, method):
    # Point-to-plane steps on a handful of matched points once went thousands of scene sizes away
    # (a small object onto a large scene: a pose 16 km from a 50 m scene).
    rng = np.random.default_rng(0)
    source = rng.normal(size=(300, 3))
    start = np.eye(4)
    start[:3, 3] = [0.05, 0.0, 0.0]
    away = np.eye(4)
    away[:3, 3] = [1e4, 0.0, 0.0]
    monkeypatch.setattr(refine.o3d.pipelines.registration, "registration_icp", lambda *args, **kwargs: SimpleNamespace(transformation=away))
    monkeypatch.setattr(refine, "plane_steps", lambda *args, **kwargs: away)
    result = refine.icp(source, source, start, 0.5, refine.ICPConfig(method=method))
    assert np.array_equal(result.transformation, start) and result.fitness == 1.0


def _bumpy_surface(rng, n):
    """(n, 3) points drawn at random on z = 0.1 sin(3x) cos(2y) over [-1, 1]^2: a surface that
    holds every motion."""
    xy = rng.uniform(-1, 1, (n, 2))
    return np.c_[xy, 0.1 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])]


@pytest.mark.parametrize("seed", [0, 1])
def test_point_to_plane_steps_are_open3ds(seed):
    from o3dsoft.refine import normals, plane_steps

    rng = np.random.default_rng(seed)
    target, source = _bumpy_surface(rng, 3000), _bumpy_surface(rng, 2500)  # two samplings, as scans are
    n = normals(target, 20)
    start = rigid(euler_to_matrix(rng.uniform(-4, 4, 3)), rng.uniform(-0.05, 0.05, 3))
    reg = refine.o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=50)
    o3d_target = refine.to_open3d(target)
    o3d_target.normals = refine.o3d.utility.Vector3dVector(n)
    theirs = np.asarray(
        reg.registration_icp(refine.to_open3d(source), o3d_target, 0.1, start, reg.TransformationEstimationPointToPlane(), criteria).transformation
    )
    ours = plane_steps(source, target, n, start, 0.1, criteria)
    assert np.abs(ours - theirs).max() < 1e-9  # the same steps; only the order of the sums differs
    assert rotation_error_deg(ours[:3, :3], np.eye(3)) < 0.5 and np.abs(ours[:3, 3]).max() < 0.01


def test_point_to_plane_steps_leave_a_motion_no_pair_holds_where_it_is():
    from o3dsoft.refine import plane_steps

    # A flat square onto itself shifted within its plane: every normal is z, so the normal
    # equations hold no shift along x or y and no turn about z (singular); ICP moves it along z only.
    rng = np.random.default_rng(2)
    plate = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    start = rigid(np.eye(3), np.array([0.03, -0.02, 0.05]))
    criteria = refine.o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=10)
    T = plane_steps(plate, plate, np.tile([0.0, 0.0, 1.0], (500, 1)), start, 0.2, criteria)
    assert np.all(np.isfinite(T)) and np.allclose(T[:2, 3], [0.03, -0.02], atol=1e-12) and abs(T[2, 3]) < 1e-12


def test_registering_scans_twice_gives_the_same_pose_to_the_bit(bunny_root):
    # Open3D's point-to-plane ICP sums its normal equations over threads in no fixed order: one
    # pair of scans came back a little different at every call, and where the surfaces hold the
    # pose loosely, far apart.
    source = o3dsoft.read_points(bunny_root / "bun045.ply")
    target = o3dsoft.read_points(bunny_root / "bun000.ply")
    first, second = register(source, target), register(source, target)
    assert first.icp_method == "plane"
    assert np.array_equal(first.transformation, second.transformation) and first.confidence == second.confidence
