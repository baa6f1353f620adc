import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from o3dsoft.errors import InputError
from o3dsoft.preprocess import (
    clean_points,
    data_grid,
    denormalise_transform,
    flat_normal,
    isolated_points,
    normalisation_for,
    normalise_pair,
    normalise_transform,
    point_spacing,
    principal_extents,
    same_profile_pvalue,
    sample_points,
    scene_size,
)

from .conftest import apply, blob, random_transform


def test_isolated_points_have_fewer_than_two_others_within_the_radius():
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), [0.0]), axis=-1).reshape(-1, 3)  # a plane, spacing 1
    lone = np.array([[5.0, 5.0, 10.0], [30.0, 0.0, 0.0], [0.0, 0.0, -3.5]])  # 10, 10 and 3.5 from the plane
    pair = np.array([[50.0, 50.0, 50.0], [51.0, 50.0, 50.0]])  # two outliers side by side: one other each
    three = np.array([[0.0, 50.0, 50.0], [1.0, 50.0, 50.0], [2.0, 50.0, 50.0]])  # two others each: a thin structure
    isolated = isolated_points(np.vstack([grid, lone, pair, three]), 3.0)
    assert not isolated[: len(grid)].any() and isolated[len(grid) : len(grid) + 5].all() and not isolated[-3:].any()
    for radius in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="radius must be positive"):
            isolated_points(grid, radius)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 400), st.floats(0.02, 0.5))
def test_isolated_points_are_those_open3d_radius_outlier_removal_drops(seed, n, radius):
    from o3dsoft.refine import to_open3d

    rng = np.random.default_rng(seed)
    points = np.vstack([rng.uniform(0.0, 1.0, (n, 3)), rng.uniform(0.0, 1.0, (2, 3)) * [1.0, 1.0, 0.0]])
    _, kept = to_open3d(points).remove_radius_outlier(nb_points=2, radius=radius)
    expected = np.ones(len(points), dtype=bool)
    expected[np.asarray(kept, dtype=np.int64)] = False
    assert np.array_equal(isolated_points(points, radius), expected)


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


def test_the_cleaned_points_are_a_copy_of_the_callers():
    # Where nothing is dropped, nothing is indexed either: the copy is made on purpose.
    cloud = _surface(np.random.default_rng(1), 500)
    rep = clean_points(cloud)
    assert np.array_equal(rep.points, cloud) and not np.may_share_memory(rep.points, cloud)
    assert np.array_equal(rep.rows, np.arange(500))


def test_stray_far_points_are_dropped_and_counted():
    # A sensor's glitch at 1e12 made a surface look like a line (its spread is all along the
    # glitch) and overflowed the voxel grids; points at a few times the cloud's reach stay.
    rng = np.random.default_rng(2)
    cloud = _surface(rng, 2_000)
    rep = clean_points(cloud)
    assert rep.strays == 0 and np.array_equal(rep.points, cloud)  # nothing stray: the cloud as given
    far = np.vstack([cloud[:1000], [[1e12, -1e12, 5e11]], cloud[1000:], [[3.0, 3.0, 3.0]], [[-2e9, 0.0, 0.0]]])
    rep = clean_points(far, "scan.ply")
    assert rep.strays == 2 and np.array_equal(rep.points, np.vstack([cloud, [[3.0, 3.0, 3.0]]]))
    with pytest.raises(InputError, match="scan.ply: all points lie on one line"):  # two strays hid it
        clean_points(np.vstack([np.outer(np.arange(500.0), [1, 2, 3]), [[1e12, 0, 0], [0, 1e12, 0]]]), "scan.ply", min_points=2)


def test_glitches_up_to_a_tenth_of_the_cloud_are_strays_and_garbage_is_refused():
    rng = np.random.default_rng(3)
    cloud = _surface(rng, 2_000)
    glitches = rng.normal(size=(100, 3)) * 1e12  # 5 % of the cloud
    rep = clean_points(np.vstack([cloud, glitches]), "scan.ply")
    assert rep.strays == 100 and np.array_equal(rep.points, cloud)
    garbage = rng.normal(size=(600, 3)) * 1e200  # 30 %: the cloud itself cannot be told apart
    with pytest.raises(InputError, match=r"scan.ply: a coordinate of .*e\+200 remains after dropping 0 strays; .* is the file damaged\?"):
        clean_points(np.vstack([cloud, garbage]), "scan.ply")


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.6), st.sampled_from([1e3, 1e12, 1e100, 1e200, 1e308]))
def test_a_cloud_with_glitches_of_any_size_is_cleaned_or_refused_in_words(seed, share, size):
    # A cut or damaged file leaves values of any size in a cloud; cleaning must not fail otherwise.
    from o3dsoft.preprocess import MAX_COORDINATE

    rng = np.random.default_rng(seed)
    cloud = _surface(rng, 300)
    bad = rng.random(len(cloud)) < share
    with np.errstate(over="ignore"):  # 1e308 times a normal draw: some become inf, as garbage may
        cloud[bad] = rng.normal(size=(int(bad.sum()), 3)) * size
    try:
        rep = clean_points(cloud, "scan.ply")
    except InputError:
        return
    assert np.abs(rep.points).max() <= MAX_COORDINATE and len(rep.points) >= 1


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2_100, 6_000), st.floats(0.3, 3.0))
def test_the_grid_test_on_a_subset_decides_as_the_whole_cloud(seed, n, factor):
    # A point's nearest neighbour in a subset is never nearer: the shortcut may only say yes
    # where the whole cloud would.
    from o3dsoft.preprocess import point_spacing, spaced_closer_than

    cloud = _surface(np.random.default_rng(seed), n)
    spacing = point_spacing(cloud)
    for threshold in (spacing * factor, spacing, np.nextafter(spacing, np.inf)):
        assert spaced_closer_than(cloud, threshold, subset=50) == (spacing < threshold)
        assert spaced_closer_than(cloud, threshold, subset=n // 2) == (spacing < threshold)


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


def _surface(rng, n, radii=(1.0, 0.6, 0.3)):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * radii


def test_dense_scans_get_a_grid_of_their_own_size_and_sparse_clouds_none():
    rng = np.random.default_rng(0)
    dense, sparse = _surface(rng, 40_000), _surface(rng, 1_024)
    assert data_grid(dense, dense[::2], 0.01) == pytest.approx(0.01 * scene_size(dense), rel=0.02)
    assert data_grid(sparse, sparse, 0.01) is None  # ModelNet40-like: every point kept
    assert data_grid(dense, dense, 0.0) is None
    # A grid only where a cloud is denser than half of it.
    middle = _surface(rng, 12_000)
    assert point_spacing(middle) < 0.5 * 0.01 * scene_size(middle) < point_spacing(middle) * 2
    assert data_grid(middle, middle, 0.01) == pytest.approx(0.01 * scene_size(middle))
    assert data_grid(middle, middle, 0.005) is None


@settings(max_examples=15, deadline=None)
@given(st.floats(1e-3, 1e3), st.integers(0, 2**16))
def test_the_grid_follows_the_units(units, seed):
    rng = np.random.default_rng(seed)
    cloud = _surface(rng, 40_000)
    assert data_grid(units * cloud, units * cloud, 0.01) == pytest.approx(units * data_grid(cloud, cloud, 0.01))


def test_a_stray_far_point_does_not_change_the_scene_size():
    rng = np.random.default_rng(1)
    cloud = _surface(rng, 5_000)
    assert scene_size(np.vstack([cloud, [[1000.0, 0.0, 0.0]]])) == pytest.approx(scene_size(cloud), rel=0.01)


def _with_ghosts(cloud, share, rng):
    """`cloud` and a `share` of its count of ghost returns 60-600 times its size out, above it."""
    n = max(1, int(share * len(cloud)))
    away = rng.normal(size=(n, 3))
    away[:, 2] = np.abs(away[:, 2])
    away *= rng.uniform(60, 600, (n, 1)) * scene_size(cloud) / np.linalg.norm(away, axis=1, keepdims=True)
    return np.vstack([cloud, np.median(cloud, axis=0) + away])


@pytest.mark.parametrize("share", [0.002, 0.02])
def test_ghost_returns_far_out_change_neither_the_scale_nor_the_grid(share):
    """A few points hundreds of sizes out (sky returns, multipath) moved the centroid and tripled
    the scale that every distance of the pipeline follows; past 1 % they coarsened the grid."""
    rng = np.random.default_rng(4)
    source, target = _surface(rng, 20_000), _surface(rng, 20_000)
    ghosted = _with_ghosts(source, share, rng), _with_ghosts(target, share, rng)
    clean, noisy = normalisation_for(source, target), normalisation_for(*ghosted)
    assert noisy.scale == pytest.approx(clean.scale, rel=1e-9)
    assert np.allclose(noisy.source_centroid, clean.source_centroid) and np.allclose(noisy.target_centroid, clean.target_centroid)
    assert data_grid(*ghosted, 0.01) == pytest.approx(data_grid(source, target, 0.01), rel=1e-9)
    assert principal_extents(ghosted[0])[0] == pytest.approx(principal_extents(source)[0], rel=0.02)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 200), st.integers(0, 2**32 - 1))
def test_first_of_each_row_equals_a_byte_exact_unique(n, seed):
    from o3dsoft.preprocess import first_of_each_row

    rng = np.random.default_rng(seed)
    values = np.array([0.0, -0.0, 1.0, -1.5, 1e-300, 2.0**60])  # few values: many repeated rows
    pts = values[rng.integers(0, len(values), size=(n, 3))]
    expected = np.sort(np.unique(pts.view(np.dtype((np.void, 24))).ravel(), return_index=True)[1])
    np.testing.assert_array_equal(first_of_each_row(pts), expected)


def test_distinct_points_read_from_float32_get_distinct_hashes():
    """Their float64 bytes end in 29 zero bits; the hash must not keep only the rest."""
    from o3dsoft.preprocess import _row_hashes

    rng = np.random.default_rng(0)
    pts = np.unique(rng.uniform(-50, 50, (1_000_000, 3)).astype(np.float32), axis=0).astype(np.float64)
    hashes = _row_hashes(np.ascontiguousarray(pts).view(np.uint64).reshape(-1, 3))
    assert len(np.unique(hashes)) == len(pts)


def test_first_of_each_row_falls_back_on_a_hash_collision(monkeypatch):
    from o3dsoft import preprocess

    pts = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    # Every row hashed alike: the rows' bytes decide.
    monkeypatch.setattr(preprocess, "_row_hashes", lambda rows: np.zeros(len(rows), dtype=np.uint64))
    np.testing.assert_array_equal(preprocess.first_of_each_row(pts), [0, 1])
    np.testing.assert_array_equal(preprocess.first_of_each_row(pts[:2]), [0, 1])  # two rows, one hash, both kept


def _pipe(rng, n=20_000, length=100.0, radius=0.05):
    """Points on a thin cylinder along a random direction: a pipe or a power line."""
    a, along = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, length, n)
    local = np.c_[along, radius * np.cos(a), radius * np.sin(a)]
    from scipy.spatial.transform import Rotation

    return local @ Rotation.random(random_state=3).as_matrix().T


def test_a_thin_structure_keeps_its_cross_section_on_the_grid():
    pipe = _pipe(np.random.default_rng(0))
    sides, axes = principal_extents(pipe)
    assert sides[0] == pytest.approx(98.0, rel=0.01) and sides[1] == pytest.approx(0.1, rel=0.02) and sides[2] == pytest.approx(0.1, rel=0.02)
    assert abs(axes[:, 0] @ (pipe[-1] - pipe[0])) == pytest.approx(np.linalg.norm(pipe[-1] - pipe[0]), rel=0.01)  # the pipe's axis
    # 1 % of its 98-unit length would be a 1-unit grid, ten times its diameter: a line of ~100 points.
    assert data_grid(pipe, pipe, 0.01) is None  # 1 / 10 of its diameter: finer than its 4 cm spacing, so no grid
    dense = _pipe(np.random.default_rng(1), n=60_000, length=10.0)  # spaced 3 mm: on 1 % of its length, 0.1
    assert data_grid(dense, dense, 0.01) == pytest.approx(0.01, rel=0.03)


def test_a_flat_cloud_is_told_from_a_thin_one():
    rng = np.random.default_rng(2)
    flat = np.c_[rng.uniform(0, 8, (500, 2)), np.zeros(500)]
    assert abs(flat_normal(flat) @ [0, 0, 1]) == pytest.approx(1.0)
    assert flat_normal(flat + [0.0, 0.0, 1e6]) is not None  # far from the origin, still flat
    assert flat_normal(np.c_[flat[:, :2], rng.normal(0, 1e-3, 500)]) is None  # a 1 mm thick sheet is a 3D cloud
