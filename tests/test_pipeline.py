import math
from dataclasses import replace

import numpy as np
import pytest

import o3dsoft
from o3dsoft import degeneracy as degeneracy_stage
from o3dsoft.baselines import GlobalConfig
from o3dsoft.coarse import load_model
from o3dsoft.confidence import ConfidenceConfig
from o3dsoft.config import FeatureSearchConfig, RegisterConfig, RestartConfig, SearchConfig, StartsConfig
from o3dsoft.errors import InputError, UsageError
from o3dsoft.metrics import pair_errors, rotation_error_deg
from o3dsoft.pipeline import register
from o3dsoft.preprocess import scene_size
from o3dsoft.refine import ICPConfig
from o3dsoft.search import FeatureMatchConfig
from o3dsoft.symmetry import SymmetryConfig
from o3dsoft.transforms import euler_to_matrix, rigid, rotation_angle_deg

from .conftest import EXAMPLES, apply, blob, python_output, random_transform
from .fakes import NO_SECOND, AlwaysWrongModel, NearSightedModel, blob_pair, moved_bunny, record_icp


def test_register_small_motion_recovered_after_icp(tiny_model_path):
    # Within ICP's basin the pipeline must be exact, whatever the coarse stage says.
    src, tgt, T = blob_pair()
    cfg = RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5))
    res = register(src, tgt, cfg)
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1e-3 and e.translation < 1e-4
    assert res.fitness == pytest.approx(1.0)
    assert res.inlier_rmse < 1e-5
    assert res.transformation.shape == (4, 4) and res.transformation.dtype == np.float64
    assert res.confidence > 0.99 and not res.likely_failed and res.fitness_tight == pytest.approx(1.0)
    assert res.failure_reason is None
    assert 0.0 < res.mean_weight <= 1.0
    assert set(res.timings_ms) >= {"clean", "sample_normalise", "coarse", "refine", "score", "total"}


def test_the_result_is_rigid_to_float64_precision_and_reads_as_a_summary(tiny_model_path):
    # The network's rotations are float32 products (orthonormal to about 1e-7): every transform
    # the result gives is projected onto the rotations.
    import pickle

    src, tgt, _ = blob_pair(seed=6)
    res = register(src, tgt, RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5)))
    for name in ("transformation", "coarse_transformation", "network_transformation"):
        R = getattr(res, name)[:3, :3]
        assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12 and np.linalg.det(R) == pytest.approx(1.0, abs=1e-12), name
    # Results compare by identity (arrays have no single truth value), hash, and print as a summary.
    again = pickle.loads(pickle.dumps(res))
    assert res == res and res != again and res in [res] and len({res, again}) == 2
    assert np.array_equal(again.transformation, res.transformation)
    import copy

    for kept in (res, pickle.loads(pickle.dumps(res)), copy.deepcopy(res)):  # frozen: its arrays too, however copied
        for name in ("transformation", "coarse_transformation", "network_transformation"):
            with pytest.raises(ValueError, match="read-only"):
                getattr(kept, name)[:3, 3] *= 1000.0
    text = repr(res)
    assert text.startswith("RegistrationResult(trusted; confidence") and "cloud units (lower is better)" in text
    assert len(text) < 600 and text.count("\n") == 5


def test_weights_given_as_a_path_are_held_as_text(tiny_model_path):
    import json

    config = RegisterConfig(weights=tiny_model_path, second_network=o3dsoft.SecondNetworkConfig(weights=tiny_model_path))
    assert config.weights == config.second_network.weights == str(tiny_model_path)
    assert json.loads(json.dumps(config.to_dict()))["weights"] == str(tiny_model_path)
    src, tgt, T = blob_pair(seed=1)
    res = register(src, tgt, replace(config, icp=ICPConfig(distance=0.5)))
    assert pair_errors(res.transformation, T).rotation_deg < 1e-3
    # The search's network is not asked for with the search off: its name is not checked either.
    off = SearchConfig(mode="off", starts=StartsConfig(weights="nope"))
    assert register(src, tgt, replace(config, icp=ICPConfig(distance=0.5), search=off)).transformation.shape == (4, 4)


@pytest.mark.parametrize("units", [1e-3, 1.0, 1e3])
def test_any_units_and_open3d_input(tiny_model_path, units):
    src, tgt, T = blob_pair(seed=1, units=units)
    from o3dsoft.refine import to_open3d

    res = o3dsoft.register(to_open3d(src), to_open3d(tgt), RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5)))
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1e-3 and e.translation < 1e-4 * units
    assert res.scale == pytest.approx(np.linalg.norm(src - src.mean(0), axis=1).max(), rel=1e-6)


def test_no_refine_reports_the_coarse_estimate(tiny_model_path):
    src, tgt, _ = blob_pair(seed=2)
    res = register(src, tgt, RegisterConfig(weights=str(tiny_model_path), refine=False))
    assert np.array_equal(res.transformation, res.coarse_transformation)


def test_cleaning_is_reported(tiny_model_path):
    src, tgt, T = blob_pair(seed=3)
    dirty = np.vstack([src, [[np.nan, 0, 0]], src[:5]])
    res = register(dirty, tgt, RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5)))
    assert res.removed["source_non_finite"] == 1 and res.removed["source_duplicates"] == 5
    assert res.num_source == len(src)
    assert pair_errors(res.transformation, T).rotation_deg < 1e-3


def test_deterministic(tiny_model_path):
    src, tgt, _ = blob_pair(seed=4)
    cfg = RegisterConfig(weights=str(tiny_model_path))
    assert np.array_equal(register(src, tgt, cfg).transformation, register(src, tgt, cfg).transformation)
    # the search too: its RANSAC draws from a seeded generator
    src, tgt = o3dsoft.read_points(EXAMPLES / "bun045.ply"), o3dsoft.read_points(EXAMPLES / "bun000.ply")
    cfg = RegisterConfig(
        weights=str(tiny_model_path), voxel=0.004, icp=ICPConfig(method="point"), search=SearchConfig(mode="always", starts=StartsConfig(weights=None))
    )
    first, again = register(src, tgt, cfg), register(src, tgt, cfg)
    assert first.attempts > 1 and np.array_equal(first.transformation, again.transformation)
    # Point-to-plane (the default on a voxel grid): Open3D's threaded sums repeat to about 1e-15.
    cfg = replace(cfg, icp=ICPConfig(method="auto"))
    first, again = register(src, tgt, cfg), register(src, tgt, cfg)
    assert first.icp_method == "plane" and first.attempts == again.attempts and np.allclose(first.transformation, again.transformation, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "cloud,match",
    [
        (
            np.zeros((100, 3)),
            r"source: 1 distinct finite points \(0 rows with NaN/inf, 99 duplicates removed\); at least 8 are needed$",
        ),  # no float32 note near the origin
        (np.random.default_rng(0).normal(size=(5, 3)), "source: 5 distinct finite points; at least 8"),
        (np.outer(np.arange(100.0), [1, 1, 0]), "source: all points lie on one line"),
        (np.zeros((10, 2)), r"source: expected points of shape \(N, 3\)"),
        ("scan.ply", r"source: got the file name 'scan.ply', not points: read it first, o3dsoft.read_points\(path\)"),
        # far from the origin float32 merges a cloud's points: the message says why
        (
            (1e7 + 0.1 * np.random.default_rng(0).normal(size=(100, 3))).astype(np.float32),
            "if these coordinates went through float32, its step at 1e[+]07 is 1, .*keep them in float64",
        ),
    ],
)
def test_bad_clouds(tiny_model_path, cloud, match):
    with pytest.raises(InputError, match=match):
        register(cloud, blob(np.random.default_rng(1), 100), RegisterConfig(weights=str(tiny_model_path)))


def test_num_points_below_k_rejected(tiny_model_path):
    src, tgt, _ = blob_pair()
    with pytest.raises(UsageError, match="num_points=4 is below the network's neighbourhood size K=8"):
        register(src, tgt, RegisterConfig(weights=str(tiny_model_path), num_points=4))


def test_hundred_point_clouds(tiny_model_path):
    src, tgt, T = blob_pair(seed=5, n=100)
    res = register(src, tgt, RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5)))
    assert pair_errors(res.transformation, T).rotation_deg < 1e-3


def test_clouds_of_very_different_sizes_say_how_many_points_each_stage_used(tiny_model_path):
    rng = np.random.default_rng(3)
    d = rng.normal(size=(20_000, 3))
    dense = d / np.linalg.norm(d, axis=1, keepdims=True) * [1.0, 0.6, 0.3]  # an ellipsoid's surface
    T = random_transform(rng, max_angle=5.0, max_t=0.05)
    sparse = apply(T, dense[rng.choice(len(dense), size=100, replace=False)])
    res = register(dense, sparse, RegisterConfig(weights=str(tiny_model_path), search=SearchConfig(mode="off")))
    assert res.points_used["network"] == (1024, 100)  # each cloud at the network's sample size, or all of it
    assert res.points_used["attempts"][1] == 100 and res.points_used["attempts"][0] <= RegisterConfig().attempt_points
    # The dense cloud comes down to a grid of 1 % of the scene's size; the sparse one keeps its points.
    assert 0.01 < res.voxel < 0.05 and res.points_used["final"] == (res.num_source, 100) and 1_000 < res.num_source < 20_000
    assert pair_errors(res.transformation, T).rotation_deg < 5  # a sparse sample of the same surface


def test_a_hundred_points_against_a_scan_with_the_search_on(tiny_model_path):
    # The search runs KISS-Matcher on scans where it is installed; given a cloud of a hundred
    # points it crashed the process. In a subprocess, so that a crash fails this test only.
    import subprocess
    import sys

    code = (
        "import numpy as np, trimesh\n"
        "from o3dsoft.config import SearchConfig\n"
        "from o3dsoft.pipeline import RegisterConfig, register\n"
        "shape = trimesh.util.concatenate([trimesh.creation.capsule(height=1.0, radius=0.3), trimesh.creation.box((1.2, 0.2, 0.2))])\n"
        "dense = trimesh.sample.sample_surface(shape, 20_000, seed=1)[0]\n"
        "sparse = trimesh.sample.sample_surface(shape, 100, seed=2)[0] + [0.1, 0.2, -0.1]\n"
        f"res = register(dense, sparse, RegisterConfig(weights={str(tiny_model_path)!r}, search=SearchConfig(mode='always')))\n"
        "print(res.searched, res.points_used['final'][1])\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=600)
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    assert run.stdout.decode().split() == ["True", "100"]


@pytest.mark.parametrize("points", [120, 260])
def test_clouds_of_under_min_points_are_flagged_however_well_they_fit(points):
    # With a few dozen points the tight distance (1.5 spacings) is so wide that wrong poses of
    # real scans scored 0.996; below ConfidenceConfig.min_points the confidence is capped.
    rng = np.random.default_rng(3)
    src = blob(rng, points)
    T = random_transform(rng, 30.0, 0.2)
    res = register(src, apply(T, src))
    assert rotation_error_deg(res.transformation[:3, :3], T[:3, :3]) < 1.0
    floor = ConfidenceConfig().min_points
    if points < floor:
        assert res.likely_failed and res.confidence <= 0.5 * points / floor
        assert res.failure_reason.startswith(f"the smaller cloud has only {points} points")
    else:
        assert not res.likely_failed and res.failure_reason is None


def test_a_few_points_flagged_for_another_reason_too_say_both(tiny_model_path):
    # Two samplings of 60 points of a flat patch: the degeneracy test flags them (confidence 0),
    # and the point count is still said first.
    rng = np.random.default_rng(4)
    src, tgt = (np.column_stack([rng.uniform(-1, 1, (60, 2)), np.zeros(60)]) for _ in range(2))
    res = register(src, apply(random_transform(rng, 10.0, 0.1), tgt), RegisterConfig(weights=str(tiny_model_path)))
    assert res.likely_failed and res.failure_reason.startswith("the smaller cloud has only 60 points")
    assert "; also, the clouds " in res.failure_reason and "determine" in res.failure_reason  # the degeneracy test's reason


def test_open3d_warnings_are_off_within_o3dsoft_only(capfd):
    import open3d as o3d

    before = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Info)
    try:
        points = o3dsoft.read_points(EXAMPLES / "bun045.ply")  # Open3D warns that a PLY without faces holds no mesh
        register(points, o3dsoft.read_points(EXAMPLES / "bun000.ply"))
        assert "[Open3D WARNING]" not in capfd.readouterr().out
        assert o3d.utility.get_verbosity_level() == o3d.utility.VerbosityLevel.Info  # the caller's, as set
        o3d.io.read_point_cloud(str(EXAMPLES / "no_such_file.ply"))
        assert "[Open3D WARNING] Read PLY failed" in capfd.readouterr().out  # the caller's own calls still warn
    finally:
        o3d.utility.set_verbosity_level(before)


def _outline(rng, n, corridor=False):
    """A 2D laser scan (z = 0) of an 8 x 5 m room's walls with a round pillar, or of a 20 m
    corridor's two walls, with 5 mm noise in the plane."""
    t, side = rng.uniform(0, 1, n), rng.integers(0, 2 if corridor else 5, n)
    walls = (
        [np.c_[20 * t, 0 * t], np.c_[20 * t, 2 + 0 * t]]
        if corridor
        else [
            np.c_[8 * t, 0 * t],
            np.c_[8 + 0 * t, 3 * t],
            np.c_[8 - 4 * t, 3 + 0 * t],
            np.c_[4 + 0 * t, 3 + 2 * t],
            np.c_[2 + 0.3 * np.cos(2 * np.pi * t), 1.5 + 0.3 * np.sin(2 * np.pi * t)],
        ]
    )
    xy = np.choose(side[:, None], walls) + rng.normal(0, 0.005, (n, 2))
    return np.c_[xy, np.zeros(n)]


def test_2d_scans_register_within_their_plane():
    # A flat target's normals all leave its plane: point-to-plane ICP held no motion within it, and
    # the degeneracy test read every 2D scan as sliding (constraint 0). Now ICP is point-to-point
    # there, and the test weighs the motions within the plane, with the outline's normals.
    rng = np.random.default_rng(0)
    T = rigid(euler_to_matrix(np.array([0.0, 0.0, 12.0])), np.array([0.4, -0.3, 0.0]))
    room = register(_outline(rng, 5000), apply(T, _outline(rng, 5000)))
    assert room.icp_method == "point" and not room.likely_failed and room.constraint > 0.05
    e = pair_errors(room.transformation, T)
    assert e.rotation_deg < 0.1 and e.translation < 0.01
    corridor = register(_outline(rng, 5000, corridor=True), apply(T, _outline(rng, 5000, corridor=True)))
    assert corridor.likely_failed and "can slide" in corridor.failure_reason and corridor.constraint < 1e-3
    assert "the surfaces hold no shift along (0.98, 0.21, 0.00)" in corridor.failure_reason  # along its walls, turned 12 degrees
    # With 2 cm of range noise the walls' normals tilt and seem to hold the shift along them; the fit itself does not.
    noisy = [_outline(rng, 1000, corridor=True) + np.c_[rng.normal(0, 0.02, (1000, 2)), np.zeros(1000)] for _ in range(2)]
    wrong = rigid(np.eye(3), np.array([1.0, 0.0, 0.0]))
    held = degeneracy_stage.assess(noisy[0], noisy[1], wrong, 0.2, 10.0)
    assert held.reason is not None and "slide on each other within their plane" in held.reason


def test_a_process_forked_after_a_registration_registers_too():
    # Linux's default multiprocessing start method forks; a child of a process whose torch
    # threads had run waited forever on its first parallel operation. In a subprocess, with a
    # time limit, so that a hang fails this test only.
    code = (
        "import multiprocessing, numpy as np, torch, o3dsoft\n"
        "from o3dsoft.transforms import euler_to_matrix\n"
        "torch.set_num_threads(2)\n"
        "rng = np.random.default_rng(0)\n"
        "src = rng.normal(size=(400, 3)) * [1.0, 0.6, 0.3]\n"
        "tgt = src @ euler_to_matrix(np.array([10.0, -5.0, 20.0])).T + [0.1, 0.0, -0.2]\n"
        "def run(i):\n"
        "    return o3dsoft.register(src, tgt).transformation\n"
        "first = run(0)\n"
        "with multiprocessing.get_context('fork').Pool(2) as pool:\n"
        "    again = pool.map_async(run, range(2)).get(timeout=120)\n"
        "print(max(float(np.abs(T - first).max()) for T in again))\n"
    )
    assert float(python_output(code, timeout=300)) < 1e-6  # the same pose, computed on one thread


def test_a_process_forked_after_point_to_plane_icp_runs_it_too():
    # Point-to-plane ICP pairs points in pykdtree's OpenMP threads; a forked child inherits
    # libgomp's thread pool without its threads, and its first query waited forever.
    code = (
        "import os\n"
        "os.environ['OMP_NUM_THREADS'] = '2'  # a pool of threads to inherit: with one, none is started\n"
        "import multiprocessing, numpy as np\n"
        "from o3dsoft.refine import ICPConfig, icp\n"
        "rng = np.random.default_rng(0)\n"
        "xy = rng.uniform(-1, 1, (20000, 2))\n"
        "surface = np.c_[xy, 0.1 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])]\n"
        "start = np.eye(4)\n"
        "start[:3, 3] = [0.02, -0.01, 0.01]\n"
        "def run(i):\n"
        "    return icp(surface, surface, start, 0.1, ICPConfig(method='plane')).transformation\n"
        "first = run(0)\n"
        "with multiprocessing.get_context('fork').Pool(2) as pool:\n"
        "    again = pool.map_async(run, range(2)).get(timeout=60)\n"
        "print(max(float(np.abs(T - first).max()) for T in again))\n"
    )
    assert float(python_output(code, timeout=300)) == 0.0  # the same pose, to the bit


def test_large_clouds_are_downsampled_for_icp_and_still_exact(tiny_model_path):
    rng = np.random.default_rng(7)
    d = rng.normal(size=(300_000, 3))
    src = d / np.linalg.norm(d, axis=1, keepdims=True) * [1.0, 0.6, 0.3] * 500.0  # an ellipsoid, in mm
    T = random_transform(rng, max_angle=5.0, max_t=0.1)
    T[:3, 3] *= 500.0
    cfg = RegisterConfig(weights=str(tiny_model_path), voxel=0, icp=ICPConfig(distance=0.3, max_points=30_000))
    res = register(src, apply(T, src), cfg)
    e = pair_errors(res.transformation, T)
    # Every point kept (voxel 0): ICP voxel-downsamples both to <= 30,000 points (voxels of ~7 mm
    # on this 1 m surface) and must still land far below the voxel size.
    assert e.rotation_deg < 0.5 and e.translation < 1.0
    assert res.num_source == 300_000 and res.voxel is None
    # By default the pair is registered on a grid of 1 % of the scene's size (12 mm here), to
    # within a fraction of it.
    res = register(src, apply(T, src), replace(cfg, voxel=None))
    e = pair_errors(res.transformation, T)
    assert res.voxel == pytest.approx(12.0, rel=0.1) and e.rotation_deg < 0.5 and e.translation < 0.5 * res.voxel
    assert res.num_source < 100_000


def test_unrelated_clouds_are_flagged(tiny_model_path):
    rng = np.random.default_rng(5)
    src = blob(rng, 500)
    tgt = rng.uniform(-1, 1, size=(500, 3)) * np.array([1.0, 1.0, 0.05])  # a flat slab: nothing like the blob
    res = register(src, tgt, RegisterConfig(weights=str(tiny_model_path)))
    assert res.likely_failed and res.confidence < 0.5
    assert "can slide on each other" in res.failure_reason  # the library says why: a slab fixes no pose
    from .test_degeneracy import box_surface

    res = register(src, box_surface(rng, 500), RegisterConfig(weights=str(tiny_model_path)))  # a box does
    assert res.likely_failed and "the global search found nothing clearly better" in res.failure_reason


def test_a_large_rotation_is_found_by_the_search():
    rng = np.random.default_rng(4)
    src = blob(rng, 800)
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix([160.0, -20.0, 100.0])  # 152 degrees; 31 from the nearest start
    T[:3, 3] = [0.3, -0.2, 0.1]
    tgt = apply(T, src)
    model = NearSightedModel(T[:3, :3])
    res = register(src, tgt, RegisterConfig(second_network=NO_SECOND, num_points=800, search=SearchConfig(mode="off")), model=model)
    assert res.likely_failed and res.attempts == 1 and not res.searched and model.batches == [1] and res.search_reason is None
    model = NearSightedModel(T[:3, :3])
    res = register(
        src,
        tgt,
        RegisterConfig(
            second_network=NO_SECOND, num_points=800, search=SearchConfig(starts=StartsConfig(points=400), features=FeatureSearchConfig(enabled=False))
        ),
        model=model,
    )
    assert res.searched and not res.likely_failed and res.attempts == 2 and model.batches == [1, 24]
    assert res.search_reason == "no estimate was trusted"
    assert res.estimate_from == "network starts" and res.to_dict()["estimate_from"] == "network starts"
    assert pair_errors(res.transformation, T).rotation_deg < 1e-3


def test_the_search_can_add_a_feature_based_estimate():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    model = AlwaysWrongModel(T[:3, :3] @ euler_to_matrix([180.0, 0.0, 0.0]))  # upside down
    without = register(
        src,
        tgt,
        RegisterConfig(
            second_network=NO_SECOND, search=SearchConfig(mode="always", features=FeatureSearchConfig(enabled=False), starts=StartsConfig(weights=None))
        ),
        model=model,
    )
    assert without.likely_failed and pair_errors(without.transformation, T).rotation_deg > 90
    res = register(src, tgt, RegisterConfig(second_network=NO_SECOND, search=SearchConfig(mode="always")), model=model)  # features on by default
    # The network's wrong estimate of these scans is screened and not kept; the feature match
    # (KISS-Matcher's, where installed) comes next and is confident: the network's starts are not needed.
    assert res.screened >= 2 and res.attempts == 1 and not res.likely_failed and res.estimate_from != "network starts"
    assert pair_errors(res.transformation, T).rotation_deg < 1.0


def test_georeferenced_scans_register_as_they_do_at_the_origin():
    # Scans in UTM coordinates lie millions of units from the origin: point-to-plane ICP, which
    # linearises the rotation about the origin, lost them (9.6 deg off, flagged) and KISS-Matcher
    # crashed the process. Registered about the target's median, they give the origin's answer.
    from o3dsoft.preprocess import local_origin

    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    at_origin = register(src, tgt)
    assert not local_origin(tgt).any() and pair_errors(at_origin.transformation, T).rotation_deg < 1.0 and not at_origin.likely_failed
    utm = np.array([512_345.0, 4_123_456.0, 231.0])
    shift = np.eye(4)
    shift[:3, 3] = utm
    for source_offset in (utm, np.zeros(3)):  # both far, or only the target
        res = register(src + source_offset, tgt + utm)
        assert np.allclose(local_origin(tgt + utm), np.median(tgt, axis=0) + utm)
        unshift = np.eye(4)
        unshift[:3, 3] = -source_offset
        back = np.linalg.inv(shift) @ res.transformation @ np.linalg.inv(unshift)  # in the origin's frames
        e = pair_errors(back, at_origin.transformation)
        assert e.rotation_deg < 1e-3 and e.translation < 1e-6, e
        assert res.confidence == pytest.approx(at_origin.confidence, abs=0.01) and res.estimate_from == at_origin.estimate_from
        for given, found in ((at_origin.coarse_transformation, res.coarse_transformation), (at_origin.network_transformation, res.network_transformation)):
            assert pair_errors(np.linalg.inv(shift) @ found @ np.linalg.inv(unshift), given).rotation_deg < 1e-3


def test_a_stray_point_at_1e12_is_dropped_and_the_pair_registers_as_without_it():
    # It made the bunny "lie on one line" (refused), and past that check overflowed Open3D's
    # voxel grid (a traceback from the command line).
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    clean = register(src, tgt)
    res = register(np.vstack([src, [[1e12, -1e12, 5e11]]]), tgt)
    assert res.removed["source_strays"] == 1 and res.removed["target_strays"] == 0 and clean.removed["source_strays"] == 0
    assert np.allclose(res.transformation, clean.transformation, atol=1e-9) and res.confidence == pytest.approx(clean.confidence)
    swapped = register(tgt, np.vstack([src, [[1e12, -1e12, 5e11]]]))  # counts follow the clouds' roles
    assert swapped.removed["target_strays"] == 1 and swapped.removed["source_strays"] == 0


def test_the_quick_search_is_the_feature_match_that_goes_first_alone():
    # multiway's first pass: the feature match on a partial overlap, and nothing after a flagged result.
    from benchmarks.indoor_rooms import views

    clouds, poses = views(12, pixels=64)  # two depth views of a room, 30 degrees apart
    T = np.linalg.inv(poses[3]) @ poses[4]
    model = AlwaysWrongModel(T[:3, :3] @ euler_to_matrix([180.0, 0.0, 0.0]))
    quick = RegisterConfig(second_network=NO_SECOND, search=SearchConfig(mode="quick"))
    res = register(clouds[4], clouds[3], quick, model=model)
    assert res.searched and not res.likely_failed and model.batches == []  # the feature match was trusted: no network
    assert pair_errors(res.transformation, T).rotation_deg < 1.0
    src, tgt, T = moved_bunny(0)  # one cloud moved: complete, no feature match first
    model = AlwaysWrongModel(T[:3, :3] @ euler_to_matrix([180.0, 0.0, 0.0]))
    res = register(src, tgt, quick, model=model)
    assert res.likely_failed and not res.searched and model.batches == [1]  # the network once, no search after it


def test_the_networks_estimate_of_scans_is_screened_first_and_kept_when_nothing_else_is():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    model = AlwaysWrongModel(T[:3, :3] @ euler_to_matrix([180.0, 0.0, 0.0]))
    res = register(src, tgt, RegisterConfig(second_network=NO_SECOND, search=SearchConfig(mode="off")), model=model)
    # Untrusted on the screen clouds, so not refined on the work clouds then; with no other
    # estimate it is the answer after all, refined and scored there, and flagged.
    assert res.screened == 1 and res.attempts == 1 and res.estimate_from == "network" and res.likely_failed
    assert pair_errors(res.transformation, T).rotation_deg > 90


def test_search_settings_are_checked():
    model = NearSightedModel(np.eye(3))
    src = blob(np.random.default_rng(0), 200)
    with pytest.raises(InputError, match="search.mode='sometimes'; valid: auto, always, off"):
        register(src, src, RegisterConfig(search=SearchConfig(mode="sometimes")), model=model)
    with pytest.raises(UsageError, match="search.starts.points=4 is below the network's neighbourhood size K=8"):
        register(src, src, RegisterConfig(search=SearchConfig(starts=StartsConfig(points=4))), model=model)
    with pytest.raises(UsageError, match="attempt_points=4 is below the network's neighbourhood size K=8"):
        register(src, src, RegisterConfig(attempt_points=4), model=model)
    with pytest.raises(InputError, match="search.features.candidates must be at least 1, got 0"):
        register(src, src, RegisterConfig(search=SearchConfig(features=FeatureSearchConfig(candidates=0))), model=model)
    for bad in (0.0, 200.0):
        with pytest.raises(InputError, match=r"max_rotation must be in \(0, 180\] degrees"):
            register(src, src, RegisterConfig(max_rotation=bad), model=model)
    with pytest.raises(InputError, match="search.features.first_round must be at least 1, got 0"):
        register(src, src, RegisterConfig(search=SearchConfig(features=FeatureSearchConfig(first_round=0))), model=model)
    with pytest.raises(InputError, match="search.restart.refined must not be negative, got -1"):
        register(src, src, RegisterConfig(search=SearchConfig(restart=RestartConfig(refined=-1))), model=model)
    with pytest.raises(InputError, match="confidence: coefficients: expected 3"):
        register(src, src, RegisterConfig(confidence=ConfidenceConfig(coefficients=(1.0, 2.0))), model=model)
    for name in ("kiss_voxel", "kiss_normal_radius", "kiss_feature_radius"):
        with pytest.raises(InputError, match=f"search.{name} must be positive, got 0"):
            register(src, src, RegisterConfig(search=SearchConfig(**{name: 0.0})), model=model)


@pytest.mark.parametrize(
    "config, named",
    [
        (RegisterConfig(confidence=ConfidenceConfig(claimed=math.inf)), r"confidence.claimed must be a finite number, at least 0, got inf"),
        (RegisterConfig(search=SearchConfig(partial_pvalue=-1.0)), r"search.partial_pvalue must be a finite number, at least 0, got -1.0"),
        (RegisterConfig(icp=ICPConfig(tight_from=math.nan)), r"icp.tight_from must be a finite number, at least 0, got nan"),
        (RegisterConfig(max_rotation=-5.0), r"max_rotation must be a finite number, at least 0"),
        (RegisterConfig(confidence=ConfidenceConfig(coefficients=(math.nan, 1.0, 0.0))), r"confidence.coefficients must hold finite numbers"),
        (RegisterConfig(sparser_moves="x"), r"sparser_moves must be a number, got 'x'"),  # read before the network loads
        (
            RegisterConfig(search=SearchConfig(features=FeatureSearchConfig(match=FeatureMatchConfig(features=GlobalConfig(voxel=0.0))))),
            r"search.features.match.features.voxel must be positive, got 0.0",
        ),
    ],
)
def test_a_number_no_setting_takes_is_refused_by_name(config, named):
    """NaN, infinite and negative settings had run, some changing the result (a confidence's
    claimed share of inf trusted a flagged result)."""
    src = blob(np.random.default_rng(0), 200)
    with pytest.raises(InputError, match=named):
        register(src, src, config, model=NearSightedModel(np.eye(3)))


def test_without_icp_the_search_keeps_its_top_ranked_estimate_as_it_is():
    rng = np.random.default_rng(4)
    src = blob(rng, 800)
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix([160.0, -20.0, 100.0])
    tgt = apply(T, src)
    res = register(
        src,
        tgt,
        RegisterConfig(num_points=800, refine=False, search=SearchConfig(mode="always", features=FeatureSearchConfig(enabled=False))),
        model=NearSightedModel(T[:3, :3]),
    )
    # The stand-in is exact from the start within 50 degrees; no ICP ran on the result.
    assert res.searched and np.array_equal(res.transformation, res.coarse_transformation)
    assert pair_errors(res.transformation, T).rotation_deg < 1e-3


def test_voxel_grid_evens_out_the_clouds_before_registering():
    rng = np.random.default_rng(5)
    src = blob(rng, 3000)
    T = random_transform(rng, 30.0, 0.2)
    tgt = apply(T, src)
    res = register(src, tgt, RegisterConfig(voxel=0.2), model=NearSightedModel(T[:3, :3]))
    assert res.num_source < 3000 and res.num_target < 3000
    assert pair_errors(res.transformation, T).rotation_deg < 1.0
    with pytest.raises(InputError, match=r"source: \d+ points? left on a voxel grid of 50 units, fewer than the 8 needed"):
        register(src, tgt, RegisterConfig(voxel=50.0), model=NearSightedModel(T[:3, :3]))


def test_a_rotation_prior_rejects_a_confident_answer_beyond_it(monkeypatch):
    from o3dsoft import search

    rng = np.random.default_rng(3)
    half = rng.uniform(-1.0, 1.0, size=(750, 3)) * [1.0, 0.6, 0.3]
    box = np.concatenate([half, half * [1.0, -1.0, -1.0]])  # the half turn about x maps it onto itself
    T = random_transform(rng, 20.0, 0.2)
    flipped = T @ np.diag([1.0, -1.0, -1.0, 1.0])  # fits just as well, 160-200 degrees from the given pose
    monkeypatch.setattr(search.FeatureMatch, "candidates", lambda self, seed, count: np.stack([flipped, T]))
    model = AlwaysWrongModel(flipped[:3, :3])
    tgt = apply(T, box)
    assert 10.0 < rotation_error_deg(T[:3, :3], np.eye(3)) < 60.0
    res = register(box, tgt, RegisterConfig(second_network=NO_SECOND, search=SearchConfig(starts=StartsConfig(weights=None))), model=model)
    assert not res.searched and not res.likely_failed and pair_errors(res.transformation, T).rotation_deg > 150.0
    res = register(box, tgt, RegisterConfig(second_network=NO_SECOND, max_rotation=60.0, search=SearchConfig(starts=StartsConfig(weights=None))), model=model)
    assert res.searched and not res.likely_failed and pair_errors(res.transformation, T).rotation_deg < 1e-3
    assert res.attempts == 2  # the flipped feature estimate is screened out before ICP
    res = register(box, tgt, RegisterConfig(second_network=NO_SECOND, max_rotation=10.0, search=SearchConfig(starts=StartsConfig(weights=None))), model=model)
    assert res.likely_failed  # nothing found within the bound ...
    assert rotation_angle_deg(res.transformation[:3, :3]) <= 10.0  # ... so the result stays within it


def test_estimates_are_refined_on_reduced_clouds_and_the_kept_one_at_full_resolution(monkeypatch):
    rng = np.random.default_rng(8)
    src = blob(rng, 6000)
    T = random_transform(rng, 30.0, 0.2)
    tgt = apply(T, src)
    sizes = record_icp(monkeypatch)
    res = register(src, tgt, RegisterConfig(attempt_points=1000, search=SearchConfig(mode="off")), model=NearSightedModel(T[:3, :3]))
    assert sizes[0][0] <= 1000 and sizes[0][1] == (1.0, 0.3, 0.1)
    assert sizes[-1] == (6000, (0.1,))  # converged on the work clouds: only the last stage at full resolution
    assert res.num_source == 6000 and pair_errors(res.transformation, T).rotation_deg < 1e-3
    sizes.clear()
    register(src[:900], tgt[:900], RegisterConfig(attempt_points=1000, search=SearchConfig(mode="off")), model=NearSightedModel(T[:3, :3]))
    assert sizes == [(900, (1.0, 0.3, 0.1))]  # small clouds: refined once, as they are
    sizes.clear()
    on_a_grid = RegisterConfig(voxel=1e-6, attempt_points=1000, search=SearchConfig(mode="off"))  # a scan: point-to-plane
    res = register(src[:900], tgt[:900], on_a_grid, model=NearSightedModel(T[:3, :3]))
    assert res.icp_method == "plane" and sizes == [(900, (1.0, 0.3, 0.1))]  # its last stage ran on these clouds already


def test_a_flagged_result_is_left_unrefined_when_asked(monkeypatch):
    rng = np.random.default_rng(8)
    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = random_transform(rng, 30.0, 0.02)
    tgt = apply(T, src)
    wrong = AlwaysWrongModel(euler_to_matrix(np.array([0.0, 0.0, 120.0])) @ T[:3, :3])  # far beyond ICP's reach
    sizes = record_icp(monkeypatch)
    config = RegisterConfig(second_network=NO_SECOND, attempt_points=1000, search=SearchConfig(mode="off"))
    refined = register(src, tgt, config, model=wrong)
    assert refined.likely_failed and sizes[-1][0] == len(src) and refined.num_source == len(src)
    sizes.clear()
    left = register(src, tgt, replace(config, refine_flagged=False), model=wrong)
    assert left.likely_failed and all(n <= 1000 for n, _ in sizes), sizes  # no ICP on the full clouds
    assert left.points_used["final"] == left.points_used["attempts"] and left.num_source <= 1000


def test_without_icp_the_final_points_are_those_the_estimate_was_scored_on():
    """Without ICP nothing runs on the full clouds: the counts say so (not the full clouds')."""
    rng = np.random.default_rng(9)
    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = random_transform(rng, 20.0, 0.02)
    config = RegisterConfig(second_network=NO_SECOND, attempt_points=1000, refine=False, search=SearchConfig(mode="off"))
    res = register(src, apply(T, src), config, model=NearSightedModel(T[:3, :3]))
    assert res.points_used["attempts"][0] <= 1000 < len(src)
    assert res.points_used["final"] == res.points_used["attempts"] == (res.num_source, res.num_target)


def test_a_doubtful_result_is_searched_further_when_asked(modelnet_root):
    from o3dsoft.data import get_protocol, load_pairs

    # rpmnet-crop test pair 369 (stairs): the feature match's second estimate, half a turn off,
    # is trusted at 0.50 and ends the search; going on to 0.9 finds the right pose a few later.
    pair = load_pairs(modelnet_root, "test", get_protocol("rpmnet-crop"), 0)[369]
    src, tgt, T = pair.source.astype(np.float64), pair.target.astype(np.float64), pair.transform
    model, search_model = load_model(), load_model("partial")
    first = register(src, tgt, RegisterConfig(), model=model, search_model=search_model)
    assert 0.5 <= first.confidence < 0.9 and pair_errors(first.transformation, T).rotation_deg > 170
    assert first.search_reason == "the clouds look like a partial overlap: the feature match goes first"
    further = register(src, tgt, RegisterConfig(search=SearchConfig(features=FeatureSearchConfig(stop=0.9))), model=model, search_model=search_model)
    assert further.confidence >= 0.9 and further.attempts > first.attempts
    assert pair_errors(further.transformation, T).rotation_deg < 1.0
    with pytest.raises(InputError, match="search.features.stop must be in"):
        register(src, tgt, RegisterConfig(search=SearchConfig(features=FeatureSearchConfig(stop=0.3))), model=model)
    # With the tight restart as well, a result still below the stop gets the restart too
    # (rpmnet-crop pair 1292, a person: the feature match ends at 0.89).
    pair = load_pairs(modelnet_root, "test", get_protocol("rpmnet-crop"), 0)[1292]
    src, tgt = pair.source.astype(np.float64), pair.target.astype(np.float64)
    runs = {
        (restart, stop): register(
            src,
            tgt,
            RegisterConfig(search=SearchConfig(restart=RestartConfig(enabled=restart), features=FeatureSearchConfig(stop=stop))),
            model=model,
            search_model=search_model,
        )
        for restart, stop in ((True, 0.5), (False, 0.9), (True, 0.9))
    }
    assert runs[True, 0.5].screened == 0 and runs[True, 0.5].confidence >= 0.5  # confident: no restart at the default stop
    assert runs[False, 0.9].screened == 0 and 0.5 <= runs[False, 0.9].confidence < 0.9
    assert runs[True, 0.9].screened > 0 and runs[True, 0.9].attempts >= runs[False, 0.9].attempts
    assert runs[True, 0.9].confidence >= runs[False, 0.9].confidence  # the most trusted of more estimates


def test_array_likes_users_pass_are_taken_or_refused_with_one_clear_error():
    import torch

    from o3dsoft.pair import as_points

    grad = torch.rand(50, 3, requires_grad=True)
    assert np.array_equal(as_points(grad, "source"), grad.detach().numpy().astype(np.float64))
    with pytest.raises(InputError, match="source: expected points of shape \\(N, 3\\), got rows of different lengths"):
        as_points([[1.0, 2.0, 3.0], [1.0, 2.0]], "source")
    with pytest.raises(InputError, match="target: expected real numeric points, got dtype complex128"):
        as_points(np.ones((50, 3), dtype=complex), "target")  # the imaginary part is not silently dropped
    # ROS's point_cloud2.read_points: one record per point
    records = np.zeros(50, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])
    for k, c in enumerate("xyz"):
        records[c] = grad.detach().numpy()[:, k]
    assert np.array_equal(as_points(records, "source"), grad.detach().numpy().astype(np.float64))
    with pytest.raises(InputError, match="source: a structured array needs fields x, y and z, got x, y, intensity"):
        as_points(np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("intensity", "<f4")]), "source")
    import open3d as o3d

    pts = np.random.default_rng(0).random((50, 3))
    assert np.array_equal(as_points(o3d.t.geometry.PointCloud(o3d.core.Tensor(pts)), "source"), pts)  # Open3D's tensor API
    assert np.array_equal(as_points(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)), "source"), pts)
    assert np.array_equal(as_points(o3d.core.Tensor(pts), "source"), pts)  # a tensor PointCloud's positions
    assert np.allclose(as_points(torch.tensor(pts, dtype=torch.bfloat16), "source"), pts, atol=0.01)  # NumPy has no bfloat16
    from o3dsoft.io import as_rigid

    T = rigid(euler_to_matrix([10.0, 0.0, 0.0]), [1.0, 2.0, 3.0])
    assert np.allclose(as_rigid(o3d.core.Tensor(T), "init"), T) and np.allclose(as_rigid(torch.tensor(T), "init"), T)  # Open3D's tensor ICP takes one
    with pytest.raises(InputError, match="source: expected an Open3D PointCloud, a tensor or \\(N, 3\\) points, got a .*TriangleMesh"):
        as_points(o3d.geometry.TriangleMesh.create_sphere(), "source")


@pytest.mark.parametrize(
    "call, error, message",
    [
        (lambda s, t: register(s, t, {"voxel": 0.01}), UsageError, "config must be an o3dsoft.RegisterConfig, got dict"),
        (lambda s, t: register(s, t, model="default"), UsageError, "model is a loaded network .* got the name 'default'"),
        (lambda s, t: register(s, t, init="T.txt"), InputError, "init: expected a 4x4 transform, got the file name 'T.txt'"),
        (lambda s, t: register(s, t, RegisterConfig(voxel="0.5")), InputError, "voxel must be a number, got '0.5' \\(str\\)"),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(distance=0.0))), InputError, "icp.distance must be positive and finite, got 0.0"),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(absolute=True))), InputError, "icp.absolute needs icp.distance, in the clouds' units"),
        (
            lambda s, t: register(s, t, RegisterConfig(confidence=ConfidenceConfig(likely_failed_below=1.5))),
            InputError,
            "likely_failed_below must be in \\[0, 1\\], got 1.5",
        ),
        (
            lambda s, t: register(s, t, RegisterConfig(confidence=ConfidenceConfig(likely_failed_below=0.9))),
            InputError,
            "search.features.stop must be in \\[confidence.likely_failed_below, 1\\] = \\[0.9, 1\\]",
        ),
        (
            lambda s, t: register(s, t, RegisterConfig(confidence=ConfidenceConfig(size_note_ratio=0.5))),
            InputError,
            "confidence: size_note_ratio must be at least 1, got 0.5",
        ),
        (lambda s, t: o3dsoft.multiway([s, t], RegisterConfig()), UsageError, "config must be an o3dsoft.MultiwayConfig"),
        (lambda s, t: o3dsoft.multiway([s, t], names=["a", "a"]), InputError, "two scans share the name 'a'"),
        (lambda s, t: register(s, t, RegisterConfig(seed=-1)), InputError, "seed must not be negative, got -1"),
        (lambda s, t: register(s, t, RegisterConfig(num_points=100.5)), InputError, "num_points must be a whole number, got 100.5 \\(float\\)"),
        (lambda s, t: register(s, t, RegisterConfig(seed=None)), InputError, "seed must not be None"),
        (lambda s, t: register(s, t, RegisterConfig(refine="no")), InputError, "refine must be True or False, got 'no' \\(str\\)"),
        (
            lambda s, t: register(s, t, RegisterConfig(icp={"method": "point"})),
            InputError,
            "icp must be an o3dsoft.ICPConfig, got \\{'method': 'point'\\} \\(dict\\)",
        ),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(schedule=()))), InputError, "icp.schedule must hold at least one positive"),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(max_iterations=0))), InputError, "icp.max_iterations must be at least 1, got 0"),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(max_points=0))), InputError, "icp.max_points must be at least 1, got 0"),
        (
            lambda s, t: register(s, t, RegisterConfig(search=o3dsoft.SearchConfig(screen=o3dsoft.ScreenConfig(points=0)))),
            InputError,
            "search.screen.points must be at least 1, got 0",
        ),
        (lambda s, t: register(s, t, RegisterConfig(icp=ICPConfig(noise_rounds=-1))), InputError, "icp.noise_rounds must not be negative, got -1"),
        (lambda s, t: register(s, t, model=123), UsageError, "model must be a network o3dsoft.coarse.load_model loaded, got int"),
        (lambda s, t: register(s, t, search_model=object()), UsageError, "search_model must be a network o3dsoft.coarse.load_model loaded, got object"),
        # A mistyped model fails on every pair, not only on those hard enough to reach its stage.
        (
            lambda s, t: register(s, t, RegisterConfig(second_network=o3dsoft.SecondNetworkConfig(weights="incongruentt"))),
            UsageError,
            "second_network.weights: incongruentt: weights file not found",
        ),
        (
            lambda s, t: register(s, t, RegisterConfig(search=SearchConfig(starts=StartsConfig(weights="partail")))),
            UsageError,
            "search.starts.weights: partail: weights file not found",
        ),
        (lambda s, t: o3dsoft.multiway([s, t], model="default"), UsageError, "name a model in MultiwayConfig\\(register=RegisterConfig\\(weights="),
        (lambda s, t: o3dsoft.odometry([s, t], model="default"), UsageError, "name a model in OdometryConfig\\(register=RegisterConfig\\(weights="),
    ],
    ids=[
        "config-dict",
        "model-name",
        "init-path",
        "voxel-str",
        "icp-distance-0",
        "icp-absolute-alone",
        "threshold-1.5",
        "threshold-0.9",
        "size-note-0.5",
        "multiway-config",
        "multiway-names",
        "seed-negative",
        "int-float",
        "seed-none",
        "bool-str",
        "stage-dict",
        "schedule-empty",
        "icp-iterations-0",
        "icp-points-0",
        "screen-points-0",
        "noise-rounds-negative",
        "model-int",
        "search-model-object",
        "second-weights-typo",
        "starts-weights-typo",
        "multiway-model-name",
        "odometry-model-name",
    ],
)
def test_library_misuse_is_one_clear_o3dsoft_error(call, error, message):
    src, tgt, _ = blob_pair(seed=4)
    with pytest.raises(error, match=message):
        call(src, tgt)


def test_a_result_the_full_clouds_reject_sends_the_pair_to_the_search(monkeypatch):
    from o3dsoft import pipeline

    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = random_transform(np.random.default_rng(2), 20.0, 0.01)
    config = RegisterConfig(attempt_points=1_000)  # the work clouds are reduced: the result is refined again on all points
    first = register(src, apply(T, src), config)
    assert not first.searched and not first.likely_failed and first.points_used["attempts"][0] < first.num_source
    real, calls = pipeline._refine_full, []

    def rejected_at_first(pair, verifier, best):  # the full clouds do not trust the first pick
        refined = real(pair, verifier, best)
        calls.append(refined)
        return refined._replace(trust=0.0) if len(calls) == 1 else refined

    monkeypatch.setattr(pipeline, "_refine_full", rejected_at_first)
    res = register(src, apply(T, src), config)
    assert len(calls) == 2 and res.searched and res.attempts > first.attempts
    assert res.search_reason == "the estimate trusted on the work clouds was not trusted at full resolution"
    assert not res.likely_failed and pair_errors(res.transformation, T).rotation_deg < 1.0


def test_a_screened_network_estimate_the_full_clouds_reject_no_longer_holds_the_screens_record(monkeypatch):
    from o3dsoft import pipeline, verify
    from o3dsoft.config import ScreenConfig

    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = random_transform(np.random.default_rng(2), 20.0, 0.01)
    # Work clouds of 2,000 points, screens of 512: the network's estimate of these scans is screened
    # first, trusted there and on the work clouds, then rejected at full resolution.
    config = RegisterConfig(attempt_points=2_000, search=SearchConfig(screen=ScreenConfig(points=512)))
    real, calls, records = pipeline._refine_full, [], []

    def rejected_at_first(pair, verifier, best):
        refined = real(pair, verifier, best)
        calls.append(refined)
        return refined._replace(trust=0.0) if len(calls) == 1 else refined

    real_distrust = verify.Verifier.distrust

    def distrust(self, attempt, trust):
        real_distrust(self, attempt, trust)
        records.append(max(s.trust for s in self.screened))

    monkeypatch.setattr(pipeline, "_refine_full", rejected_at_first)
    monkeypatch.setattr(verify.Verifier, "distrust", distrust)
    res = register(src, apply(T, src), config)
    assert len(calls) == 2 and res.searched and res.screened > 1
    assert records == [0.0]  # the search's estimates are promoted against a record of 0, not the rejected pose's
    assert not res.likely_failed and pair_errors(res.transformation, T).rotation_deg < 1.0


def test_the_screen_tries_at_most_its_budget_of_estimates():
    from o3dsoft.config import ScreenConfig

    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = random_transform(np.random.default_rng(4), 150.0, 0.05)
    search = SearchConfig(mode="always", screen=ScreenConfig(points=512, budget=3))
    res = register(src, apply(T, src), RegisterConfig(attempt_points=2_000, search=search))
    assert res.searched and 2 <= res.screened <= 3  # the network's (these are scans) and the search's
    assert res.search_reason == "the search mode is 'always'"


def test_scans_with_a_stray_far_point_or_in_other_units_are_right_or_flagged():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    stray = np.vstack([src, src.mean(axis=0) + [1000.0, 0.0, 0.0]])  # one point 1 km away from a 20 cm scan
    res = register(stray, tgt)
    assert not res.likely_failed and pair_errors(res.transformation, T).rotation_deg < 1.0
    assert res.scale < 1.0  # the scene's scale, not the stray point's
    res = register(1000.0 * src, tgt)  # millimetres against metres: no rigid transform fits
    assert res.likely_failed and res.failure_reason.startswith("the clouds' sizes differ 1021-fold (are they in the same units? ")
    res = register(3.2808 * src, tgt)  # feet against metres
    assert res.likely_failed and res.failure_reason.startswith("the clouds' sizes differ 3.4-fold (are they in the same units? ")
    quiet = register(3.2808 * src, tgt, RegisterConfig(confidence=ConfidenceConfig(size_note_ratio=5.0)))  # sizes named over 5-fold only
    assert quiet.likely_failed and "sizes differ" not in quiet.failure_reason and res.failure_reason.endswith(quiet.failure_reason)


def test_a_low_overlap_rgbd_pair_in_millimetres_as_in_metres(real_scans_root):
    from o3dsoft import baselines

    if not baselines.installed("kiss_matcher"):
        pytest.skip("the optional package kiss-matcher is not installed")
    folder = real_scans_root / "3dmatch_redkitchen"
    src, tgt = o3dsoft.read_points(folder / "cloud_bin_34.ply"), o3dsoft.read_points(folder / "cloud_bin_21.ply")
    truth = o3dsoft.read_transform(folder / "gt_34_to_21.txt")
    mm = np.diag([1000.0, 1000.0, 1000.0, 1.0])
    for scale in (np.eye(4), mm):  # KISS-Matcher's estimate carries this pair in both units
        res = register(scale[0, 0] * src, scale[0, 0] * tgt)
        errors = pair_errors(np.linalg.inv(scale) @ res.transformation @ scale, truth)
        assert not res.likely_failed and errors.rotation_deg < 5.0 and errors.translation < 0.1  # metres


def test_a_noisy_low_overlap_pair_that_fits_from_one_side_only_is_flagged(real_scans_root):
    from o3dsoft import bench

    folder = bench.scan_folder(real_scans_root / "3dmatch_redkitchen")
    pairs = {p.category: p for p in folder.pairs}
    config = RegisterConfig(search=SearchConfig(kiss=False))  # the feature match alone: the same estimates on every run
    for seed in (0, 3):  # noise of 0.5 % of the room (1.8 cm) on both fragments, which overlap by 10-21 %
        (noisy,) = bench.noisy_pairs([pairs["cloud_bin_34->cloud_bin_6"]], 0.005, seed=seed)
        res = register(noisy.source, noisy.target, config)
        assert pair_errors(res.transformation, noisy.transform).rotation_deg > 90.0  # wrong, and fitting the source's side closely:
        assert res.consistency > 0.91 and res.target_consistency < 0.88  # trusted by the strict confidence from there alone
        assert res.likely_failed and res.failure_reason.startswith("it fits from the source's side only: of the target's points near the source, 8")
    right = register(pairs["cloud_bin_6->cloud_bin_4"].source, pairs["cloud_bin_6->cloud_bin_4"].target, config)  # fits from both sides
    assert pair_errors(right.transformation, pairs["cloud_bin_6->cloud_bin_4"].transform).rotation_deg < 3.0
    assert not right.likely_failed and right.target_consistency > 0.9

    # A source on a grid of three times the spacing: the scorer counts its points from either side, so no other side is measured.
    from o3dsoft.clock import StageClock
    from o3dsoft.pair import PreparedPair
    from o3dsoft.pipeline import _target_side
    from o3dsoft.refine import ICPResult
    from o3dsoft.verify import Attempt

    pair = pairs["cloud_bin_6->cloud_bin_4"]
    _, first = np.unique(np.floor(pair.source / 0.1).astype(np.int64), axis=0, return_index=True)
    for source in (pair.source, pair.source[np.sort(first)]):
        prepared = PreparedPair(source, pair.target, config, 32, ("source", "target"), StageClock())
        trusted = Attempt(0.9, prepared.scorer("work")(pair.transform), ICPResult(pair.transform, 1.0, 0.0), pair.transform, pair.transform)
        side = _target_side(prepared, trusted, "work")
        assert (side is None) == (len(source) < len(pair.source))


def test_scattered_outliers_off_the_grid_are_left_out(bunny_root):
    """Scans thinned at random to 6,000 points are registered whole, on no grid: their isolated
    points are judged by each cloud's own spacing."""
    from o3dsoft import bench

    pair = {p.category: p for p in bench.scan_folder(bunny_root).pairs}["bun000->bun090"]
    rng = np.random.default_rng(0)
    src, tgt = (c[rng.choice(len(c), 6_000, replace=False)] for c in (pair.source, pair.target))
    noisy = tuple(np.vstack([c, rng.uniform(c.min(0), c.max(0), (240, 3))]) for c in (src, tgt))  # 4 % more, scattered
    res = register(*noisy)
    assert res.voxel is None and res.removed["source_isolated"] > 120 and res.removed["target_isolated"] > 120
    assert not res.likely_failed and pair_errors(res.transformation, pair.transform, pair.origin).rotation_deg < 1.0
    kept = register(*noisy, RegisterConfig(isolated_spacings=0.0))  # with them it ended a half turn off, flagged
    assert kept.removed["source_isolated"] == 0
    clean = register(src, tgt)  # a clean thinned scan keeps every point
    assert clean.removed["source_isolated"] == clean.removed["target_isolated"] == 0


def test_a_scan_whose_point_spacing_underflows_is_registered_not_an_internal_error():
    """Most points within a few subnormal steps of each other (a damaged file's): their spacing
    is 0, and no point is left out as isolated by it."""
    rng = np.random.default_rng(0)
    tiny = rng.integers(1, 10**6, (6000, 3)) * 5e-324
    spread = rng.uniform(-1.0, 1.0, (4000, 3))
    result = register(np.vstack([tiny, spread]), np.vstack([tiny, spread + 0.01]))
    assert result.voxel is None  # off a grid: isolated points by the (zero) spacing
    assert result.removed["source_isolated"] == result.removed["target_isolated"] == 0


def test_off_the_grid_only_a_few_isolated_points_are_outliers():
    """Off a grid, a cloud with more than ISOLATED_MAX_SHARE_OFF_GRID of its points isolated is
    sparse in places and kept whole; a scan that loses its outliers stays a scan."""
    from o3dsoft.pair import ISOLATED_MAX_SHARE_OFF_GRID, SCAN_POINTS, PreparedPair

    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.arange(64), np.arange(65))
    sheet = np.stack([u.ravel(), v.ravel(), 0.1 * np.sin(u.ravel() / 5.0)], axis=1).astype(float)  # 4,160 points, spacing 1
    assert len(sheet) > SCAN_POINTS

    scattered = rng.uniform([0, 0, -30], [63, 64, 30], (int(0.03 * len(sheet)), 3))  # in the sheet's box
    few = np.vstack([sheet, scattered])
    pair = PreparedPair(few, few + 0.01, RegisterConfig(), k=8)
    assert pair.voxel is None and pair.scans and 0 < pair.isolated[0] <= len(scattered)
    # Far returns: a ring of points 10 apart, far out from the sheet, under the 10 %.
    angle = np.arange(0, 2 * np.pi, 10 / 150)
    ring = np.stack([32 + 150 * np.cos(angle), 32 + 150 * np.sin(angle), np.zeros_like(angle)], axis=1)
    out = np.vstack([sheet, ring])
    assert len(ring) < ISOLATED_MAX_SHARE_OFF_GRID * len(out)
    assert PreparedPair(out, out + 0.01, RegisterConfig(), k=8).isolated == (0, 0)
    # Far returns: a second sheet with points 8 apart, each with no other within 6 spacings.
    u, v = np.meshgrid(np.arange(0, 200, 8.0), np.arange(0, 200, 8.0))
    far = np.stack([u.ravel(), v.ravel(), np.full(u.size, 300.0)], axis=1)
    many = np.vstack([sheet, far])
    assert len(far) > ISOLATED_MAX_SHARE_OFF_GRID * len(many)
    assert PreparedPair(many, many + 0.01, RegisterConfig(), k=8).isolated == (0, 0)


def test_scattered_outliers_on_the_grid_are_left_out():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    rng = np.random.default_rng(0)
    n, m = len(src) // 10, len(tgt) // 10  # 10 % more points, scattered in each scan's box
    noisy = (np.vstack([src, rng.uniform(src.min(0), src.max(0), (n, 3))]), np.vstack([tgt, rng.uniform(tgt.min(0), tgt.max(0), (m, 3))]))
    res = register(*noisy, RegisterConfig(voxel=0.004))
    assert not res.likely_failed and pair_errors(res.transformation, T).rotation_deg < 1.0
    assert res.removed["source_isolated"] > 0.3 * n and res.removed["target_isolated"] > 0.3 * m  # the rest lie near others in a 15 cm box
    kept = register(*noisy, RegisterConfig(voxel=0.004, isolated_radius=0.0))  # with them, the clouds fill a volume
    assert kept.likely_failed and kept.removed["source_isolated"] == 0
    clean = register(src, tgt, RegisterConfig(voxel=0.004))  # a clean scan's few isolated points stay
    assert clean.removed["source_isolated"] == clean.removed["target_isolated"] == 0


def test_clouds_that_do_not_overlap_are_flagged():
    rng = np.random.default_rng(6)
    bunny = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    floor = np.c_[rng.uniform(-5, 5, size=(20_000, 2)), rng.normal(scale=0.002, size=20_000)]  # a 10 m floor
    res = register(bunny, floor)
    assert res.likely_failed and res.failure_reason


def test_kiss_matchers_estimate_comes_before_the_feature_match_on_scans(monkeypatch):
    from o3dsoft import baselines
    from o3dsoft.strategies import features

    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    truth = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    feature_runs, kiss_runs = [], []
    real_propose = features.FeatureMatchProposals.propose
    monkeypatch.setattr(features.FeatureMatchProposals, "propose", lambda self, pair, verifier: feature_runs.append(1) or real_propose(self, pair, verifier))
    monkeypatch.setattr(baselines, "kiss_matcher", lambda s, t, voxel, *radii: kiss_runs.append((voxel, *radii)) or truth)
    monkeypatch.setattr("o3dsoft.pipeline.kiss_available", lambda: True)  # faked above: the optional package need not be installed
    config = RegisterConfig(voxel=0.003, search=SearchConfig(mode="always"))  # on a grid: a scan
    res = register(src, tgt, config)
    assert len(kiss_runs) == 1 and not feature_runs  # trusted: the feature match is not needed
    assert kiss_runs[0][0] == pytest.approx(0.01 * max(scene_size(src), scene_size(tgt)), rel=0.05)
    assert kiss_runs[0][1:] == (config.search.kiss_normal_radius, config.search.kiss_feature_radius)
    assert not res.likely_failed and pair_errors(res.transformation, truth).rotation_deg < 0.5
    register(src, tgt, replace(config, search=replace(config.search, kiss=False)))
    register(src[::2], tgt[::2], replace(config, voxel=None))  # 3,500 points, no grid: the ModelNet40 protocols' path
    register(src, tgt, replace(config, voxel=0))  # every point of 7,000: a scan a user downsampled already
    assert len(kiss_runs) == 2 and len(feature_runs) == 2
    monkeypatch.setattr("o3dsoft.pipeline.kiss_available", lambda: False)  # o3dsoft without its [peers] extra
    register(src, tgt, config)
    assert len(kiss_runs) == 2 and len(feature_runs) == 3


def _turned_pair(euler_deg):
    rng = np.random.default_rng(4)
    src = blob(rng, 800)
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix(euler_deg)
    T[:3, 3] = [0.3, -0.2, 0.1]
    return src, apply(T, src), T


def test_a_flagged_first_network_is_followed_by_the_second_one(monkeypatch, tmp_path):
    from o3dsoft import coarse
    from o3dsoft.config import SecondNetworkConfig

    src, tgt, T = _turned_pair([150.0, -20.0, 30.0])
    asked = []
    second = NearSightedModel(np.eye(3))
    second.R_true = T[:3, :3]
    second.config = replace(second.config)  # k=8, like the first
    weights = tmp_path / "second.pt"
    weights.touch()  # a file, as register checks before it runs; the fake loader gives the network

    def fake_cached_model(path, device="cpu"):
        asked.append((path, device))
        return second if path == str(weights) else coarse.load_model(path, device)

    monkeypatch.setattr(coarse, "cached_model", fake_cached_model)
    off = SearchConfig(mode="off")
    first = AlwaysWrongModel(euler_to_matrix([0.0, 0.0, 180.0]))  # a half turn about z, far from either pair's truth: flagged
    config = RegisterConfig(num_points=800, search=off, second_network=SecondNetworkConfig(weights=weights, iterations=2))
    second_only_finds_under_50 = register(src, tgt, config, model=first)
    # NearSightedModel finds rotations under 50 degrees only: from the pose as given it returns the
    # identity, so the result stays flagged, with both networks' estimates tried.
    assert second_only_finds_under_50.likely_failed and second_only_finds_under_50.attempts == 2
    assert asked == [(str(weights), "cpu")] and "second_network" in second_only_finds_under_50.timings_ms

    src, tgt, T = _turned_pair([40.0, 0.0, 0.0])
    second.R_true = T[:3, :3]
    res = register(src, tgt, config, model=first)
    assert not res.likely_failed and res.attempts == 2 and pair_errors(res.transformation, T).rotation_deg < 1e-3
    assert res.estimate_from == "second network"
    assert rotation_angle_deg(res.network_transformation[:3, :3]) == pytest.approx(180.0)  # the first network's own estimate is still reported

    asked.clear()
    on_a_grid = register(src, tgt, replace(config, voxel=0.02), model=first)  # a scan's path: the search's feature match follows, not the second network
    assert on_a_grid.voxel == 0.02 and on_a_grid.likely_failed and on_a_grid.attempts == 1 and asked == [] and "second_network" not in on_a_grid.timings_ms

    asked.clear()
    res = register(src, tgt, RegisterConfig(num_points=800, search=off, second_network=SecondNetworkConfig(weights=None)), model=first)
    assert res.likely_failed and res.attempts == 1 and asked == [] and "second_network" not in res.timings_ms
    assert res.estimate_from == "network"

    confident_first = NearSightedModel(T[:3, :3])
    res = register(src, tgt, config, model=confident_first)
    assert not res.likely_failed and res.attempts == 1 and asked == []  # trusted: the second network is not even loaded


def test_second_network_settings_are_checked():
    from o3dsoft.config import SecondNetworkConfig

    src, tgt, _ = blob_pair()
    with pytest.raises(InputError, match="second_network.iterations"):
        register(src, tgt, RegisterConfig(second_network=SecondNetworkConfig(iterations=0)))


def _dense_onto_sparse(seed=21):
    """A dense source of 3,000 points, and a target of 150 of them, moved."""
    rng = np.random.default_rng(seed)
    src = blob(rng, 3000)
    T = random_transform(rng, max_angle=8.0, max_t=0.2)
    return src, apply(T, src[rng.choice(len(src), 150, replace=False)]), T


def test_a_much_sparser_target_is_registered_onto_the_source_and_the_result_inverted(tiny_model_path):
    from o3dsoft.refine import evaluate

    src, tgt, T = _dense_onto_sparse()
    cfg = RegisterConfig(weights=str(tiny_model_path), icp=ICPConfig(distance=0.5), second_network=NO_SECOND)
    res = register(src, tgt, cfg)
    assert res.sparser_moved
    reverse = register(tgt, src, cfg)  # the same registration, asked the other way round
    assert not reverse.sparser_moved
    np.testing.assert_allclose(res.transformation, np.linalg.inv(reverse.transformation), atol=1e-9)
    # every field speaks of the source onto the target, as asked
    assert (res.num_source, res.num_target) == (3000, 150) and res.points_used["network"] == (1024, 150)
    assert res.fitness == pytest.approx(evaluate(src, tgt, res.transformation, res.correspondence_distance).fitness)
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1e-3 and e.translation < 1e-4  # each sparse point has its exact partner
    kept = register(src, tgt, replace(cfg, sparser_moves=0.0))
    assert not kept.sparser_moved and pair_errors(kept.transformation, T).rotation_deg > 10 * e.rotation_deg


def test_sparser_moves_is_validated(tiny_model_path):
    src, tgt, _ = blob_pair()
    with pytest.raises(InputError, match="sparser_moves"):
        register(src, tgt, RegisterConfig(weights=str(tiny_model_path), sparser_moves=0.5))


def test_repeated_calls_load_the_network_once(monkeypatch):
    from o3dsoft import coarse

    loaded = []
    real = coarse.load_model
    monkeypatch.setattr(coarse, "_LOADED", {})
    monkeypatch.setattr(coarse, "load_model", lambda path=None, device="cpu": loaded.append(path) or real(path, device))
    src, tgt, _ = _turned_pair([10.0, 0.0, 0.0])
    config = RegisterConfig(num_points=800, search=SearchConfig(mode="off"))
    first, again = register(src, tgt, config), register(src, tgt, config)
    assert loaded == [None] and "load_model" in first.timings_ms
    np.testing.assert_array_equal(first.transformation, again.transformation)


def test_right_alignments_of_independent_samplings_of_a_complete_shape_are_reported_trusted(modelnet_root):
    from o3dsoft import confidence
    from o3dsoft.data import get_protocol, load_pairs

    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent"), 0)
    strict_flags = 0
    for i in (2, 3, 6):  # each cloud 512 of a shape's 1,024 points, none shared
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        errors = pair_errors(result.transformation, pairs[i].transform)
        assert errors.rotation_deg < 2 and errors.translation < 0.02, i
        assert not result.likely_failed and result.failure_reason is None, (i, result.confidence)
        f = confidence.features(pairs[i].source, pairs[i].target, result.transformation, 0.1 * result.scale)
        strict_flags += confidence.confidence(f) < 0.5
        # A wrong pose of the same pair, turned 40 degrees about a vertical axis, is not trusted.
        turned = rigid(euler_to_matrix(np.array([0.0, 0.0, 40.0])), np.zeros(3)) @ result.transformation
        assert confidence.complete_confidence(confidence.features(pairs[i].source, pairs[i].target, turned, 0.1 * result.scale)) < 0.5
    assert strict_flags >= 2  # the strict function alone would flag them


def test_on_independent_samplings_of_a_complete_shape_the_choice_weighs_the_overlap(modelnet_root, monkeypatch):
    from o3dsoft import verify
    from o3dsoft.data import get_protocol, load_pairs

    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent-so3"), 0)
    for i in (51, 89):  # a bathtub and a sink, any rotation, no point shared
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        errors = pair_errors(result.transformation, pairs[i].transform)
        assert errors.rotation_deg < 5 and errors.translation < 0.05 and not result.likely_failed, (i, errors, result.confidence)
    # Ranked by the strict confidence alone, the sink's search ends on its half turn, trusted; the
    # symmetry probe finds a copy of that pose that fits the clouds closer, and flags it.
    monkeypatch.setattr(verify.Verifier, "independent", lambda self: False)
    unprobed = RegisterConfig(symmetry=SymmetryConfig(enabled=False))
    strict_choice = o3dsoft.register(pairs[89].source, pairs[89].target, unprobed)
    assert pair_errors(strict_choice.transformation, pairs[89].transform).rotation_deg > 170 and not strict_choice.likely_failed
    probed = o3dsoft.register(pairs[89].source, pairs[89].target)
    assert probed.likely_failed and probed.copy_fit < 0.8 and "a copy of the result turned" in probed.failure_reason


def test_a_trusted_pose_the_geometry_does_not_hold_starts_the_search(modelnet_root, monkeypatch):
    from o3dsoft import pipeline
    from o3dsoft.data import get_protocol, load_pairs

    # A tv stand and a night stand, no point shared: the first network's pose fits a part of the
    # shape closely (trusted strictly) and fits as well turned 30 degrees (flagged as undetermined).
    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent"), 0)
    for i in (185, 199):
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        errors = pair_errors(result.transformation, pairs[i].transform)
        assert errors.rotation_deg < 5 and errors.translation < 0.05, (i, errors)
        # Trusted, unless its half-turned copy fits as closely (the tv stand): then flagged for that alone.
        assert not result.likely_failed or "a copy of the result turned" in result.failure_reason, (i, result.failure_reason)
        assert result.searched and pair_errors(result.network_transformation, pairs[i].transform).rotation_deg > 20
    # A bowl: what the search finds is another turn of the bowl, which fits the clouds no closer
    # than the flagged pose; the result stays flagged, where replacing it would trust a wrong pose.
    bowl = pairs[25]
    kept = o3dsoft.register(bowl.source, bowl.target)
    assert kept.searched and kept.likely_failed
    replaced = o3dsoft.register(bowl.source, bowl.target, RegisterConfig(search=SearchConfig(undetermined_gain=1.0), symmetry=SymmetryConfig(enabled=False)))
    assert not replaced.likely_failed and pair_errors(replaced.transformation, bowl.transform).rotation_deg > 20
    # The symmetry probe flags that pose too: a turned copy fits as closely.
    probed = o3dsoft.register(bowl.source, bowl.target, RegisterConfig(search=SearchConfig(undetermined_gain=1.0)))
    assert probed.likely_failed and probed.copy_fit <= 1.1 and "a copy of the result turned" in probed.failure_reason
    # Without the geometry's flag, the first network's pose, trusted strictly, is kept and nothing else is tried.
    real = pipeline._assess
    monkeypatch.setattr(pipeline, "_assess", lambda pair, best: real(pair, best)._replace(reason=None))
    unflagged = o3dsoft.register(pairs[185].source, pairs[185].target)
    assert not unflagged.searched and pair_errors(unflagged.transformation, pairs[185].transform).rotation_deg > 20


def test_only_complete_looking_clouds_that_are_not_scans_count_as_complete():
    from o3dsoft.pair import PreparedPair

    rng = np.random.default_rng(4)

    def ellipsoid(n):  # n points on the surface of an ellipsoid of semi-axes 1, 0.6 and 0.3
        p = rng.normal(size=(n, 3))
        return p / np.linalg.norm(p, axis=1, keepdims=True) * [1.0, 0.6, 0.3]

    config = RegisterConfig()
    assert PreparedPair(ellipsoid(800), ellipsoid(800), config, 8).complete  # two samplings of one shape
    cut = ellipsoid(1600)
    assert not PreparedPair(ellipsoid(800), cut[cut[:, 0] > 0.3], config, 8).complete  # a partial overlap
    assert not PreparedPair(ellipsoid(30_000), ellipsoid(30_000), config, 8).complete  # scans


def test_the_reason_a_complete_looking_pair_is_flagged_names_the_overlap_when_that_is_what_is_short():
    from o3dsoft import confidence
    from o3dsoft.pipeline import _failure_reason
    from o3dsoft.refine import ICPResult
    from o3dsoft.verify import Attempt

    def flagged(consistency: float, overlap: float) -> Attempt:
        f = confidence.Features(fitness_tight=0.4, tight_distance=0.07, consistency=consistency, overlap=overlap, spacing_ratio=1.1)
        assert max(confidence.confidence(f), confidence.complete_confidence(f)) < 0.5
        return Attempt(0.01, f, ICPResult(np.eye(4), 0.5, 0.01), np.eye(4), np.eye(4))

    config = RegisterConfig()
    half_turn = flagged(consistency=0.86, overlap=0.44)  # a sink turned by 180 degrees: half of it has no partner
    assert "both clouds look complete but those points are only 44 % of the smaller one" in _failure_reason(half_turn, config, True, complete=True)
    assert "complete" not in _failure_reason(half_turn, config, True, complete=False)
    apart = flagged(consistency=0.5, overlap=0.97)  # overlapping, but not close: the overlap is not what is short
    assert "complete" not in _failure_reason(apart, config, True, complete=True)
    assert "surface" not in _failure_reason(apart, config, True)  # planar not measured
    scan = apart._replace(scored=apart.scored._replace(planar=0.31))
    assert "and 31 % within 0.007 units of its surface" in _failure_reason(scan, config, True)


def test_right_alignments_of_scans_whose_overlap_grazes_are_reported_trusted(bunny_root, monkeypatch):
    from o3dsoft import confidence
    from o3dsoft.scans import read_conf, relative_pose

    # The two bunny scans that overlap least of the bench's pairs: at the right pose about one in
    # eight of their nearby points lies off the other scan at grazing angles, so the strict
    # function flags it; most of the overlap lies on the other scan's surface.
    poses = read_conf(bunny_root / "bun.conf")
    src, tgt = (o3dsoft.read_points(bunny_root / f"{name}.ply") for name in ("bun090", "bun180"))
    truth = relative_pose(poses, "bun090.ply", "bun180.ply")
    res = register(src, tgt)
    errors = pair_errors(res.transformation, truth)
    assert errors.rotation_deg < 1.0 and errors.translation < 0.002
    assert not res.likely_failed and res.consistency < 0.9
    # By the strict function alone, the same pose is flagged.
    monkeypatch.setattr(confidence, "scan_confidence", lambda f, config=None: 0.0)
    strict = register(src, tgt)
    assert np.allclose(strict.transformation, res.transformation, atol=1e-9) and strict.likely_failed


def test_the_second_networks_trusted_pose_of_two_independent_samplings_ends_the_search(modelnet_root):
    from o3dsoft.config import SecondNetworkConfig
    from o3dsoft.data import get_protocol, load_pairs

    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent"), 0)
    for i in (10, 28):  # each cloud 512 of a shape's 1,024 points, none shared; the first network is far off
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        errors = pair_errors(result.transformation, pairs[i].transform)
        assert errors.rotation_deg < 2 and errors.translation < 0.02 and not result.likely_failed, (i, errors, result.confidence)
        assert result.estimate_from == "second network" and not result.searched
        assert pair_errors(result.network_transformation, pairs[i].transform).rotation_deg > 10
    # Without the rule only the strict confidence ends the search, and it flags the second network's pose.
    searched = o3dsoft.register(pairs[28].source, pairs[28].target, RegisterConfig(second_network=SecondNetworkConfig(ends_search=None)))
    assert searched.searched and searched.attempts > 20


def test_the_second_network_from_turned_starts_ends_the_search_on_clouds_turned_far(modelnet_root):
    from o3dsoft.config import SecondNetworkConfig
    from o3dsoft.data import get_protocol, load_pairs

    # Two independent samplings of a shape turned by any rotation: from the pose as given the
    # second network, trained within 45 degrees per axis, is far off; from one of a cube's
    # rotations it is right, and the complete confidence trusts that pose.
    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent-so3"), 0)
    turned = RegisterConfig(second_network=SecondNetworkConfig(turns=4))
    for i in (153, 157):
        result = o3dsoft.register(pairs[i].source, pairs[i].target, turned)
        errors = pair_errors(result.transformation, pairs[i].transform)
        assert errors.rotation_deg < 2 and errors.translation < 0.03 and not result.likely_failed, (i, errors, result.confidence)
        assert result.estimate_from == "second network, turned" and not result.searched and result.attempts < 20
        # Without the turned starts the search runs, and its answer is not within (5 deg, 0.05).
        unturned = o3dsoft.register(pairs[i].source, pairs[i].target)  # the default: off
        assert unturned.searched and unturned.estimate_from != "second network, turned"
        off = pair_errors(unturned.transformation, pairs[i].transform)
        assert off.rotation_deg > 5 or off.translation > 0.05, (i, off)


def test_before_the_second_network_ends_the_search_the_feature_match_looks_for_shared_points(modelnet_root):
    from o3dsoft.config import SecondNetworkConfig
    from o3dsoft.data import get_protocol, load_pairs

    # A bowl and a table cropped from one noisy point set: the second network's pose is a wrong
    # turn that fits like two independent samplings; the feature match's first candidate is right.
    pairs = load_pairs(modelnet_root, "test", get_protocol("rpmnet-crop"), 0)
    for i in (25, 26):
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        assert pair_errors(result.transformation, pairs[i].transform).rotation_deg < 1 and not result.likely_failed, i
        assert result.estimate_from == "feature match" and not result.searched
        unchecked = o3dsoft.register(pairs[i].source, pairs[i].target, RegisterConfig(second_network=SecondNetworkConfig(shared_check=0)))
        assert unchecked.estimate_from == "second network" and not unchecked.searched
        assert pair_errors(unchecked.transformation, pairs[i].transform).rotation_deg > 45 and not unchecked.likely_failed, i


def test_the_second_networks_search_settings_are_checked():
    from o3dsoft.config import SecondNetworkConfig

    src, tgt, _ = blob_pair()
    with pytest.raises(InputError, match="second_network.ends_search"):
        register(src, tgt, RegisterConfig(second_network=SecondNetworkConfig(ends_search=0.3)))
    with pytest.raises(InputError, match="second_network.shared_check"):
        register(src, tgt, RegisterConfig(second_network=SecondNetworkConfig(shared_check=-1)))
    for turns in (-1, 24):
        with pytest.raises(InputError, match="second_network.turns"):
            register(src, tgt, RegisterConfig(second_network=SecondNetworkConfig(turns=turns)))


def test_on_partial_overlaps_the_choice_takes_the_pose_that_brings_most_points_into_contact(modelnet_root):
    from o3dsoft.data import get_protocol, load_pairs

    # A sink and a guitar, each cloud half of a shape's points cropped to about 70 %, none shared:
    # the strict confidence trusts most a half turn whose part fits closely.
    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent-crop"), 0)
    most_trusted = RegisterConfig(search=SearchConfig(partial_choice=None))
    for i in (15, 19):
        result = o3dsoft.register(pairs[i].source, pairs[i].target)
        assert pair_errors(result.transformation, pairs[i].transform).rotation_deg < 2, i
        assert pair_errors(o3dsoft.register(pairs[i].source, pairs[i].target, most_trusted).transformation, pairs[i].transform).rotation_deg > 150, i


def test_the_partial_choice_weights_are_checked():
    src, tgt, _ = blob_pair()
    for bad in ((1.0, 2.0), (1.0, 2.0, float("nan"), 0.0)):
        with pytest.raises(InputError, match="search.partial_choice"):
            register(src, tgt, RegisterConfig(search=SearchConfig(partial_choice=bad)))


def test_on_a_partial_overlap_the_confidence_counts_the_estimates_that_reached_the_pose(modelnet_root):
    from o3dsoft.confidence import ConfidenceConfig
    from o3dsoft.data import get_protocol, load_pairs

    # A crop pair of independent samplings that the search ran on: its right pose, reached by
    # several estimates, fits no closer than the wrong poses the strict confidence flags alike.
    pair = load_pairs(modelnet_root, "test", get_protocol("incongruent-crop"), 0)[13]
    result = o3dsoft.register(pair.source, pair.target)
    off = o3dsoft.register(pair.source, pair.target, RegisterConfig(confidence=ConfidenceConfig(partial_coefficients=None)))
    np.testing.assert_allclose(result.transformation, off.transformation)  # the confidence changes no pose
    assert pair_errors(result.transformation, pair.transform).rotation_deg < 2 and result.searched
    c0, c1 = ConfidenceConfig().partial_coefficients
    assert 5 <= result.agreeing < result.attempts
    assert result.confidence == pytest.approx(1 / (1 + np.exp(-(c0 + c1 * np.log(result.agreeing)))))
    assert result.confidence > 2 * off.confidence
    assert f", and {result.agreeing} of the {result.attempts} estimates reached this pose (trusted from 43)" in result.failure_reason
    assert 1 / (1 + np.exp(-(c0 + c1 * np.log(43)))) >= 0.5 > 1 / (1 + np.exp(-(c0 + c1 * np.log(42))))
    assert off.agreeing == result.agreeing and "estimates reached" not in off.failure_reason


def test_an_initial_guess_near_the_truth_is_refined_and_ends_the_proposals():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    guess = rigid(euler_to_matrix([6.0, -4.0, 5.0]) @ T[:3, :3], T[:3, 3] + [0.004, -0.003, 0.002])  # 8 degrees, 5 mm off
    model = AlwaysWrongModel(T[:3, :3] @ euler_to_matrix([180.0, 0.0, 0.0]))  # would turn the source over
    res = register(src, tgt, model=model, init=guess)
    # The result is T_target_source of the clouds as given, from ICP started at the guess; the
    # network and the feature match never ran.
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1.0 and e.translation < 0.002 and not res.likely_failed
    assert res.estimate_from == "initial guess" and res.network_transformation is None and not res.searched
    assert np.allclose(res.coarse_transformation, guess)
    # A target ten times sparser is registered the other way round: the guess still holds.
    sparse = register(src, tgt[::10], model=model, init=guess)
    assert sparse.sparser_moved and sparse.estimate_from == "initial guess" and pair_errors(sparse.transformation, T).rotation_deg < 1.0


def test_a_wrong_initial_guess_does_not_stop_the_pipeline():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    T = o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")
    wrong = rigid(euler_to_matrix([0.0, 150.0, 0.0]) @ T[:3, :3], T[:3, 3])
    res = register(src, tgt, init=wrong)
    assert res.estimate_from != "initial guess" and pair_errors(res.transformation, T).rotation_deg < 1.0 and not res.likely_failed
    # Under a rotation prior the bound holds about the guess: nothing within 10 degrees of it fits.
    bounded = register(src, tgt, RegisterConfig(max_rotation=10.0), init=wrong)
    assert bounded.likely_failed and rotation_error_deg(bounded.transformation[:3, :3], wrong[:3, :3]) <= 10.0 + 1e-6


@pytest.mark.parametrize(
    "init, match",
    [
        (np.eye(3), r"init: expected a 4x4 transform \(or 3x4 \[R \| t\]\), got shape \(3, 3\)"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "init: not a rigid transform"),
        (np.full((4, 4), np.nan), "init: contains NaN"),
    ],
)
def test_an_initial_guess_must_be_a_rigid_transform(init, match):
    with pytest.raises(InputError, match=match):
        register(blob(np.random.default_rng(0)), blob(np.random.default_rng(1)), init=init)


def test_an_initial_guess_may_be_3x4_as_its_files_may(tmp_path):
    from o3dsoft.io import as_rigid

    T = rigid(euler_to_matrix([10.0, -20.0, 30.0]), np.array([1.0, 2.0, 3.0]))
    assert np.array_equal(as_rigid(T[:3], "init"), T)
    with pytest.raises(InputError, match="T.txt: not a rigid transform"):
        o3dsoft.write_transform(tmp_path / "T.txt", np.diag([2.0, 1.0, 1.0, 1.0]))  # what read_transform would refuse
    with pytest.raises(InputError, match="T.txt: contains NaN"):
        o3dsoft.write_transform(tmp_path / "T.txt", np.full((4, 4), np.nan))
    assert not (tmp_path / "T.txt").exists()


def test_from_a_guess_on_geometry_that_cannot_fix_the_pose_the_guess_is_kept(monkeypatch):
    from o3dsoft import pipeline

    def floor_and_wall(rng, n=1500):  # two planes: free to slide along the line where they meet
        return np.vstack([np.c_[rng.uniform(0, 2, n), rng.uniform(0, 2, n), np.zeros(n)], np.c_[np.zeros(n), rng.uniform(0, 2, n), rng.uniform(0, 1, n)]])

    rng = np.random.default_rng(0)
    T = rigid(euler_to_matrix([5.0, -8.0, 20.0]), np.array([0.3, -0.2, 0.1]))
    src, tgt = floor_and_wall(rng), apply(T, floor_and_wall(rng))
    # Whatever the search finds fits closer (as a feature-match pose 86 degrees off did on a real floor and wall).
    monkeypatch.setattr(pipeline, "_fits_closer", lambda *args: True)
    res = register(src, tgt, init=T)
    assert res.likely_failed and "can slide" in res.failure_reason and res.search_reason is not None
    assert res.estimate_from == "initial guess" and pair_errors(res.transformation, T).rotation_deg < 1.0


def test_from_a_guess_the_motions_the_surfaces_leave_free_stay_at_the_guess():
    from o3dsoft.degeneracy import DegeneracyConfig

    def corridor(rng, start, end, n=1500):  # two walls 1.5 apart: nothing holds the motion along them
        return np.vstack(
            [np.c_[np.zeros(n), rng.uniform(start, end, n), rng.uniform(0, 2, n)], np.c_[np.full(n, 1.5), rng.uniform(start, end, n), rng.uniform(0, 2, n)]]
        )

    rng = np.random.default_rng(0)
    T = rigid(euler_to_matrix([3.0, -4.0, 10.0]), np.array([0.3, -0.2, 0.1]))
    src, tgt = corridor(rng, 0, 3), apply(T, corridor(rng, 1, 4))  # views of overlapping stretches
    kept = register(src, tgt, init=T)
    assert kept.likely_failed and "the initial guess is kept" in kept.failure_reason
    assert pair_errors(kept.transformation, T).translation < 0.01
    slid = register(src, tgt, RegisterConfig(degeneracy=DegeneracyConfig(held_from=0.0)), init=T)  # every motion ICP made
    # (ICP's tight stages, which run first from a guess, slide 5 cm here; the whole schedule 0.3 m and more)
    assert pair_errors(slid.transformation, T).translation > 0.03 and "kept" not in slid.failure_reason


def test_open3d_warnings_come_back_after_blocks_that_overlap_across_threads():
    import threading

    import open3d as o3d

    from o3dsoft._open3d import quiet

    before = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Info)
    try:
        entered, leave = threading.Event(), threading.Event()

        def other():
            with quiet():
                entered.set()
                leave.wait(10)

        thread = threading.Thread(target=other)
        thread.start()
        entered.wait(10)
        with quiet():  # enters after the other thread, leaves before it
            assert o3d.utility.get_verbosity_level() == o3d.utility.VerbosityLevel.Error
        assert o3d.utility.get_verbosity_level() == o3d.utility.VerbosityLevel.Error  # the other block is still open
        leave.set()
        thread.join(10)
        assert o3d.utility.get_verbosity_level() == o3d.utility.VerbosityLevel.Info
    finally:
        o3d.utility.set_verbosity_level(before)


def ground_with_a_few_objects(real_scans_root):
    """The laser pair cut to its ground within 20 m plus five small objects (posts, cars' parts):
    (source, target, T_target_source). Yaw rests on the objects alone."""
    import open3d as o3d

    folder = real_scans_root / "outdoor_laser_car"
    source, target = (o3dsoft.read_points(folder / f"car_cloud{n}.ply") for n in (401, 400))
    T = o3dsoft.read_transform(folder / "gt_401_to_400.txt")
    plane = np.array([-0.0715, 0.1875, 0.9797, 0.9373])  # the ground's (normal, offset) in the target's frame
    height = lambda p: p @ plane[:3] + plane[3]  # noqa: E731
    near = lambda p: np.linalg.norm(p[:, :2], axis=1) < 20.0  # noqa: E731
    standing = target[(np.abs(height(target)) > 0.3) & near(target)]
    labels = np.array(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(standing)).cluster_dbscan(0.6, 10))
    small = [c for c in range(labels.max() + 1) if 30 <= (labels == c).sum() <= 600 and np.ptp(standing[labels == c], axis=0).max() < 8.0]
    rng = np.random.default_rng(0)
    rng.choice(small, 2, replace=False)
    objects = standing[np.isin(labels, rng.choice(small, 5, replace=False))]
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(objects)))

    def cut(points_in_target_frame: np.ndarray) -> np.ndarray:
        on_object = np.array([tree.search_knn_vector_3d(p, 1)[2][0] < 0.25 for p in points_in_target_frame])
        return near(points_in_target_frame) & ((np.abs(height(points_in_target_frame)) < 0.25) | on_object)

    return source[cut(apply(T, source))], target[cut(target)], T


def test_from_a_close_guess_icp_does_not_slide_on_a_ground_with_a_few_objects(real_scans_root):
    """ICP's loose first stage (10 % of the scene's radius, 2 m here) pulls a guess 3 degrees and
    0.5 m off on the ground to a pose 10 degrees off, which the ground alone makes look right:
    from a guess the tight stages run first."""
    source, target, T = ground_with_a_few_objects(real_scans_root)
    guess = rigid(euler_to_matrix([0.0, 0.0, 3.0]), [0.5, 0.0, 0.0]) @ T  # 3 degrees about the ground's normal, 0.5 m
    res = register(source, target, init=guess)
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1.0 and e.translation < 0.3, (e, res.confidence)
    assert res.estimate_from == "initial guess" and not res.likely_failed


def test_the_library_entry_points_read_as_short_signatures_and_take_none_for_the_defaults():
    """help(o3dsoft.register) opens with its signature: not the whole default RegisterConfig."""
    import inspect

    for function in (o3dsoft.register, o3dsoft.multiway):
        assert len(str(inspect.signature(function))) < 400, function.__name__
    src, tgt, T = blob_pair(n=200)
    assert pair_errors(register(src, tgt, None).transformation, T).rotation_deg < 1.0


def test_a_flagged_scan_result_says_when_kiss_matcher_is_missing(monkeypatch):
    from o3dsoft import pipeline

    rng = np.random.default_rng(3)
    unrelated = blob(rng, 5000), blob(rng, 5000) * [1.0, 0.5, 2.0]  # scans by their size, no pose fits both
    monkeypatch.setattr(pipeline, "kiss_available", lambda: False)
    res = register(*unrelated)
    assert res.likely_failed and res.failure_reason.endswith("is not installed: pip install 'o3dsoft[peers]'"), res.failure_reason


def test_a_guess_turned_far_off_on_a_street_scan_is_searched_past(real_scans_root):
    """ICP from a guess turned 90 degrees ends at a pose that fits the thinned street scan closely
    but as well turned (the geometry's flag); nothing else had been tried: the search runs."""
    from scipy.spatial.transform import Rotation

    folder = real_scans_root / "outdoor_laser_car"
    source, target = (o3dsoft.read_points(folder / f"car_cloud{n}.ply") for n in (401, 400))
    rng = np.random.default_rng(11)
    source, target = source[rng.choice(len(source), 10000, replace=False)], target[rng.choice(len(target), 10000, replace=False)]
    T = o3dsoft.read_transform(folder / "gt_401_to_400.txt")
    turn = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    centre = apply(T, source.mean(axis=0)[None])[0]
    res = register(source, target, init=rigid(turn, centre - turn @ centre) @ T)
    e = pair_errors(res.transformation, T)
    assert e.rotation_deg < 1.0 and e.translation < 0.3 and not res.likely_failed and res.searched, (e.rotation_deg, res.failure_reason)


def test_prepared_clouds_come_in_pairs_of_one_kind():
    from o3dsoft.pair import PreparedPair, on_grid
    from o3dsoft.preprocess import clean_points

    points = blob(np.random.default_rng(0), 400)
    cleaned = clean_points(points)
    gridded = on_grid(cleaned, 0.05, RegisterConfig(), 8, "blob")
    for source, target in ((cleaned, points), (points, cleaned), (gridded, cleaned), (cleaned, gridded)):
        with pytest.raises(ValueError, match="come in pairs"):
            PreparedPair(source, target, RegisterConfig(), 8)
    pair = PreparedPair(cleaned, cleaned._replace(points=points + 1.0), RegisterConfig(), 8)
    assert pair.full[0] is cleaned.points and pair.cleaned[0] is cleaned  # cleaned by the caller: not again
