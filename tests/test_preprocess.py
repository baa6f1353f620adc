import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from o3dsoft.errors import InputError
from o3dsoft.preprocess import (
    clean_points,
    denormalise_transform,
    normalisation_for,
    normalise_pair,
    normalise_transform,
    same_profile_pvalue,
    sample_points,
)

from .conftest import apply, blob, random_transform


def test_clean_drops_non_finite_and_duplicates_in_order():
    pts = np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, np.inf], [0, 0, 1]], float)
    rep = clean_points(pts)
    assert rep.non_finite == 2 and rep.duplicates == 1
    assert np.array_equal(rep.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


@pytest.mark.parametrize(
    "pts,match",
    [
        (np.zeros((50, 3)), "1 distinct finite points"),
        (np.ones((50, 3)) * [1, 2, 3], "1 distinct finite points"),
        (np.outer(np.arange(50.0), [1, 2, 3]), "lie on one line"),
        (np.full((50, 3), np.nan), "0 distinct finite points"),
        (np.zeros((50, 2)), r"shape \(N, 3\)"),
    ],
)
def test_degenerate_clouds_rejected(pts, match):
    with pytest.raises(InputError, match=match):
        clean_points(pts, "cloud.ply", min_points=2)


def test_too_few_points_named():
    with pytest.raises(InputError, match="src.ply: 10 distinct finite points; at least 32 are needed"):
        clean_points(blob(np.random.default_rng(0), 10), "src.ply", min_points=32)


def test_sample_points_deterministic_subset():
    pts = blob(np.random.default_rng(0), 500)
    a = sample_points(pts, 100, seed=3)
    assert a.shape == (100, 3)
    assert np.array_equal(a, sample_points(pts, 100, seed=3))
    assert len({tuple(p) for p in a}) == 100  # no repeats
    assert sample_points(pts[:50], 100).shape == (50, 3)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1e-3, 1e3))
def test_normalisation_round_trip(seed, units):
    rng = np.random.default_rng(seed)
    src = blob(rng, 64) * units + rng.uniform(-5, 5, 3) * units
    T = random_transform(rng)
    T[:3, 3] *= units
    tgt = apply(T, src)
    s, t, norm = normalise_pair(src, tgt)
    assert max(np.linalg.norm(s, axis=1).max(), np.linalg.norm(t, axis=1).max()) == pytest.approx(1.0)
    T_norm = normalise_transform(T, norm)
    assert np.allclose(apply(T_norm, s), t, atol=1e-9)  # the same motion, in the normalised frame
    assert np.allclose(denormalise_transform(T_norm, norm), T, atol=1e-9 * max(1, units))


def test_normalisation_uses_both_clouds():
    a = blob(np.random.default_rng(0), 50)
    n = normalisation_for(a, a * 3)
    assert n.scale == pytest.approx(3 * np.linalg.norm(a - a.mean(0), axis=1).max())


def test_profiles_tell_a_partial_overlap_from_two_samplings_of_one_shape():
    rng = np.random.default_rng(4)
    shape = blob(rng, 4000)
    a, b = shape[:1000], shape[1000:2000]  # two samplings of one shape
    moved = apply(random_transform(rng, 180.0, 5.0), b)
    assert same_profile_pvalue(a, moved) > 0.01
    assert same_profile_pvalue(a, moved) == pytest.approx(same_profile_pvalue(a, b), abs=1e-9)  # rigid motions change nothing
    part = shape[2000:][shape[2000:, 0] < np.quantile(shape[2000:, 0], 0.7)]  # 70 % of another sampling, cut by a plane
    assert same_profile_pvalue(a, part) < 0.01
