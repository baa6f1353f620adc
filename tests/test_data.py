from dataclasses import replace

import numpy as np
import pytest

from o3dsoft.data import PROTOCOLS, get_protocol, load_modelnet40, load_pairs, make_pair, resolve_data_root
from o3dsoft.errors import InputError, UsageError
from o3dsoft.metrics import rotation_error_deg

from .conftest import apply, blob, tetra_off


@pytest.fixture
def shape():
    return blob(np.random.default_rng(0), 1024).astype(np.float32)


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_pairs_follow_their_protocol(shape, name):
    p = get_protocol(name)
    pair = make_pair(shape, p, seed=7, index=3)
    again = make_pair(shape, p, seed=7, index=3)
    assert np.array_equal(pair.source, again.source) and np.array_equal(pair.target, again.target)
    other = make_pair(shape, p, seed=7, index=4)
    assert not np.array_equal(pair.transform, other.transform)
    if p.disjoint_share >= 1:
        n_source = int(round(p.source_share * len(shape)))
        n_source, n_target = (int(round(p.crop_keep * n)) for n in (n_source, len(shape) - n_source))
    else:
        n_source = n_target = p.num_points or len(shape)
    if p.view_deg is None:
        assert pair.source.shape == (n_source, 3) and pair.target.shape == (n_target, 3)
    elif p.num_points is not None:  # each view resampled to one size
        assert pair.source.shape == pair.target.shape == (p.num_points, 3)
    else:  # what each camera sees: a part of each half
        assert 32 <= len(pair.source) < n_source and 32 <= len(pair.target) < n_target
    R, t = pair.transform[:3, :3], pair.transform[:3, 3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
    assert (np.abs(t) <= p.translation).all()
    if p.rotation == "euler":
        assert pair.angle <= np.sqrt(3) * max(abs(p.angle_min), abs(p.angle_max)) + 1e-6
    if p.noise_std == 0 and p.crop_keep == 1 and p.disjoint_share == 0:
        # Same points, shuffled: each target point is a transformed source point, order differs.
        moved = apply(pair.transform, pair.source.astype(np.float64))
        assert not np.allclose(moved, pair.target, atol=1e-4)
        assert np.allclose(np.sort(moved, axis=0), np.sort(pair.target, axis=0), atol=1e-4)


def test_crop_keeps_seventy_percent_and_noise_is_clipped(shape):
    pair = make_pair(shape, get_protocol("rpmnet-crop"), seed=0, index=0)
    assert pair.source.shape == (717, 3)
    nearest_dist = np.min(np.linalg.norm(pair.source[:, None] - shape[None], axis=2), axis=1)
    assert nearest_dist.max() <= 0.05 * np.sqrt(3) + 1e-6  # noise is clipped to +-0.05 per axis
    assert nearest_dist.mean() > 0.005  # and there is noise


def test_mixed_protocol_degrades_about_its_share_of_pairs(shape):
    p = get_protocol("wide45-partial")
    degraded = 0
    for i in range(60):
        pair = make_pair(shape, p, seed=0, index=i)
        assert pair.source.shape == pair.target.shape == (717, 3)
        nearest = np.min(np.linalg.norm(pair.source[:, None] - shape[None], axis=2), axis=1)
        if nearest.max() > 0:  # noisy, hence degraded; clean pairs are exact points of the shape
            degraded += 1
            assert nearest.mean() > 0.005
    assert 18 <= degraded <= 42  # Binomial(60, 0.5): outside this range with probability < 0.002


def test_protocol_rotation_ranges(shape):
    angles = [make_pair(shape, get_protocol("paper"), 0, i).transform for i in range(200)]
    max_err = max(rotation_error_deg(T[:3, :3], np.eye(3)) for T in angles)
    assert max_err < 22.5 * np.sqrt(3)
    so3 = [rotation_error_deg(make_pair(shape, get_protocol("so3"), 0, i).transform[:3, :3], np.eye(3)) for i in range(200)]
    assert max(so3) > 120  # uniform on SO(3) reaches large angles


def test_unknown_protocol_lists_valid():
    with pytest.raises(UsageError, match="unknown protocol 'nope'; valid: paper, dcp"):
        get_protocol("nope")


def test_modelnet_splits_and_categories(modelnet_root):
    test = load_modelnet40(modelnet_root, "test")
    assert test.points.shape == (2468, 1024, 3)
    assert len(test.categories) == 40 and test.categories[0] == "airplane"
    assert len(test.names) == 2468 and test.names[2] == "airplane/airplane_0631.ply"
    unseen = load_modelnet40(modelnet_root, "test", "unseen")
    assert (unseen.labels >= 20).all() and 0 < len(unseen.labels) < 2468
    pairs = load_pairs(str(modelnet_root), "test", get_protocol("dcp-unseen"))
    assert (pairs.shapes.labels >= 20).all()
    train_pairs = load_pairs(str(modelnet_root), "train", get_protocol("dcp-unseen"))
    assert (train_pairs.shapes.labels < 20).all()


def test_missing_data_says_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.delenv("O3DSOFT_DATA", raising=False)
    with pytest.raises(UsageError, match="O3DSOFT_DATA"):
        resolve_data_root(None)
    with pytest.raises(UsageError, match="no such folder"):
        resolve_data_root(str(tmp_path / "nope"))
    (tmp_path / "shape_names.txt").write_text("a\n")
    with pytest.raises(UsageError, match="shape_names.txt: not a folder"):
        resolve_data_root(str(tmp_path / "shape_names.txt"))
    with pytest.raises(UsageError, match="nope: no such folder.* pass its folder with --extra-data PATH"):
        resolve_data_root(str(tmp_path / "nope"), "--extra-data")
    with pytest.raises(InputError, match="no ModelNet40 test split here"):
        load_modelnet40(tmp_path, "test")


def test_wrong_h5_keys(tmp_path):
    import h5py

    (tmp_path / "shape_names.txt").write_text("a\nb\n")
    with h5py.File(tmp_path / "ply_data_test0.h5", "w") as f:
        f["points"] = np.zeros((2, 10, 3))
    with pytest.raises(InputError, match="expected datasets 'data' and 'label'"):
        load_modelnet40(tmp_path, "test")


def _write_h5(folder, split, data, labels, names=("a", "b")):
    import h5py

    (folder / "shape_names.txt").write_text("\n".join(names) + "\n")
    with h5py.File(folder / f"ply_data_{split}0.h5", "w") as f:
        f["data"] = data
        f["label"] = labels.reshape(-1, 1)


def test_official_2048_layout_takes_the_first_1024_points(tmp_path):
    data = np.random.default_rng(0).normal(size=(3, 2048, 3)).astype(np.float32)
    _write_h5(tmp_path, "test", data, np.array([0, 1, 1]))
    shapes = load_modelnet40(tmp_path, "test")
    assert shapes.points.shape == (3, 1024, 3)
    np.testing.assert_array_equal(shapes.points, data[:, :1024])
    assert load_modelnet40(tmp_path, "test", points_per_shape=None).points.shape == (3, 2048, 3)
    with pytest.raises(InputError, match="2048 points, fewer than the 4096 asked for"):
        load_modelnet40(tmp_path, "test", points_per_shape=4096)


def test_off_folder_is_sampled_on_faces_and_normalised(tmp_path):
    for category, header in (("cone", "OFF\n4 4 0\n"), ("box", "OFF4 4 0\n")):  # the second: ModelNet's malformed header
        for split in ("train", "test"):
            folder = tmp_path / category / split
            folder.mkdir(parents=True)
            for i in range(2):
                (folder / f"{category}_{i:04d}.off").write_text(tetra_off(i, header))
    shapes = load_modelnet40(tmp_path, "test", points_per_shape=64)
    assert shapes.points.shape == (4, 64, 3)
    assert shapes.categories == ["box", "cone"] and list(shapes.labels) == [0, 0, 1, 1]
    assert shapes.names[0] == "box/test/box_0000.off"
    np.testing.assert_allclose(shapes.points.mean(axis=1), 0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(shapes.points, axis=2).max(axis=1), 1, atol=1e-6)
    again = load_modelnet40(tmp_path, "test", points_per_shape=64)
    np.testing.assert_array_equal(shapes.points, again.points)
    (tmp_path / "box" / "test" / "box_0001.off").write_text("OFF\n3 1 0\n0 0 0\n1 0\n")
    with pytest.raises(InputError, match="box_0001.off"):
        load_modelnet40(tmp_path, "test", points_per_shape=64)


@pytest.mark.parametrize("name", [n for n, p in sorted(PROTOCOLS.items()) if p.disjoint_share >= 1])
def test_independently_sampled_protocols_share_no_point(shape, name):
    p = get_protocol(name)
    pair = make_pair(shape, p, seed=3, index=5)
    back = apply(np.linalg.inv(pair.transform), pair.target.astype(np.float64))
    gap = np.min(np.linalg.norm(pair.source[:, None].astype(np.float64) - back[None], axis=2), axis=1)
    spacing = np.sort(np.linalg.norm(shape[:, None] - shape[None], axis=2), axis=1)[:, 1]
    assert gap.min() > 0  # not one point in both clouds
    if p.noise_std == 0 and p.crop_keep == 1:
        # Two disjoint halves that together make up the shape, each in random order.
        both = np.concatenate([pair.source, back]).astype(np.float64)
        assert np.allclose(np.sort(both, axis=0), np.sort(shape.astype(np.float64), axis=0), atol=1e-5)
        assert np.median(gap) < 3 * np.median(spacing)  # yet samples of the same surface


def test_a_camera_sees_the_side_of_a_sphere_that_faces_it():
    from o3dsoft.data import seen_from

    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    camera = np.array([0.0, 0.0, 3.0])
    seen = seen_from(sphere, camera)
    # Nothing of the far side (the horizon seen from 3 radii is at z = 1/3; the operator keeps some
    # grazing points just beyond it).
    assert (seen[:, 2] > 0.1).all()
    facing = sphere[sphere[:, 2] > 0.5]  # well inside the horizon
    assert len(seen) >= 0.9 * len(facing)
    assert {tuple(q) for q in seen} <= {tuple(q) for q in sphere}  # points of the cloud, none made up


def test_views_are_two_cameras_parts_of_the_disjoint_halves(shape):
    p = get_protocol("incongruent-view")
    pair = make_pair(shape, p, seed=3, index=5)
    whole = make_pair(shape, replace(p, view_deg=None, noise_std=0.0), seed=3, index=5)
    back = apply(np.linalg.inv(pair.transform), pair.target.astype(np.float64))
    assert len(pair.source) < len(whole.source) and len(pair.target) < len(whole.target)
    # Different parts: the source's nearest target points leave some of it without a partner.
    gap = np.min(np.linalg.norm(pair.source[:, None].astype(np.float64) - back[None], axis=2), axis=1)
    assert gap.min() > 0 and np.median(gap) < np.max(gap) / 2


def test_the_literatures_protocols_share_every_point(shape):
    for name in ("paper", "dcp", "so3"):
        pair = make_pair(shape, get_protocol(name), seed=3, index=5)
        back = apply(np.linalg.inv(pair.transform), pair.target.astype(np.float64))
        assert np.allclose(np.sort(back, axis=0), np.sort(pair.source, axis=0), atol=1e-5)


def test_mixture_parts_and_evaluation_protocol():
    from o3dsoft.data import MIXTURES, check_training_recipe, evaluation_protocol, training_parts

    for name, mixture in MIXTURES.items():
        parts = training_parts(name)
        assert abs(sum(w for _, w in parts) - 1) < 1e-9
        assert any(p.disjoint_share > 0 for p, _ in parts)
        if name != "incongruent-overlap-mix":  # for an overlap head trained alone: the rest of the network keeps what it learnt
            assert any(p.disjoint_share == 0 for p, _ in parts)
        assert evaluation_protocol(name).name == mixture.evaluate
    assert training_parts("dcp") == ((get_protocol("dcp"), 1.0),)
    with pytest.raises(UsageError, match="incongruent-mix"):
        check_training_recipe("nonsense")
