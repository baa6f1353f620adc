"""o3dsoft.multiway: the spanning tree, the pose graph, and scans of one object into one frame."""

from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

import o3dsoft
from o3dsoft.cli.main import main
from o3dsoft.coarse import load_model
from o3dsoft.config import RegisterConfig, SearchConfig
from o3dsoft.errors import InputError
from o3dsoft.io import read_points, read_poses, write_points
from o3dsoft.metrics import pair_errors
from o3dsoft.multiway import Edge, MultiwayConfig, _anchor, _groups, _optimise, _tree, choose_pairs, merged_cloud, multiway
from o3dsoft.transforms import euler_to_matrix, rigid

from .conftest import EXAMPLES, apply, blob, random_transform
from .fakes import AlwaysWrongModel


def _edge(source, target, confidence, T=None):
    return Edge(source, target, np.eye(4) if T is None else T, confidence, 0.9, confidence < 0.5, None, 0.1)


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.fixture(scope="module")
def scans():
    """Four views of the bundled bunny scan: each a random 60 % of its points cut by its own
    half-space to about 80 %, then moved by a known pose (world_T_scan^-1)."""
    rng = np.random.default_rng(3)
    shape = read_points(EXAMPLES / "bun000.ply")
    clouds, poses = [], []
    for k in range(4):
        points = shape[rng.random(len(shape)) < 0.6]
        direction = rng.normal(size=3)
        along = (points - points.mean(axis=0)) @ direction
        points = points[along < np.quantile(along, 0.8)]
        pose = np.eye(4) if k == 0 else random_transform(rng, max_angle=25.0, max_t=0.03)
        clouds.append(apply(np.linalg.inv(pose), points))
        poses.append(pose)
    return clouds, poses


def test_pairs_all_sequence_and_near():
    clouds = [np.zeros((3, 3)) + [x, 0, 0] for x in (0.0, 10.0, 1.0, 11.0)]
    assert choose_pairs(clouds, MultiwayConfig(neighbours="all")) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert choose_pairs(clouds, MultiwayConfig(neighbours="sequence", window=1)) == [(0, 1), (1, 2), (2, 3)]
    # the nearest of each pair lie in their own group (x 0 and 1, 10 and 11): the nearest pair between the groups joins them
    assert choose_pairs(clouds, MultiwayConfig(neighbours="near", near=1)) == [(0, 2), (1, 2), (1, 3)]
    many = [np.zeros((3, 3))] * 14
    assert len(choose_pairs(many, MultiwayConfig())) == 13 * 3 - 3  # auto: sequence beyond 12 scans, window 3


def test_near_pairs_of_a_sequence_with_a_gap_stay_one_group():
    # Scans 1 m apart along a line, with an 11 m gap after the tenth: each scan's 4 nearest lie on its
    # own side, and one pair, the nearest across the gap, joins the two sides.
    x = np.concatenate([np.arange(10.0), 20.0 + np.arange(10.0)])
    clouds = [blob(np.random.default_rng(0), 20)] * 20
    guesses = [rigid(np.eye(3), [v, 0.0, 0.0]) for v in x]
    pairs = choose_pairs(clouds, MultiwayConfig(neighbours="near"), guesses)
    assert [(i, j) for i, j in pairs if i < 10 <= j] == [(9, 10)]
    assert len(pairs) == len(set(pairs))


def test_near_pairs_scans_where_their_initial_poses_put_them():
    clouds = [blob(np.random.default_rng(k), 50) for k in range(4)]  # four clouds about the origin
    guesses = [rigid(np.eye(3), [x, 0.0, 0.0]) for x in (0.0, 5.0, 1.0, 6.0)]
    assert choose_pairs(clouds, MultiwayConfig(neighbours="near", near=1), guesses) == [(0, 2), (1, 2), (1, 3)]
    # Beyond all_up_to, "auto" pairs by position where every scan has a pose, else in sequence.
    assert choose_pairs(clouds, MultiwayConfig(all_up_to=2, near=1), guesses) == [(0, 2), (1, 2), (1, 3)]
    assert choose_pairs(clouds, MultiwayConfig(all_up_to=2, window=1), guesses[:3] + [None]) == [(0, 1), (1, 2), (2, 3)]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_near_pairs_do_not_depend_on_the_frame_the_poses_come_in(seed):
    rng = np.random.default_rng(seed)
    clouds = [blob(rng, 30) * 0.1 + rng.uniform(-1, 1, 3) for _ in range(6)]
    poses = [random_transform(rng, max_angle=180.0, max_t=3.0) for _ in range(6)]
    frame = random_transform(rng, max_angle=180.0, max_t=100.0)  # the same scene in another world frame
    config = MultiwayConfig(neighbours="near", near=2)
    assert choose_pairs(clouds, config, poses) == choose_pairs(clouds, config, [frame @ P for P in poses])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_poses_read_back_from_kitti_text_as_written(tmp_path_factory, seed):
    rng = np.random.default_rng(seed)
    poses = [random_transform(rng, max_angle=180.0, max_t=1000.0) for _ in range(3)]
    path = tmp_path_factory.mktemp("poses") / "poses.txt"
    path.write_text("".join(" ".join(f"{v:.9e}" for v in P[:3].ravel()) + "\n" for P in poses))  # KITTI's layout
    for read, P in zip(read_poses(path, ["a", "b", "c"]), poses):
        assert np.allclose(read, P, atol=1e-5) and np.allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-12)


def _spanning_tree(n, edges):
    """The world scan (the first of the largest group) and that group's tree, as multiway builds them."""
    largest = _groups(n, edges)[0]
    return largest[0], _tree(largest, largest[0], edges)


def test_spanning_tree_takes_the_most_confident_trusted_edges():
    edges = [_edge(1, 0, 0.9), _edge(2, 0, 0.6), _edge(2, 1, 0.95), _edge(3, 2, 0.2)]
    world, tree = _spanning_tree(4, edges)
    assert world == 0
    assert {child: parent for child, (parent, _) in tree.items()} == {1: 0, 2: 1}  # 2 via 1 (0.95), not via 0 (0.6)
    assert 3 not in tree  # its only edge is flagged


def test_spanning_tree_of_the_largest_group():
    world, tree = _spanning_tree(4, [_edge(0, 1, 0.1), _edge(2, 3, 0.9), _edge(1, 3, 0.8)])
    assert world == 1 and set(tree) == {2, 3}


def test_a_wrong_loop_closure_is_pruned_and_the_right_ones_kept():
    rng = np.random.default_rng(0)
    shape = blob(rng, 2000)
    poses = [np.eye(4)] + [random_transform(rng, 30.0, 0.2) for _ in range(3)]
    clouds = [apply(np.linalg.inv(p), shape) for p in poses]

    def truth(i, j):  # T_j_i: maps scan i onto scan j
        return np.linalg.inv(poses[j]) @ poses[i]

    wrong = random_transform(rng, 40.0, 0.3) @ truth(3, 0)
    edges = [
        _edge(1, 0, 0.99, truth(1, 0)),
        _edge(2, 1, 0.99, truth(2, 1)),
        _edge(3, 2, 0.99, truth(3, 2)),
        _edge(2, 0, 0.9, truth(2, 0)),
        _edge(3, 0, 0.8, wrong),
    ]
    world, tree = _spanning_tree(4, edges)
    optimised, pruned = _optimise(clouds, edges, world, np.eye(4), tree, 0.05, MultiwayConfig())
    assert pruned == {(3, 0)}
    for k in range(4):
        assert pair_errors(optimised[k], poses[k]).rotation_deg < 1e-3


def test_scans_of_one_object_come_into_one_frame(scans, model):
    clouds, poses = scans
    calls = []
    result = multiway(clouds, MultiwayConfig(), names=[f"view{k}" for k in range(4)], model=model, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (6, 6)
    assert result.world == 0 and all(result.joined)
    for k in range(4):
        errors = pair_errors(result.poses[k], poses[k])
        assert errors.rotation_deg < 1.0 and errors.translation < 0.002  # metres: 1 degree, 2 mm
    assert sum(e.in_tree for e in result.edges) == 3
    record = json.loads(json.dumps(result.to_dict()))
    assert [s["name"] for s in record["scans"]] == ["view0", "view1", "view2", "view3"]
    points, labels, colors = merged_cloud(clouds, result, voxel=0.002)
    assert set(labels) == {0, 1, 2, 3} and colors is None
    assert len(points) < sum(map(len, clouds))  # the grid merges the overlapping views
    tints = [np.tile([k / 3, 0.5, 1 - k / 3], (len(c), 1)) for k, c in enumerate(clouds)]  # one colour per view
    whole = merged_cloud(clouds, result, colors=tints)
    assert np.allclose(whole.colors, np.column_stack([whole.scans / 3, np.full(len(whole.scans), 0.5), 1 - whole.scans / 3]))
    gridded = merged_cloud(clouds, result, voxel=0.002, colors=tints)
    assert np.allclose(gridded.points, points) and gridded.colors.shape == points.shape
    assert np.allclose(gridded.colors[:, 1], 0.5) and np.allclose(gridded.colors[:, 0] + gridded.colors[:, 2], 1.0)  # means of the views'
    assert merged_cloud(clouds, result, colors=tints[:3] + [None]).colors is None  # a view without colours: none


def test_views_of_rooms_alike_come_into_one_frame(model):
    # Walls, floor and ceiling are most of what each view sees, and they look alike from room to
    # room: without the feature match, the network's poses turned 28 and 120 degrees were trusted
    # and joined the views before the search could run.
    from benchmarks.indoor_rooms import pose_errors, views

    clouds, truth = views(12, pixels=64)
    result = multiway(clouds[1:6], model=model)
    assert all(result.joined)
    assert all(rotation < 2.0 and translation < 0.1 for rotation, translation in pose_errors(result.poses, truth[1:6]))  # degrees, metres


def test_initial_poses_start_the_pairs_and_keep_their_frame(scans):
    clouds, poses = scans
    rng = np.random.default_rng(5)
    world = random_transform(rng, max_angle=90.0, max_t=2.0)  # the frame the guesses come in
    guesses = [world @ rigid(euler_to_matrix(rng.uniform(-4, 4, 3)), rng.uniform(-0.003, 0.003, 3)) @ p for p in poses]
    wrong = AlwaysWrongModel(euler_to_matrix([180.0, 0.0, 0.0]))  # would turn every scan over
    config = MultiwayConfig(register=RegisterConfig(search=SearchConfig(mode="off")))
    result = multiway(clouds, config, model=wrong, init_poses=guesses)
    assert all(result.joined) and not wrong.batches  # ICP from the guesses was trusted on each pair
    assert np.allclose(result.poses[0], guesses[0])  # the world scan stays where its guess put it
    for k in range(1, 4):
        errors = pair_errors(np.linalg.inv(result.poses[0]) @ result.poses[k], poses[k])  # poses[0] is the identity
        assert errors.rotation_deg < 1.0 and errors.translation < 0.002  # metres: 1 degree, 2 mm


def test_initial_poses_must_be_rigid_and_one_per_scan(scans, model):
    clouds, _ = scans
    with pytest.raises(InputError, match="2 initial poses for 4 scans"):
        multiway(clouds, model=model, init_poses=[np.eye(4)] * 2)
    with pytest.raises(InputError, match="scan1: initial pose: not a rigid transform"):
        multiway(clouds, model=model, init_poses=[None, np.diag([2.0, 1.0, 1.0, 1.0]), None, None])


def test_poses_files(tmp_path):
    names = ["a/s0.ply", "a/s1.ply", "a/s2.ply"]
    T = rigid(euler_to_matrix([10.0, 0.0, 30.0]), [1.0, 2.0, 3.0])
    kitti = tmp_path / "poses.txt"
    kitti.write_text("# KITTI layout\n" + "\n".join(" ".join(map(str, P[:3].ravel())) for P in (np.eye(4), T, T)) + "\n")
    poses = read_poses(kitti, names)
    assert np.allclose(poses[0], np.eye(4)) and np.allclose(poses[2], T, atol=1e-12)
    # A poses.json from another folder: its scans are found by file name; a scan without a pose has none.
    record = {"scans": [{"name": "b/s1.ply", "world_T_scan": T.tolist()}, {"name": "b/s2.ply", "world_T_scan": None}]}
    (tmp_path / "poses.json").write_text(json.dumps(record))
    poses = read_poses(tmp_path / "poses.json", names)
    assert poses[0] is None and np.allclose(poses[1], T) and poses[2] is None
    bad = tmp_path / "bad.txt"
    for text, match in [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n", "1 poses for 3 scans"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n1 0 0 0 0 1 0 0 0 0 1 0\n", "bad.txt, line 2: 3 values; expected 12 or 16 per line"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 2 0\n1 0 0 0 0 1 0 0 0 0 1 0\n", "bad.txt, line 2: not a rigid transform"),
    ]:
        bad.write_text(text)
        with pytest.raises(InputError, match=match):
            read_poses(bad, names)
    (tmp_path / "other.json").write_text(json.dumps({"scans": [{"name": "c.ply", "world_T_scan": T.tolist()}]}))
    with pytest.raises(InputError, match="none of its scans with a pose is among the scans given"):
        read_poses(tmp_path / "other.json", names)
    # An exact name wins over a file name; a file name that fits two scans, or two entries for one
    # scan, is refused in words.
    record = {"scans": [{"name": "a/s0.ply", "world_T_scan": np.eye(4).tolist()}, {"name": "old/s0.ply", "world_T_scan": T.tolist()}]}
    (tmp_path / "exact.json").write_text(json.dumps(record))
    poses = read_poses(tmp_path / "exact.json", names + ["b/s0.ply"])
    assert np.allclose(poses[0], np.eye(4)) and np.allclose(poses[3], T)
    with pytest.raises(InputError, match=r"exact.json: scan 'a/s0.ply' matches 2 of the scans given by file name \(x/s0.ply, y/s0.ply\)"):
        read_poses(tmp_path / "exact.json", ["x/s0.ply", "y/s0.ply"])
    record["scans"].append({"name": "new/s0.ply", "world_T_scan": T.tolist()})
    (tmp_path / "twice.json").write_text(json.dumps(record))
    with pytest.raises(InputError, match="twice.json: scans 'old/s0.ply' and 'new/s0.ply' both give the pose of b/s0.ply"):
        read_poses(tmp_path / "twice.json", ["a/s0.ply", "b/s0.ply"])
    (tmp_path / "huge.json").write_text('{"scans": [{"name": "a/s1.ply", "world_T_scan": [[1' + "0" * 400 + "]]}]}")
    with pytest.raises(InputError, match="huge.json, scan 'a/s1.ply': world_T_scan is not a 4x4 array of numbers"):
        read_poses(tmp_path / "huge.json", names)
    # A last row a rounding off is read as exact, so that the pose passes multiway's stricter check.
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2 + "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1.0005\n")
    assert read_poses(kitti, names)[2][3].tolist() == [0.0, 0.0, 0.0, 1.0]


def test_poses_from_a_stanford_conf(tmp_path):
    """The Stanford 3D Scanning Repository's .conf (``bmesh NAME tx ty tz qx qy qz qw``): its scans
    are found by name, as a poses.json's, for odometry --gt and multiway --init."""
    from o3dsoft.scans import read_conf

    conf = tmp_path / "bun.conf"
    conf.write_text("camera 0 0 0 0 0 0 1\nbmesh s0.ply 0 0 0 0 0 0 1\nbmesh s2.ply 0.1 -0.2 0.3 0 0.3826834 0 0.9238795\n")
    poses = read_poses(conf, ["a/s0.ply", "a/s1.ply", "a/s2.ply"])
    assert np.allclose(poses[0], np.eye(4)) and poses[1] is None and np.array_equal(poses[2], read_conf(conf)["s2.ply"])
    # T_world_scan: the translation as written, the quaternion's rotation transposed (the repository's convention)
    assert np.allclose(poses[2][:3, 3], [0.1, -0.2, 0.3]) and np.allclose(poses[2][:3, :3] @ [0.0, 0.0, 1.0], [-np.sqrt(0.5), 0.0, np.sqrt(0.5)])
    assert read_poses(conf.rename(tmp_path / "BUN.CONF"), ["s2.ply"])[0] is not None
    with pytest.raises(InputError, match="BUN.CONF: none of its scans with a pose is among the scans given"):
        read_poses(tmp_path / "BUN.CONF", ["c.ply", "d.ply"])
    for text, match in [
        ("bmesh s0.ply 0 0 0 0 0 1\n", "line 1: expected 'bmesh NAME tx ty tz qx qy qz qw', got 8 fields"),
        ("bmesh s0.ply 0 0 x 0 0 0 1\n", "line 1: 'x' is not a number; expected 'bmesh NAME tx ty tz qx qy qz qw'"),
        ("camera 0 0 0 0 0 0 1\n", "no 'bmesh' lines; expected lines 'bmesh NAME tx ty tz qx qy qz qw'"),
    ]:
        conf.write_text(text)
        with pytest.raises(InputError, match=match):
            read_poses(conf, ["s0.ply"])
    conf.write_bytes(b"\xff\xfe\x00bmesh")
    with pytest.raises(InputError, match="bun.conf: not a text file"):
        read_poses(conf, ["s0.ply"])


def test_a_scan_that_overlaps_none_is_left_out(scans, model):
    clouds, _ = scans
    stray = blob(np.random.default_rng(1), 3000) * 0.05 + [5.0, 0.0, 0.0]
    result = multiway([clouds[0], stray, clouds[1]], MultiwayConfig(register=MultiwayConfig().register), model=model)
    assert result.joined == (True, False, True)
    assert result.poses[1] is None
    assert not any(e.used for e in result.edges if 1 in (e.source, e.target))


def test_scans_in_different_units_are_named_before_they_are_registered(tmp_path, scans):
    from o3dsoft.multiway import units_note

    clouds, _ = scans
    assert units_note(clouds[:2], ["a", "b"]) is None
    assert units_note([clouds[0], np.full((5, 3), np.nan), np.ones((4, 3))], ["a", "nan", "one point"]) is None  # refused later, by name
    note = units_note([clouds[0], clouds[1] * 1000.0], ["m.ply", "mm.ply"])
    assert note.startswith("mm.ply is ") and " times the size of m.ply" in note and 500 < float(note.split()[2]) < 2000
    a = write_points(tmp_path / "a.ply", clouds[0])
    mm = write_points(tmp_path / "mm.ply", clouds[1] * 1000.0)
    r = CliRunner().invoke(main, ["multiway", str(a), str(mm), "--out", str(tmp_path / "o"), "--search", "off", "--no-progress"])
    assert r.exit_code == 3 and "are the scans in the same units?" in r.output
    (tmp_path / "nan.xyz").write_text("nan nan nan\n" * 40)
    r = CliRunner().invoke(main, ["multiway", str(a), str(tmp_path / "nan.xyz"), "--out", str(tmp_path / "o2"), "--no-progress"])
    assert r.exit_code == 1 and "nan.xyz: 0 distinct finite points" in r.output and "IndexError" not in r.output


def test_the_merged_grid_is_the_finest_of_the_trusted_pairs():
    from types import SimpleNamespace

    from o3dsoft.multiway import _merge_grid

    def pair(voxel, failed):
        return SimpleNamespace(voxel=voxel, likely_failed=failed)

    # A scan of another scene, finer, joins none: its pairs' grid does not set the merged cloud's.
    assert _merge_grid(MultiwayConfig(), [pair(0.04, False), pair(0.002, True), pair(0.05, False)]) == 0.04
    assert _merge_grid(MultiwayConfig(), [pair(0.04, True), pair(0.002, True)]) == 0.002  # none trusted: every pair's
    assert _merge_grid(MultiwayConfig(), [pair(None, False), pair(0.002, True)]) is None
    assert _merge_grid(MultiwayConfig(voxel=0.01), [pair(0.04, False)]) == 0.01


def test_a_scan_that_overlaps_none_keeps_its_initial_pose(scans, model):
    clouds, poses = scans
    stray = blob(np.random.default_rng(1), 3000) * 0.05
    stray_guess = rigid(euler_to_matrix([0.0, 0.0, 30.0]), [5.0, 0.0, 0.0])  # 5 m from the views
    guesses = [poses[0], stray_guess, poses[1]]
    config = MultiwayConfig(register=RegisterConfig(search=SearchConfig(mode="off")))
    result = multiway([clouds[0], stray, clouds[1]], config, model=model, init_poses=guesses)
    assert result.placed_by == ("registration", "initial pose", "registration") and result.joined == (True, False, True)
    assert np.allclose(result.poses[1], stray_guess, atol=2e-3)  # the joined scans' corrections are near the identity
    labels = merged_cloud([clouds[0], stray, clouds[1]], result).scans
    assert set(labels) == {0, 2}  # unverified, so not merged
    assert json.loads(json.dumps(result.to_dict()))["scans"][1]["placed_by"] == "initial pose"


def test_a_group_apart_is_placed_by_the_initial_pose_nearest_a_joined_scan():
    points = [np.zeros((4, 3)) + [x, 0.0, 0.0] for x in (0.0, 10.0, 9.0, 3.0)]
    rng = np.random.default_rng(2)
    guesses = [random_transform(rng, 40.0, 0.5), random_transform(rng, 40.0, 0.5), None, random_transform(rng, 40.0, 0.5)]
    guesses[1][:3, 3] = [10.0, 0.0, 0.0]  # the guesses put scan 1 at 20 m, nearer scan 3 (at 3 m + 10) than scan 0
    guesses[3][:3, 3] = [10.0, 0.0, 0.0]
    poses = [random_transform(rng, 40.0, 0.5), None, None, random_transform(rng, 40.0, 0.5)]  # 0 and 3 joined
    k, pose = _anchor(points, poses, guesses, [1, 2])
    assert k == 1 and np.allclose(pose, poses[3] @ np.linalg.inv(guesses[3]) @ guesses[1])  # the correction at 3, carried to 1
    assert _anchor(points, poses, guesses, [2]) is None  # no guess in the group
    assert _anchor(points, [None, None, None, poses[3]], [None, guesses[1], None, None], [1]) is None  # no placed scan with a guess


def test_a_second_group_keeps_its_alignments_and_is_placed_by_its_initial_poses(scans, model):
    clouds, poses = scans
    rng = np.random.default_rng(4)
    shape = blob(rng, 4000) * 0.05
    apart = [shape[rng.random(len(shape)) < 0.6] + [5.0, 0.0, 0.0] for _ in range(2)]  # two views of another object, 5 m away
    moved = random_transform(rng, 20.0, 0.01)
    apart[1] = apply(np.linalg.inv(moved), apart[1] - [5.0, 0.0, 0.0]) + [5.0, 0.0, 0.0]  # world_T_scan = T(5 m) moved T(-5 m)
    truth = [poses[0], poses[1], np.eye(4), rigid(np.eye(3), [5.0, 0.0, 0.0]) @ moved @ rigid(np.eye(3), [-5.0, 0.0, 0.0])]
    off = rigid(euler_to_matrix([0.0, 0.0, 6.0]), [0.0, 0.0, 0.0])
    guesses = [truth[0], truth[1], truth[2], truth[3] @ off]  # the last guess 6 degrees off
    config = MultiwayConfig(register=RegisterConfig(search=SearchConfig(mode="off")))
    result = multiway([clouds[0], clouds[1], *apart], config, model=model, init_poses=guesses)
    assert result.placed_by == ("registration", "registration", "initial pose", "initial pose")
    relative = np.linalg.inv(result.poses[2]) @ result.poses[3]  # from the alignment of the two views, not the guess
    assert pair_errors(relative, np.linalg.inv(truth[2]) @ truth[3]).rotation_deg < 1.0
    assert any(e.in_tree for e in result.edges if {e.source, e.target} == {2, 3})


def test_bad_settings_and_too_few_scans(scans, model):
    with pytest.raises(InputError, match="at least two scans"):
        multiway(scans[0][:1], model=model)
    with pytest.raises(InputError, match="neighbours='nearest'"):
        multiway(scans[0], MultiwayConfig(neighbours="nearest"), model=model)
    with pytest.raises(InputError, match="register must be an o3dsoft.RegisterConfig, got 'x'"):
        multiway(scans[0], MultiwayConfig(register="x"), model=model)
    with pytest.raises(InputError, match="loop_closure_preference must be a finite number, at least 0, got nan"):
        multiway(scans[0], MultiwayConfig(loop_closure_preference=float("nan")), model=model)


def test_cli_writes_poses_and_the_merged_cloud(tmp_path, scans):
    clouds, poses = scans
    files = [write_points(tmp_path / f"view{k}.ply", c, colors=np.tile([k / 2, 0.2, 0.8], (len(c), 1))) for k, c in enumerate(clouds[:3])]
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(out), "--render", str(tmp_path / "merged.png"), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "3 scans" in result.output and "Picture:" in result.output
    assert "Time (s, lower is better): cleaning " in result.output
    record = json.loads((out / "poses.json").read_text())
    for k, scan in enumerate(record["scans"]):
        assert scan["joined"]
        assert pair_errors(np.array(scan["world_T_scan"]), poses[k]).rotation_deg < 1.0
    merged = o3d.io.read_point_cloud(str(out / "merged.ply"))  # the scans' colours, averaged on the grid
    assert len(merged.points) > 0 and merged.has_colors()
    assert np.allclose(np.asarray(merged.colors)[:, 1:], [0.2, 0.8], atol=1 / 255) and np.ptp(np.asarray(merged.colors)[:, 0]) > 0.9
    assert (tmp_path / "merged.png").stat().st_size > 0


def test_cli_starts_from_initial_poses(tmp_path, scans):
    clouds, poses = scans
    files = [write_points(tmp_path / f"view{k}.ply", c) for k, c in enumerate(clouds[:3])]
    world = rigid(euler_to_matrix([0.0, 0.0, 90.0]), [100.0, 50.0, 0.0])  # e.g. a site's frame
    guesses = tmp_path / "guesses.txt"
    guesses.write_text("\n".join(" ".join(f"{v:.9f}" for v in (world @ P)[:3].ravel()) for P in poses[:3]) + "\n")
    result = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(tmp_path / "out"), "--init", str(guesses), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert f"world frame: that of {guesses} ({files[0]} held at its pose there)" in result.output
    assert "points: every scan's, overlaps included; --merge-voxel thins them onto a grid)." in result.output  # small scans: no grid
    record = json.loads((tmp_path / "out" / "poses.json").read_text())
    for k, scan in enumerate(record["scans"]):
        assert pair_errors(np.array(scan["world_T_scan"]), world @ poses[k]).rotation_deg < 1.0
    record["scans"] = record["scans"][:2]  # an earlier run without the last view
    (tmp_path / "earlier.json").write_text(json.dumps(record))
    some = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(tmp_path / "o3"), "--init", str(tmp_path / "earlier.json"), "--no-progress"])
    assert some.exit_code == 0 and f"gives no initial pose for 1 scan(s), registered without one: {files[2]}" in some.output
    guesses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    short = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(tmp_path / "o2"), "--init", str(guesses)])
    assert short.exit_code == 1 and "guesses.txt: 1 poses for 3 scans" in short.output and "Traceback" not in short.output
    assert not (tmp_path / "o2").exists()
    # Scans in a shell glob's order (v10 before v2) against a text file's lines: said first.
    named = [tmp_path / n for n in ("v1.ply", "v10.ply", "v2.ply")]
    for src, dst in zip(files, named):
        dst.write_bytes(src.read_bytes())
    glob = CliRunner().invoke(main, ["multiway", *map(str, named), "--out", str(tmp_path / "o4"), "--init", str(guesses)])
    assert f"so {named[1]} comes before {named[2]}: {guesses}'s lines are read in the order the scans are given" in glob.output
    # A Stanford .conf names its scans: their order does not matter.
    from scipy.spatial.transform import Rotation

    conf = tmp_path / "scans.conf"
    lines = []
    for path, P in zip(named, poses[:3]):  # each line's quaternion is of the rotation's transpose
        lines.append(" ".join(["bmesh", path.name, *map(str, P[:3, 3]), *map(str, Rotation.from_matrix(P[:3, :3].T).as_quat())]))
    conf.write_text("\n".join(lines) + "\n")
    stanford = CliRunner().invoke(main, ["multiway", *map(str, named), "--out", str(tmp_path / "o5"), "--init", str(conf), "--no-progress"])
    assert stanford.exit_code == 0 and "comes before" not in stanford.output, stanford.output
    record = json.loads((tmp_path / "o5" / "poses.json").read_text())
    for k, scan in enumerate(record["scans"]):
        assert pair_errors(np.array(scan["world_T_scan"]), poses[k]).rotation_deg < 1.0


def test_cli_refuses_one_file_twice_and_reports_a_stray_scan(tmp_path, scans):
    clouds, _ = scans
    a = write_points(tmp_path / "a.ply", clouds[0])
    b = write_points(tmp_path / "b.ply", clouds[1])
    stray = write_points(tmp_path / "stray.ply", blob(np.random.default_rng(1), 3000) * 0.05 + [5.0, 0.0, 0.0])
    runner = CliRunner()
    twice = runner.invoke(main, ["multiway", str(a), str(b), str(a), "--out", str(tmp_path / "o1")])
    assert twice.exit_code == 2 and "given twice" in twice.output
    assert not (tmp_path / "o1").exists()
    (tmp_path / "o4").mkdir()
    merged = write_points(tmp_path / "o4" / "merged.ply", clouds[1])
    over = runner.invoke(main, ["multiway", str(a), str(merged), "--out", str(tmp_path / "o4")])
    assert over.exit_code == 2 and "merged.ply (--out's merged cloud): the same file as the scan" in over.output
    assert np.array_equal(read_points(merged), clouds[1])
    import laspy

    laspy.LasData(laspy.LasHeader(point_format=0, version="1.4")).write(tmp_path / "empty.las")
    empty = runner.invoke(main, ["multiway", str(a), str(tmp_path / "empty.las"), "--out", str(tmp_path / "o3")])
    assert empty.exit_code == 1 and "empty.las: holds 0 points" in empty.output
    assert not (tmp_path / "o3").exists()
    left = runner.invoke(main, ["multiway", str(a), str(stray), str(b), "--out", str(tmp_path / "o2"), "--no-progress"])
    assert left.exit_code == 3
    assert "stray.ply: not joined (no trusted alignment reaches" in left.output and "left out of the merged cloud: " in left.output
    assert json.loads((tmp_path / "o2" / "poses.json").read_text())["scans"][1]["joined"] is False
    # With initial poses the stray keeps its own, in poses.json only.
    clouds_poses = [scans[1][0], np.eye(4), scans[1][1]]
    (tmp_path / "init.txt").write_text("".join(" ".join(f"{x:.17g}" for x in p[:3].ravel()) + "\n" for p in clouds_poses))
    kept = runner.invoke(
        main, ["multiway", str(a), str(stray), str(b), "--out", str(tmp_path / "o5"), "--init", str(tmp_path / "init.txt"), "--search", "off", "--no-progress"]
    )
    assert kept.exit_code == 3 and "stray.ply placed by the initial poses in poses.json (unverified)" in kept.output
    record = json.loads((tmp_path / "o5" / "poses.json").read_text())["scans"][1]
    assert record["placed_by"] == "initial pose" and np.allclose(record["world_T_scan"], np.eye(4), atol=2e-3)


@pytest.mark.slow
def test_the_ten_bunny_scans_within_a_degree_and_two_millimetres(bunny_root, model):
    from o3dsoft.scans import read_conf

    conf = read_conf(bunny_root / "bun.conf")
    names = sorted(conf)
    clouds = [read_points(bunny_root / name) for name in names]
    t0 = time.perf_counter()
    result = multiway(clouds, names=names, model=model)
    seconds = time.perf_counter() - t0
    assert all(result.joined) and result.world == 0
    for name, pose in zip(names, result.poses):
        errors = pair_errors(pose, np.linalg.inv(conf[names[0]]) @ conf[name])
        assert errors.rotation_deg < 1.0 and errors.translation < 0.002, name
    print(f"ten bunny scans: {seconds:.1f} s")


def test_cli_takes_every_scan_of_an_e57(tmp_path, scans):
    import pye57

    clouds, poses = scans
    survey = pye57.E57(str(tmp_path / "survey.e57"), mode="w")
    shades = {0: (0, 0, 255), 1: (255, 0, 0), 2: (0, 255, 0)}  # a colour per scan
    for k in (1, 2):
        c = clouds[k]
        colour = {name: np.full(len(c), value, dtype=np.uint8) for name, value in zip(("colorRed", "colorGreen", "colorBlue"), shades[k])}
        survey.write_scan_raw({"cartesianX": c[:, 0], "cartesianY": c[:, 1], "cartesianZ": c[:, 2], **colour}, name=f"station {k}")
    survey.close()
    first = write_points(tmp_path / "view0.ply", clouds[0], colors=np.tile(np.array(shades[0]) / 255, (len(clouds[0]), 1)))
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["multiway", str(first), str(tmp_path / "survey.e57"), "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    record = json.loads((out / "poses.json").read_text())
    assert [s["name"] for s in record["scans"]] == [str(first), f"{tmp_path / 'survey.e57'}#0", f"{tmp_path / 'survey.e57'}#1"]
    for scan, pose in zip(record["scans"], poses[:3]):
        assert pair_errors(np.array(scan["world_T_scan"]), pose).rotation_deg < 1.0
    merged = o3d.io.read_point_cloud(str(out / "merged.ply"))
    assert {tuple(c) for c in np.round(np.asarray(merged.colors) * 255).astype(int)} == set(shades.values())  # each scan's own


def test_scans_that_join_none_leave_the_first_as_the_world(tmp_path, scans):
    rng = np.random.default_rng(0)
    a = write_points(tmp_path / "a.ply", scans[0][0])
    b = write_points(tmp_path / "b.ply", rng.uniform(size=(2000, 3)) * [3, 3, 0.1] + [10, 0, 0])
    result = CliRunner().invoke(main, ["multiway", str(a), str(b), "--out", str(tmp_path / "out"), "--no-progress"])
    assert result.exit_code == 3 and "Traceback" not in result.output
    assert "b.ply: not joined" in result.output
    assert len(read_points(tmp_path / "out" / "merged.ply")) <= len(scans[0][0])  # the first scan alone


def test_the_module_is_callable_as_its_function():
    # Importing o3dsoft.multiway (for MultiwayConfig) binds the package's name to the module.
    import o3dsoft.multiway as module

    assert o3dsoft.multiway is module or o3dsoft.multiway is module.multiway
    with pytest.raises(InputError, match="multiway needs at least two scans, got 1"):
        module([np.random.default_rng(0).random((50, 3))])


def _recording_register(calls):
    """A stand-in for register_cleaned that flags every pair and records (source, target, search
    mode, max_rotation, init given)."""
    from types import SimpleNamespace

    def fake(source, target, config, model=None, source_name="", target_name="", init=None):
        calls.append((source_name, target_name, config.search.mode, config.max_rotation, init is not None))
        return SimpleNamespace(
            transformation=np.eye(4), confidence=0.0, fitness=0.0, likely_failed=True, failure_reason="flagged", searched=False, voxel=None, tight_distance=0.01
        )

    return fake


def test_scans_left_apart_are_searched_nearest_in_the_sequence_first(monkeypatch):
    # The second pass stops searching a scan's pairs once one joins it; searched in index order,
    # a last scan's farthest pair came first and joined it 31 degrees off.
    import o3dsoft.multiway as mw

    calls = []
    monkeypatch.setattr(mw, "register_cleaned", _recording_register(calls))
    clouds = [blob(np.random.default_rng(k), 300) for k in range(4)]
    multiway(clouds, MultiwayConfig(neighbours="all"), names=["a", "b", "c", "d"], model=AlwaysWrongModel(np.eye(3)))
    assert [mode for _, _, mode, _, _ in calls[:6]] == ["quick"] * 6  # the first pass: the feature match on partial overlaps, no more
    searched = [(s, t) for s, t, mode, _, _ in calls if mode == "auto"]
    assert searched == [("b", "a"), ("c", "b"), ("d", "c"), ("c", "a"), ("d", "b"), ("d", "a")]


def test_pairs_from_initial_poses_are_held_near_the_turn_between_them(monkeypatch):
    import o3dsoft.multiway as mw

    clouds = [blob(np.random.default_rng(k), 300) for k in range(3)]
    for config, held in (
        (MultiwayConfig(), 45.0),  # odometry is seldom that far off
        (MultiwayConfig(register=replace(RegisterConfig(), max_rotation=10.0)), 10.0),  # the caller's own bound
        (MultiwayConfig(init_max_rotation=None), None),
    ):
        calls = []
        monkeypatch.setattr(mw, "register_cleaned", _recording_register(calls))
        multiway(clouds, config, model=AlwaysWrongModel(np.eye(3)), init_poses=[np.eye(4), np.eye(4), None])
        assert {(s, t): (bound, given) for s, t, _, bound, given in calls}[("scan1", "scan0")] == (held, True)
        assert all(bound == config.register.max_rotation for s, t, _, bound, given in calls if not given)  # no guess, no bound
    with pytest.raises(InputError, match="init_max_rotation must be in"):
        multiway(clouds, MultiwayConfig(init_max_rotation=0.0), model=AlwaysWrongModel(np.eye(3)))


def test_icp_options_set_multiways_icp(tmp_path, scans, monkeypatch):
    """--icp-distance, --icp-absolute and --icp-method set the ICP of every pair, as for register."""
    import o3dsoft.multiway as mw

    clouds, _ = scans
    files = [write_points(tmp_path / f"s{k}.ply", c) for k, c in enumerate(clouds[:2])]
    seen = []
    real = mw.multiway
    monkeypatch.setattr(mw, "multiway", lambda clouds, config, **kwargs: seen.append(config.register.icp) or real(clouds, config, **kwargs))
    args = ["multiway", *map(str, files), "--out", str(tmp_path / "o"), "--search", "off", "--no-progress", "--icp-distance", "0.3", "--icp-method", "plane"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code in (0, 3), r.output  # 3: a scan left unjoined
    assert [(c.distance, c.absolute, c.method) for c in seen] == [(0.3, False, "plane")]


def test_cli_warns_where_many_trusted_alignments_are_pruned(tmp_path, scans, monkeypatch):
    from dataclasses import replace

    import o3dsoft.multiway as multiway_module

    clouds, _ = scans
    files = [write_points(tmp_path / f"view{k}.ply", c) for k, c in enumerate(clouds[:3])]
    r = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(tmp_path / "a"), "--no-progress"])
    assert r.exit_code == 0 and "were pruned" not in r.output  # consistent views: none pruned
    real = multiway_module.multiway

    def all_pruned(*args, **kwargs):  # as on turntable views of a symmetric object
        result = real(*args, **kwargs)
        return replace(result, edges=tuple(replace(e, pruned=not e.likely_failed) for e in result.edges))

    monkeypatch.setattr(multiway_module, "multiway", all_pruned)
    r = CliRunner().invoke(main, ["multiway", *map(str, files), "--out", str(tmp_path / "b"), "--no-progress"])
    assert "trusted alignments disagreed with the others and were pruned: the scans' poses may be wrong" in r.output
    assert r.exit_code == 3 and (tmp_path / "b" / "poses.json").exists()  # written, and doubted as scans left out are


def test_each_scan_is_cleaned_once_and_every_one_before_the_first_pair(scans, model, monkeypatch):
    # Cleaning a dense scan costs as much as a pair's registration: once per scan, not once per pair it is in.
    import o3dsoft.multiway as mw
    import o3dsoft.pair as pair_module
    import o3dsoft.preprocess as preprocess

    clouds, _ = scans
    cleaned = []
    for module in (preprocess, pair_module, mw):
        real = module.clean_points
        monkeypatch.setattr(module, "clean_points", lambda points, name="cloud", *a, _real=real, **k: cleaned.append(name) or _real(points, name, *a, **k))
    result = multiway(clouds, MultiwayConfig(neighbours="all"), names=["a", "b", "c", "d"], model=model)
    assert sorted(cleaned) == ["a", "b", "c", "d"] and len(result.edges) == 6
    assert set(result.timings_s) == {"clean", "pairs", "optimise", "total"} and result.timings_s["clean"] <= result.timings_s["total"]
    # A bad scan late in the run fails by its name before any pair is registered.
    pairs = []
    monkeypatch.setattr(mw, "register_cleaned", lambda *a, **k: pairs.append(a[4:6]))
    line = np.linspace(0.0, 1.0, 200)[:, None] * [1.0, 2.0, 3.0]
    with pytest.raises(InputError, match="d: .*one line"):
        multiway([*clouds[:3], line], names=["a", "b", "c", "d"], model=model)
    assert pairs == []


def test_a_pair_of_cleaned_scans_registers_as_the_raw_pair(scans, model):
    from o3dsoft.pipeline import register, register_cleaned
    from o3dsoft.preprocess import clean_each

    clouds, _ = scans
    source = np.vstack([clouds[1], clouds[1][:50], np.full((3, 3), np.nan)])  # duplicates and NaN rows, cleaned out
    target = clouds[0]
    config = RegisterConfig()
    raw = register(source, target, config, model=model, source_name="s", target_name="t")
    cleaning = clean_each([source, target], ["s", "t"], model.config.k)
    assert cleaning[0].rows is not None and cleaning[1].rows is None  # only the source lost rows
    given = register_cleaned(cleaning[0].of(source), cleaning[1].of(target), config, model, "s", "t")
    assert np.allclose(given.transformation, raw.transformation, atol=1e-9)
    assert given.removed == raw.removed and given.removed["source_duplicates"] == 50 and given.removed["source_non_finite"] == 3
    assert given.confidence == pytest.approx(raw.confidence, abs=1e-9) and given.likely_failed == raw.likely_failed
    with pytest.raises(o3dsoft.UsageError, match="s: register_cleaned takes o3dsoft.preprocess.CleanReport clouds"):
        register_cleaned(cleaning[0], cleaning[1].of(target), config, model, "s", "t")  # the record, not the cleaned cloud
    few = cleaning[1].of(target)._replace(points=target[: model.config.k - 1])
    with pytest.raises(InputError, match=f"t: {model.config.k - 1} distinct finite points; at least {model.config.k} are needed"):
        register_cleaned(cleaning[0].of(source), few, config, model, "s", "t")
