import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from o3dsoft.procrustes import _RotationFromCovariance, rotation_from_covariance, weighted_procrustes
from o3dsoft.transforms import random_rotation


def _random_problem(seed, b=4, n=50):
    rng = np.random.default_rng(seed)
    R = np.stack([random_rotation(rng) for _ in range(b)])
    t = rng.uniform(-1, 1, size=(b, 3))
    p = rng.normal(size=(b, n, 3))
    q = np.einsum("bij,bnj->bni", R, p) + t[:, None]
    return [torch.as_tensor(a, dtype=torch.float64) for a in (p, q, R, t)]


def test_recovers_known_transform_to_1e6():
    p, q, R, t = _random_problem(0)
    res = weighted_procrustes(p, q)
    assert torch.allclose(res.R, R, atol=1e-6)
    assert torch.allclose(res.t, t, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_property_recovery_and_proper_rotation(seed):
    p, q, R, t = _random_problem(seed, b=2, n=10)
    res = weighted_procrustes(p, q)
    assert torch.allclose(res.R, R, atol=1e-6)
    assert torch.allclose(res.t, t, atol=1e-6)
    det = torch.det(res.R)
    assert torch.allclose(det, torch.ones_like(det), atol=1e-9)


def test_weights_ignore_outliers():
    p, q, R, t = _random_problem(1, b=1, n=40)
    q_bad = q.clone()
    q_bad[:, :10] += 5.0  # ten wrong partners...
    w = torch.ones(1, 40, dtype=torch.float64)
    w[:, :10] = 0.0  # ...with zero weight
    res = weighted_procrustes(p, q_bad, w)
    assert torch.allclose(res.R, R, atol=1e-6)
    assert torch.allclose(res.t, t, atol=1e-6)
    unweighted = weighted_procrustes(p, q_bad)
    assert not torch.allclose(unweighted.R, R, atol=1e-3)


def test_reflection_is_fixed():
    # Planar points mirrored: the best orthogonal map is a reflection; we must return a rotation.
    rng = np.random.default_rng(2)
    p = rng.normal(size=(1, 30, 3)) * np.array([1.0, 1.0, 0.0])
    q = p * np.array([1.0, 1.0, -1.0])
    res = weighted_procrustes(torch.as_tensor(p), torch.as_tensor(q))
    assert torch.det(res.R).item() == pytest.approx(1.0, abs=1e-9)


def test_gradient_matches_finite_differences_including_reflections():
    torch.manual_seed(0)
    H = torch.randn(30, 3, 3, dtype=torch.float64, requires_grad=True)
    assert (torch.det(H) < 0).any()
    assert torch.autograd.gradcheck(_RotationFromCovariance.apply, (H,))


@pytest.mark.parametrize(
    "points",
    [
        torch.zeros(1, 5, 3),  # all identical
        torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]]),  # collinear
    ],
)
def test_degenerate_input_gives_no_nan(points):
    p = points.clone().requires_grad_(True)
    w = torch.ones(1, p.shape[1], requires_grad=True)
    res = weighted_procrustes(p, p.detach() * 2.0 + 1.0, w)
    (res.R.sum() + res.t.sum()).backward()
    for x in (res.R, res.t, p.grad, w.grad):
        assert torch.isfinite(x).all()


def test_all_zero_weights_gives_no_nan():
    p, q, _, _ = _random_problem(3, b=2, n=8)
    p.requires_grad_(True)
    w = torch.zeros(2, 8, dtype=torch.float64, requires_grad=True)
    res = weighted_procrustes(p, q, w)
    (res.R.sum() + res.t.sum()).backward()
    assert all(torch.isfinite(x).all() for x in (res.R, res.t, p.grad, w.grad))


def test_symmetric_shape_repeated_singular_values_gradients_finite():
    # A regular square: two equal singular values, where torch.linalg.svd's backward is inf/NaN.
    p = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]], dtype=torch.float64, requires_grad=True)
    res = weighted_procrustes(p, p.detach())
    res.R.sum().backward()
    assert torch.isfinite(p.grad).all()


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        weighted_procrustes(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="shape of p"):
        weighted_procrustes(torch.zeros(1, 4, 3), torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match="w must have shape"):
        weighted_procrustes(torch.zeros(1, 4, 3), torch.zeros(1, 4, 3), torch.zeros(1, 5))


def test_scripted_rotation_equals_eager():
    scripted = torch.jit.script(rotation_from_covariance)
    H = torch.randn(10, 3, 3)
    assert torch.equal(scripted(H), rotation_from_covariance(H))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.booleans())
def test_rigid_fit_equals_the_batched_fit(seed, mirrored):
    from o3dsoft.procrustes import rigid_fit

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(40, 3))
    q = p @ random_rotation(rng).T + rng.normal(size=3) + 0.01 * rng.normal(size=(40, 3))
    if mirrored:  # the best orthogonal fit is a reflection: both must return a rotation
        q[:, 0] *= -1.0
    R, t = rigid_fit(p, q)
    expected = weighted_procrustes(torch.from_numpy(p)[None], torch.from_numpy(q)[None])
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R, expected.R[0].numpy(), atol=1e-9)
    np.testing.assert_allclose(t, expected.t[0].numpy(), atol=1e-9)
