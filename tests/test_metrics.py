import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from o3dsoft.metrics import input_chamfer_distance, modified_chamfer_distance, pair_errors, rotation_error_deg, summarise
from o3dsoft.transforms import euler_to_matrix, matrix_to_euler_deg, nearest_rigid, random_rotation, rigid

from .conftest import apply, blob


@settings(max_examples=50, deadline=None)
@given(st.floats(-89, 89), st.floats(-89, 89), st.floats(-179, 179))
def test_euler_round_trip(a, b, c):
    assert np.allclose(matrix_to_euler_deg(euler_to_matrix(np.array([a, b, c]))), [a, b, c], atol=1e-6)


@pytest.mark.parametrize("angle", [1e-4, 0.01, 1.0, 30.0, 179.0])
def test_rotation_error_exact_angle(angle):
    R = euler_to_matrix(np.array([0.0, 0.0, angle]))
    assert rotation_error_deg(R, np.eye(3)) == pytest.approx(angle, rel=1e-6)


def test_rotation_error_resolves_tiny_angles_in_float32():
    R = euler_to_matrix(np.array([0.0, 0.0, 0.005])).astype(np.float32)
    assert rotation_error_deg(R, np.eye(3, dtype=np.float32)) == pytest.approx(0.005, rel=1e-2)


def test_pair_errors_values():
    T_gt = np.eye(4)
    T_est = np.eye(4)
    T_est[:3, :3] = euler_to_matrix(np.array([0.0, 2.0, 0.0]))
    T_est[:3, 3] = [0.03, -0.04, 0.0]
    e = pair_errors(T_est, T_gt)
    assert e.rotation_deg == pytest.approx(2.0)
    assert e.translation == pytest.approx(0.05)
    assert e.translation_l1 == pytest.approx(0.07)
    assert np.allclose(e.euler_abs_deg, [0, 2, 0])
    assert e.rotation_l2 == pytest.approx(np.linalg.norm(T_est[:3, :3] - np.eye(3)))
    s = summarise([e, pair_errors(T_gt, T_gt)])
    assert s["recall_1deg"] == 0.5 and s["recall_5deg"] == 0.5
    assert s["euler_rmse_deg"] == pytest.approx(math.sqrt(4 / 6))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1.0, 1e7))
def test_translation_errors_about_an_origin_do_not_depend_on_the_frame(seed, far):
    # The same two alignments of clouds far from their frame's origin, seen in a frame at the
    # clouds: errors about that origin equal the errors the clouds' own frame gives.
    rng = np.random.default_rng(seed)
    T_gt, T_est = np.eye(4), np.eye(4)
    T_gt[:3, :3], T_est[:3, :3] = random_rotation(rng), random_rotation(rng)
    T_gt[:3, 3], T_est[:3, 3] = rng.normal(size=3), rng.normal(size=3)
    origin = far * rng.normal(size=3) / np.sqrt(3)
    S = np.eye(4)
    S[:3, 3] = origin  # clouds around `origin`: each transform seen from the frame it was given in
    near = pair_errors(T_est, T_gt)
    moved = pair_errors(S @ T_est @ np.linalg.inv(S), S @ T_gt @ np.linalg.inv(S), origin)
    assert moved.rotation_deg == pytest.approx(near.rotation_deg, abs=1e-9)
    assert np.allclose(moved.translation_abs, near.translation_abs, atol=1e-9 * far)
    assert pair_errors(T_est, T_gt, np.zeros(3)).translation == near.translation  # no origin: the errors as before, to the bit


def test_chamfer_zero_at_ground_truth_and_grows():
    rng = np.random.default_rng(0)
    src = blob(rng, 200)
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    tgt = apply(T, src)
    assert modified_chamfer_distance(src, tgt, T, T) == pytest.approx(0.0, abs=1e-12)
    T_off = T.copy()
    T_off[:3, 3] += 0.1
    assert modified_chamfer_distance(src, tgt, T_off, T) > 0.005


def _box_surface(rng, n, size=(2.0, 1.0, 0.5)):
    """(n, 3) points drawn uniformly on the faces of a centred box (a shape with three half-turn symmetries)."""
    half = np.asarray(size) / 2
    p = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
    return p


def test_input_chamfer_sees_only_the_inputs_a_half_turn_of_a_box_fits_as_the_truth():
    rng = np.random.default_rng(1)
    src, other = _box_surface(rng, 600), _box_surface(rng, 600)  # two independent samplings
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), (0.3, -0.2, 0.1)
    tgt = apply(T, other)
    truth = input_chamfer_distance(src, tgt, T)
    half_turn = T @ np.diag([-1.0, -1.0, 1.0, 1.0])  # about the box's z axis
    quarter_turn = T.copy()
    quarter_turn[:3, :3] = T[:3, :3] @ euler_to_matrix([90.0, 0.0, 0.0])
    assert 0 < truth < 0.01  # independent samplings: about a squared point spacing, not 0
    assert input_chamfer_distance(src, tgt, half_turn) == pytest.approx(truth, rel=0.25)
    assert input_chamfer_distance(src, tgt, quarter_turn) > 5 * truth
    assert input_chamfer_distance(src, apply(T, src), T) == pytest.approx(0.0, abs=1e-20)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_input_chamfer_is_the_same_seen_from_either_cloud(seed):
    rng = np.random.default_rng(seed)
    src, tgt = blob(rng, 80), blob(rng, 50) + rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(size=3)
    assert input_chamfer_distance(tgt, src, np.linalg.inv(T)) == pytest.approx(input_chamfer_distance(src, tgt, T), rel=1e-9)


def test_pair_errors_refuse_what_is_no_rigid_transform():
    from o3dsoft.errors import InputError

    with pytest.raises(InputError, match=r"T_gt: expected a \(4, 4\) transform, got shape \(3, 3\)"):
        pair_errors(np.eye(4), np.eye(3))
    with pytest.raises(InputError, match=r"T_est: expected a \(4, 4\) transform"):
        pair_errors(np.eye(3), np.eye(4), origin=np.array([1.0, 2.0, 3.0]))
    with pytest.raises(InputError, match="T_est: not a rigid transform"):
        pair_errors(np.diag([2.0, 2.0, 2.0, 1.0]), np.eye(4))  # a scaled matrix read 75.5 degrees off
    with pytest.raises(InputError, match="T_est: not a rigid transform"):
        pair_errors(np.diag([1.0, 1.0, -1.0, 1.0]), np.eye(4))  # a reflection
    failed = pair_errors(np.full((4, 4), np.nan), np.eye(4))  # a method that failed still counts as a failure
    assert failed.rotation_deg == 180.0 or np.isnan(failed.rotation_deg)


def test_euler_errors_do_not_flip_across_the_gimbal_lock():
    # A turn of 0.1 degree about y across b = 90 degrees: the angles' formula returns the other
    # triple, (180, 89.95, 180), which read 180 degrees off in x and z.
    truth, estimate = euler_to_matrix(np.array([0.0, 89.95, 0.0])), euler_to_matrix(np.array([0.0, 90.05, 0.0]))
    assert abs(abs(matrix_to_euler_deg(estimate)[0]) - 180.0) < 1e-6  # the flipped triple
    T_gt, T_est = np.eye(4), np.eye(4)
    T_gt[:3, :3], T_est[:3, :3] = truth, estimate
    assert np.allclose(pair_errors(T_est, T_gt).euler_abs_deg, [0.0, 0.1, 0.0], atol=1e-6)


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 1e-5))
def test_nearest_rigid_is_a_rotation_within_the_perturbation(seed, eps):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    t = rng.normal(size=3)
    E = eps * rng.normal(size=(3, 3))
    c = 1e6 * rng.normal(size=3)  # far from the origin, as georeferenced scans are
    T = nearest_rigid(rigid(R + E, t), c)
    off = np.abs((R + E) @ (R + E).T - np.eye(3)).max()
    assert np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() < (1e-14 if off > 1e-9 else 1e-9) and np.linalg.det(T[:3, :3]) > 0
    if off <= 1e-9:  # rigid to float64 products' precision: as it was
        assert np.array_equal(T[:3, :3], R + E)
    # no rotation is nearer the perturbed matrix than the projection, so it is within 2 |E| of R
    assert np.linalg.norm(T[:3, :3] - R) <= 2 * np.linalg.norm(E) + 1e-14 and np.array_equal(T[3], [0, 0, 0, 1])
    assert np.allclose(T[:3, :3] @ c + T[:3, 3], (R + E) @ c + t, rtol=0, atol=1e-9)  # the centre goes where it went
