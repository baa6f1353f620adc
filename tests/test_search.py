import numpy as np
import pytest

from o3dsoft.config import RestartConfig
from o3dsoft.metrics import pair_errors, rotation_error_deg
from o3dsoft.transforms import euler_to_matrix, rigid, rotation_angle_deg

from .conftest import apply, random_transform
from .fakes import bundled_scan_pair, moved_bunny


def test_local_starts_surround_the_given_pose():
    from o3dsoft.search import local_rotations

    R = local_rotations()
    assert R.shape == (15, 3, 3) and np.array_equal(R[0], np.eye(3))
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3)) and np.allclose(np.linalg.det(R), 1.0)
    assert all(rotation_error_deg(r, np.eye(3)) == pytest.approx(45.0) for r in R[1:])
    pairwise = [rotation_error_deg(R[i], R[j]) for i in range(15) for j in range(i)]
    assert min(pairwise) > 20.0  # 14 distinct axes


def test_feature_match_candidates_are_distinct_reproducible_and_find_a_large_rotation():
    from o3dsoft.baselines import GlobalConfig
    from o3dsoft.preprocess import normalisation_for
    from o3dsoft.search import FeatureMatch, FeatureMatchConfig

    DISTINCT_DEG = FeatureMatchConfig().distinct_deg

    src, tgt, T = bundled_scan_pair()
    turn = np.eye(4)
    turn[:3, :3] = euler_to_matrix([150.0, -40.0, 70.0])
    moved = apply(turn, src)  # T @ inv(turn) maps it onto the target: 150+ degrees from the given pose
    truth = T @ np.linalg.inv(turn)
    scale = normalisation_for(moved, tgt).scale
    # The tutorial's features (unoriented normals) match poorly across this turn: many distinct estimates.
    match = FeatureMatch(moved, tgt, scale, FeatureMatchConfig(features=GlobalConfig()))
    first = match.candidates(seed=0, count=8)
    assert 1 < len(first) <= 8 and first.shape[1:] == (4, 4)
    assert np.array_equal(first, match.candidates(seed=0, count=8))  # same seed, same estimates
    assert np.array_equal(first[:3], match.candidates(seed=0, count=3))  # a larger count extends a smaller one
    assert pair_errors(first[0], truth).rotation_deg < 10.0  # the best-supported is near the truth, before ICP
    # The search's own features match well: the best-supported estimate is close before ICP.
    assert pair_errors(FeatureMatch(moved, tgt, scale).candidates(seed=0, count=8)[0], truth).rotation_deg < 2.0
    for i in range(len(first)):
        for j in range(i):
            apart = rotation_error_deg(first[i][:3, :3], first[j][:3, :3]) >= DISTINCT_DEG
            assert apart or np.linalg.norm(first[i][:3, 3] - first[j][:3, 3]) >= 0.1 * scale
    assert len(match.candidates(seed=0, count=1)) == 1
    with pytest.raises(ValueError, match="count must be at least 1"):
        match.candidates(seed=0, count=0)


def test_oriented_normals_make_fpfh_independent_of_the_frame():
    from scipy.spatial import cKDTree

    from o3dsoft.baselines import GlobalConfig, fpfh_features

    # Golden-spiral points on an ellipsoid, about 0.1 apart: no two share a voxel of 0.01, so the
    # downsampled clouds are the points themselves, whatever the frame.
    i = np.arange(400) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / len(i)), np.pi * (1.0 + 5.0**0.5) * i
    points = np.stack([np.sin(polar) * np.cos(azimuth), 0.7 * np.sin(polar) * np.sin(azimuth), 0.4 * np.cos(polar)], axis=1)
    turn = np.eye(4)
    turn[:3, :3] = euler_to_matrix([150.0, -40.0, 70.0])
    turn[:3, 3] = [0.3, -0.2, 0.5]

    def features(config, cloud):
        described = fpfh_features(cloud, 1.0, config)
        return np.asarray(described.cloud.points), np.asarray(described.fpfh.data).T

    def largest_difference(orient):
        config = GlobalConfig(voxel=0.01, normal_radius=40.0, fpfh_radius=80.0, orient_normals=orient)
        (p, f), (q, g) = features(config, points), features(config, apply(turn, points))
        gap, match = cKDTree(apply(turn, p)).query(q)
        assert gap.max() < 1e-9  # the same points in both
        return np.abs(f[match] - g).max()

    assert largest_difference(orient=True) < 1e-6  # histogram bins in percent
    assert largest_difference(orient=False) > 1.0  # the signs Open3D gives follow the frame


def test_support_counts_the_matches_each_hypothesis_carries():
    from o3dsoft.search import _support
    from o3dsoft.transforms import random_rotation

    rng = np.random.default_rng(0)
    R = np.stack([random_rotation(rng) for _ in range(300)])
    t = rng.normal(size=(300, 3))
    a = rng.normal(size=(200, 3)) + [100.0, -50.0, 20.0]  # far from the origin
    b = a @ R[7].T + t[7] + rng.normal(scale=0.05, size=(200, 3))
    moved = np.einsum("hij,nj->hni", R, a) + t[:, None]
    brute = (np.linalg.norm(moved - b, axis=2) < 0.1).sum(axis=1)
    assert np.array_equal(_support(R, t, a, b, 0.1), brute) and brute[7] > 100


def test_refits_fit_each_hypothesis_on_its_own_inliers_in_one_batch():
    from o3dsoft.search import FeatureMatch
    from o3dsoft.transforms import random_rotation, rigid

    rng = np.random.default_rng(1)
    a = rng.normal(size=(300, 3)) + [50.0, 0.0, -20.0]
    R_true = random_rotation(rng)
    b = a @ R_true.T + [1.0, 2.0, 3.0] + rng.normal(scale=0.01, size=(300, 3))
    b[200:] = rng.normal(size=(100, 3))  # a third of the matches are wrong
    near = R_true @ euler_to_matrix([2.0, -1.0, 1.5])  # roughly right: carries the right matches
    far = random_rotation(rng)  # carries none
    R, t = np.stack([near, far]), np.stack([b[:200].mean(0) - a[:200].mean(0) @ near.T, [0.0, 0.0, 0.0]])
    fitted = FeatureMatch._refit(R, t, a, b, distance=0.5)
    # The first is the least-squares fit of its inliers alone (the 200 right matches), found
    # the usual way; the second has fewer than 3 inliers and comes back as it was.
    A, B = a[:200] - a[:200].mean(0), b[:200] - b[:200].mean(0)
    U, _, Vt = np.linalg.svd(B.T @ A)
    R_ls = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    assert np.allclose(fitted[0], rigid(R_ls, b[:200].mean(0) - R_ls @ a[:200].mean(0)), atol=1e-9)
    assert np.allclose(fitted[1], rigid(far, t[1]))


def test_poses_are_one_within_ten_degrees_and_a_tenth_of_the_scale_wherever_the_origin_lies():
    from o3dsoft.transforms import near_poses

    centre = np.array([1000.0, 2000.0, 0.0])  # e.g. map coordinates
    turns = np.stack([euler_to_matrix([0.0, 0.0, a]) for a in (0.0, 9.0, 11.0)])
    t = centre - turns @ centre  # each turns about the centre, which stays put
    moved = turns @ centre + t  # where each pose puts the centre: the centre itself
    assert np.allclose(moved, centre) and np.linalg.norm(t[2]) > 100.0  # though t is far from 0
    assert near_poses(turns, moved, np.eye(3), centre, 1.0, 10.0, 0.1).tolist() == [True, True, False]
    assert near_poses(turns[:1], moved[:1] + [0.0, 0.09, 0.0], np.eye(3), centre, 1.0, 10.0, 0.1)[0]
    assert not near_poses(turns[:1], moved[:1] + [0.0, 0.11, 0.0], np.eye(3), centre, 1.0, 10.0, 0.1)[0]


def test_the_feature_match_gives_the_same_candidates_with_or_without_its_distance_tables(monkeypatch, modelnet_root):
    from o3dsoft import search
    from o3dsoft.data import get_protocol, load_pairs
    from o3dsoft.preprocess import normalisation_for

    pair = load_pairs(modelnet_root, "test", get_protocol("rpmnet-crop"), 0)[0]  # a crop: many distinct estimates
    src, tgt = pair.source.astype(np.float64), pair.target.astype(np.float64)
    scale = normalisation_for(src, tgt).scale

    def indices_and_candidates():
        match = search.FeatureMatch(src, tgt, scale)
        return match.match_indices(), match.candidates(0, 20), max(len(p) for p in match.points())

    (ms, mt), candidates, largest = indices_and_candidates()
    assert largest <= search.TABLE_POINTS and len(candidates) > 1  # the tables are used
    monkeypatch.setattr(search, "TABLE_POINTS", 0)  # KD-trees and coordinates instead
    (ms_tree, mt_tree), candidates_tree, _ = indices_and_candidates()
    assert np.array_equal(ms, ms_tree) and np.array_equal(mt, mt_tree)
    assert np.array_equal(candidates, candidates_tree)


def test_feature_matches_vote_for_the_translation_at_a_given_rotation():
    from o3dsoft.preprocess import normalisation_for
    from o3dsoft.search import FeatureMatch

    src, tgt, T = moved_bunny(3)
    matcher = FeatureMatch(src, tgt, normalisation_for(src, tgt).scale)
    voted = matcher.translations(T[:3, :3], 3)
    assert 1 <= len(voted) <= 3 and np.allclose(voted[:, :3, :3], T[:3, :3])
    assert np.linalg.norm(voted[0, :3, 3] - T[:3, 3]) < matcher.inlier_distance  # the most votes: the right one
    with pytest.raises(ValueError, match="count"):
        matcher.translations(T[:3, :3], 0)


def test_half_turns_about_a_clouds_axes():
    from o3dsoft.search import half_turns

    rng = np.random.default_rng(6)
    T = random_transform(rng, 180.0, 0.0)
    box = apply(T, rng.uniform(-1, 1, size=(4000, 3)) * np.array([3.0, 2.0, 1.0]))
    turns = half_turns(box)
    assert turns.shape == (3, 3, 3)
    for F, axis in zip(turns, T[:3, :3].T):  # the box's long, middle and short axes, turned
        assert np.allclose(F @ F.T, np.eye(3)) and np.isclose(np.linalg.det(F), 1.0)
        assert rotation_angle_deg(F) == pytest.approx(180.0)
        assert np.allclose(F @ axis, axis, atol=0.05)  # about that axis


def test_distinct_starts_keep_the_first_of_each_pose():
    from o3dsoft.strategies.restart import distinct_starts
    from o3dsoft.verify import Attempt

    RESTART_DISTINCT_DEG, RESTART_DISTINCT_SHIFT = RestartConfig().distinct_deg, RestartConfig().distinct_shift

    rng = np.random.default_rng(7)
    centre, scale = np.array([5.0, -2.0, 1.0]), 2.0
    base = random_transform(rng, 180.0, 1.0)
    turn = rigid(euler_to_matrix([0.5 * RESTART_DISTINCT_DEG, 0.0, 0.0]), np.zeros(3))
    about_centre = rigid(np.eye(3), centre) @ turn @ rigid(np.eye(3), -centre)  # the centre stays put
    shifted = rigid(np.eye(3), np.array([0.0, 0.0, 2.0 * RESTART_DISTINCT_SHIFT * scale])) @ base
    turned_far = base @ rigid(euler_to_matrix([2.0 * RESTART_DISTINCT_DEG, 0.0, 0.0]), np.zeros(3))
    starts = [base, base @ about_centre, shifted, turned_far, shifted]
    attempts = [Attempt(0.0, None, None, S, S) for S in starts]
    kept = distinct_starts(attempts, centre, scale, RESTART_DISTINCT_DEG, RESTART_DISTINCT_SHIFT)
    assert [id(a.start) for a in kept] == [id(base), id(shifted), id(turned_far)]
