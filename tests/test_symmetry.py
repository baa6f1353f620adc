import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import o3dsoft
from o3dsoft import refine, symmetry
from o3dsoft.errors import InputError
from o3dsoft.metrics import pair_errors
from o3dsoft.transforms import apply_transform, rotation_angle_deg

from .conftest import random_transform
from .test_degeneracy import box_surface


def _icp(source, target, distance=0.1):
    return lambda T: refine.icp(source, target, T, distance).transformation


def _with_a_handle(rng, n):
    """A box with a bar along one edge: no half turn maps it onto itself."""
    box = box_surface(rng, n)
    bar = np.c_[rng.uniform(-1, 1, n // 4), rng.uniform(-0.05, 0.05, n // 4) + 0.75, rng.uniform(-0.05, 0.05, n // 4) + 0.3]
    return np.r_[box, bar]


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_half_turns_turn_the_moved_source_half_a_turn_about_its_centroid(seed):
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(50, 3)) * [3.0, 2.0, 1.0]
    T = random_transform(rng, 180.0, 2.0)
    centre = apply_transform(T, source).mean(axis=0)
    poses = symmetry.half_turns(source, T)
    assert len(poses) == 3
    for P in poses:
        assert np.allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(P[:3, :3]) > 0
        assert rotation_angle_deg(P[:3, :3] @ T[:3, :3].T) == pytest.approx(180.0, abs=1e-4)
        assert np.allclose(apply_transform(P, source).mean(axis=0), centre, atol=1e-9)


def test_a_box_fits_as_closely_half_turned_and_a_box_with_a_handle_does_not():
    rng = np.random.default_rng(0)
    T = random_transform(rng)
    for make, ambiguous in ((box_surface, True), (_with_a_handle, False)):
        source, target = make(rng, 1500), apply_transform(T, make(rng, 1500))  # two samplings, no shared point
        found = symmetry.probe(source, target, T, _icp(source, target))
        assert found.ambiguous == ambiguous, found.fit
        if ambiguous:
            assert found.fit <= 1.1 and found.away_deg > 170 and pair_errors(found.copy, T).rotation_deg > 170
        else:
            assert found.fit > 2.0


def test_copies_outside_the_rotation_prior_are_not_counted():
    rng = np.random.default_rng(1)
    source, target = box_surface(rng, 1500), box_surface(rng, 1500)
    found = symmetry.probe(source, target, np.eye(4), _icp(source, target), admissible=lambda T: rotation_angle_deg(T[:3, :3]) <= 45)
    assert found == symmetry.NOT_PROBED


def test_a_trusted_copy_of_a_symmetric_shape_is_flagged_with_its_other_pose(modelnet_root):
    from o3dsoft.data import get_protocol, load_pairs

    pairs = load_pairs(modelnet_root, "test", get_protocol("incongruent"), 0)
    vase = pairs[11]  # two halves of a vase's points: the result is turned about the vase's axis
    result = o3dsoft.register(vase.source, vase.target)
    assert pair_errors(result.transformation, vase.transform).rotation_deg > 10
    assert result.likely_failed and "a copy of the result turned" in result.failure_reason and result.copy_fit <= 1.1
    assert result.copy_transformation.shape == (4, 4) and rotation_angle_deg(result.copy_transformation[:3, :3] @ result.transformation[:3, :3].T) > 20
    unprobed = o3dsoft.register(vase.source, vase.target, o3dsoft.RegisterConfig(symmetry=symmetry.SymmetryConfig(enabled=False)))
    assert np.allclose(unprobed.transformation, result.transformation) and not unprobed.likely_failed
    assert result.confidence == pytest.approx(unprobed.confidence / 2) and unprobed.copy_fit is None

    airplane = pairs[10]
    result = o3dsoft.register(airplane.source, airplane.target)
    assert pair_errors(result.transformation, airplane.transform).rotation_deg < 2 and not result.likely_failed
    assert result.copy_fit > 2.0


def test_the_symmetry_settings_are_checked():
    rng = np.random.default_rng(0)
    source = box_surface(rng, 300)
    for bad in ({"max_ratio": 0.9}, {"min_away_deg": -1.0}, {"min_away_deg": 200.0}, {"closed_from": 0.0}, {"closed_from": 1.5}):
        with pytest.raises(InputError, match="symmetry"):
            o3dsoft.register(source, source, o3dsoft.RegisterConfig(symmetry=symmetry.SymmetryConfig(**bad)))


def _even(points, voxel):
    return o3dsoft.preprocess.voxel_downsample(points, voxel)


def test_a_closed_surface_meets_itself_along_its_normals_and_a_view_or_an_open_box_does_not():
    rng = np.random.default_rng(2)
    box = _even(box_surface(rng, 30_000), 0.04)
    seen = box[(box >= np.array([1.0, 0.6, 0.3]) - 1e-9).any(axis=1)]  # the three faces a camera on (1, 1, 1) sees
    open_box = box[box[:, 2] < 0.3 - 1e-9]  # no lid
    shares = {name: symmetry.closed_share(c, refine.normals(c, 10)) for name, c in (("box", box), ("seen", seen), ("open", open_box))}
    assert shares["box"] >= 0.95 and shares["seen"] < 0.1 and shares["open"] < 0.9, shares


def test_two_dense_samplings_of_a_box_are_probed_and_an_unsymmetric_shape_stays_trusted():
    """Dense clouds are scans (no complete-shape confidence), and on a grid the cells' centroids of
    two samplings of a box lie as close at a half turn as at the truth (they look like shared
    points): the probe runs because both are closed surfaces."""
    rng = np.random.default_rng(3)
    T = random_transform(rng, 60.0, 0.5)
    with_a_block = lambda rng, n: np.r_[box_surface(rng, n), box_surface(rng, n // 5, (0.25, 0.2, 0.15)) + [0.6, 0.3, 0.45]]  # noqa: E731 - on the lid, off centre
    for make, ambiguous in ((box_surface, True), (with_a_block, False)):
        source, target = make(rng, 8_000), apply_transform(T, make(rng, 8_000))
        result = o3dsoft.register(source, target)
        assert result.copy_transformation is not None, result.failure_reason
        assert result.likely_failed == ambiguous, (result.confidence, result.failure_reason)
        if not ambiguous:
            assert pair_errors(result.transformation, T).rotation_deg < 2
