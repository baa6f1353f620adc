"""Pre-processing stages: clean, sample, normalise (and map a transform back).

All functions take and return NumPy arrays of shape (N, 3); transforms are (4, 4) float64 with
the convention p_target = T @ p_source (T_target_source).
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from scipy.stats import ks_2samp

from .errors import InputError, counted
from .transforms import rigid


class CleanReport(NamedTuple):
    """What :func:`clean_points` removed: non-finite rows, exact duplicates and strays."""

    points: np.ndarray  # (N', 3) float64
    non_finite: int
    duplicates: int
    strays: int = 0
    rows: Optional[np.ndarray] = None  # (N',) where each kept point was in the input


# A point farther from its cloud's median than this many times the cloud's reach (twice the distance
# within which 90 % of its points lie, so that up to a tenth of them may be glitches) is a stray (a
# sensor's glitch at 1e12): dropped. Such points overflow the voxel grids' integer cells (Open3D
# refuses the grid) and are no part of any scene.
STRAY_REACH = 1000.0
STRAY_PERCENTILE = 90.0  # the reach is twice the distance from the median within which this % of points lie
# The largest coordinate accepted once strays are dropped (cloud units): no scan measures farther in
# any unit (float64 steps are 1e-4 there), and squares of larger ones overflow. Beyond it, the file
# holds garbage (a damaged file, or values of another type).
MAX_COORDINATE = 1e12


def _float32_note(points: np.ndarray, duplicates: int) -> str:
    """Where duplicates left too few (K, 3) points, every coordinate is a float32 value, the
    points lie over 10,000 units from the origin and span under 1,000 of float32's steps there
    (far from the origin float32 merges nearby points): how coarse float32 is there; else ""."""
    if not duplicates or len(points) == 0 or not np.array_equal(points.astype(np.float32), points):
        return ""
    largest = float(np.abs(points).max())
    step = float(np.spacing(np.float32(largest)))
    if largest < 1e4 or float(np.ptp(points, axis=0).max()) > 1000 * step:
        return ""
    return f"; if these coordinates went through float32, its step at {largest:.3g} is {step:.3g}, which merges closer points: keep them in float64"


def clean_points(points: np.ndarray, name: str = "cloud", min_points: int = 1) -> CleanReport:
    """Drop rows with NaN/inf, exact duplicate points and strays (:data:`STRAY_REACH`); reject
    degenerate clouds and coordinates beyond :data:`MAX_COORDINATE`.

    Args:
        points: (N, 3) array.
        name: how to call the cloud in error messages (e.g. its file name).
        min_points: fewest distinct finite points accepted.
    Returns:
        CleanReport with the kept (N', 3) float64 points, in their original order.
    Raises:
        InputError: wrong shape, fewer than ``min_points`` points left, a coordinate beyond
            :data:`MAX_COORDINATE`, all points identical, or all points on one line.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{name}: expected points of shape (N, 3), got {pts.shape}")
    pts = pts.astype(np.float64, copy=False)
    finite = np.isfinite(pts).all(axis=1)
    non_finite = int((~finite).sum())
    rows = np.arange(len(pts))
    if non_finite:  # copies only where rows go (120 MB per 5 million points)
        pts, rows = pts[finite], rows[finite]
    keep = first_of_each_row(pts)
    duplicates = len(pts) - len(keep)
    if duplicates:
        pts, rows = pts[keep], rows[keep]
    if np.may_share_memory(pts, points):  # the caller's array is never changed, nor handed on
        pts = pts.copy()
    stray = stray_points(pts)
    strays = int(stray.sum())
    if strays:
        pts, rows = pts[~stray], rows[~stray]
    if len(pts) < min_points:
        removed = f"{non_finite} rows with NaN/inf, {duplicates} duplicates" + (f" and {strays} strays" if strays else "")
        detail = f" ({removed} removed)" if non_finite or duplicates or strays else ""
        raise InputError(f"{name}: {len(pts)} distinct finite points{detail}; at least {min_points} are needed{_float32_note(pts, duplicates)}")
    largest = float(np.abs(pts).max())
    if largest > MAX_COORDINATE:
        raise InputError(
            f"{name}: a coordinate of {largest:.6e} remains after dropping {strays} strays; no scan measures that far (coordinates up to {MAX_COORDINATE:.0e} units are taken): is the file damaged?"
        )
    check_spread(pts, name)
    return CleanReport(pts, non_finite, duplicates, strays, rows)


class Cleaning(NamedTuple):
    """What :func:`clean_points` keeps of a cloud, without a copy of its points: the rows kept
    (None: every row) and how many it removed of each kind. For callers that register one cloud
    many times (odometry, multiway): each cloud is cleaned once."""

    rows: Optional[np.ndarray]
    non_finite: int
    duplicates: int
    strays: int

    def of(self, points: np.ndarray) -> CleanReport:
        """The cleaned cloud of the (N, 3) `points` cleaning saw."""
        return CleanReport(points if self.rows is None else points[self.rows], self.non_finite, self.duplicates, self.strays)


def clean_each(clouds: Sequence[np.ndarray], names: Sequence[str], min_points: int) -> List[Cleaning]:
    """:func:`clean_points` of each (N_i, 3) cloud, kept as a :class:`Cleaning`: every cloud is
    checked to hold `min_points` distinct finite points and not to be degenerate, so that a bad
    cloud late in a long run fails before the first is registered.

    Raises:
        InputError: the first cloud that fails, by its name.
    """
    cleaning = []
    for points, name in zip(clouds, names, strict=True):
        report = clean_points(points, str(name), min_points=min_points)
        every = report.rows is None or len(report.rows) == len(points)  # then they are the rows in order
        cleaning.append(Cleaning(None if every else report.rows, report.non_finite, report.duplicates, report.strays))
    return cleaning


def stray_points(points: np.ndarray) -> np.ndarray:
    """(N,) bool: the (N, 3) points farther from their median than :data:`STRAY_REACH` times the
    cloud's reach (none where the reach is 0)."""
    beyond = _beyond_reach(points, STRAY_REACH)
    return np.zeros(len(points), dtype=bool) if beyond is None else beyond


def _beyond_reach(points: np.ndarray, reaches: float) -> Optional[np.ndarray]:
    """(N,) bool: the (N, 3) points farther from their median than `reaches` times the cloud's
    reach (twice the distance from the median within which :data:`STRAY_PERCENTILE` % of them
    lie); None where none can be: fewer than two points, a reach of 0, or a cloud whose box lies
    within that distance (most clouds: no per-point distance is taken)."""
    if len(points) < 2:
        return None
    with np.errstate(all="ignore"):  # coordinates near the float limit: distances of inf
        _, centre, distances = _about_median(points)
        reach = 2.0 * np.percentile(distances, STRAY_PERCENTILE)
        if not 0 < reach < np.inf:
            return None
        # No point is farther from the centre than sqrt(3) times its largest coordinate offset
        # (whole-array extremes: 10 times as fast as per axis).
        farthest = max(float(points.max()) - float(centre.min()), float(centre.max()) - float(points.min()))
        if np.sqrt(3.0) * farthest <= reaches * reach:
            return None
        return np.linalg.norm(points - centre, axis=1) > reaches * reach


def first_of_each_row(points: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of each distinct row of an (N, 3) float64 array, ascending:
    (N',). Rows are compared by their bytes (so -0.0 and 0.0 differ, as they do in a file).

    Each row is hashed to one 64-bit integer, and those are sorted (1.6 times as fast as sorting
    the rows' bytes on 40,000 points, 2.5 times on 10^6); where no two hashes are alike every row
    is kept, else rows that share a hash are checked for equality, and if any differ the rows'
    bytes are sorted after all."""
    rows = np.ascontiguousarray(points, dtype=np.float64).view(np.uint64).reshape(-1, 3)
    hashed = _row_hashes(rows)
    ordered = np.sort(hashed)
    if not (ordered[1:] == ordered[:-1]).any():  # no two hashes alike, so no two rows alike (most scans)
        return np.arange(len(rows))
    order = np.argsort(hashed, kind="stable")  # rows of one hash in their order: each group's first comes first
    ordered = hashed[order]
    starts = np.concatenate([[True], ordered[1:] != ordered[:-1]])
    first = order[starts]
    later = np.flatnonzero(~starts)  # sorted positions of rows whose hash an earlier row has
    if not np.array_equal(rows[order[later]], rows[first[np.cumsum(starts)[later] - 1]]):  # two different rows share a hash
        _, first = np.unique(rows.view(np.dtype((np.void, 24))).ravel(), return_index=True)
    return np.sort(first)


def _row_hashes(rows: np.ndarray) -> np.ndarray:
    """(N,) uint64 hashes of the (N, 3) uint64 rows (a float64 cloud's bytes). Each coordinate's
    high half is folded into its low one before the multiply: a float64 read from a float32 file
    has its low 29 bits zero, which a multiply keeps, and on 5 x 10^6 such points the hashes of
    distinct rows collided hundreds of times (each collision sends the rows to a byte sort)."""
    hashed = np.zeros(len(rows), dtype=np.uint64)
    for column, factor in zip(rows.T, (0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9)):
        mixed = (column ^ (column >> np.uint64(32))) * np.uint64(factor)
        hashed ^= mixed ^ (mixed >> np.uint64(29))
    return hashed


def _every_kth(points: np.ndarray) -> np.ndarray:
    """Every k-th of the (N, 3) points, up to 2 x 10^5 of them: enough for a median or a percentile."""
    return points[:: max(1, len(points) // 100_000)]


def _about_median(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_every_kth` of the (N, 3) points, their (3,) median, and each one's distance to it."""
    sample = _every_kth(points)
    centre = np.median(sample, axis=0)
    return sample, centre, np.linalg.norm(sample - centre, axis=1)


def check_spread(points: np.ndarray, name: str = "cloud") -> None:
    """Raise InputError if the points are all identical or all on one line (no rotation is defined),
    judged on those within twice the distance from their median that 99 % of them lie within (so
    that a few stray far points neither hide a line nor make a surface look like one)."""
    with np.errstate(all="ignore"):  # coordinates near the float limit: distances of inf
        points, _, reach = _about_median(points)
        points = points[reach <= 2.0 * np.percentile(reach, 99)]
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] <= 1e-12 * max(1.0, np.abs(points).max()):
        raise InputError(f"{name}: all points are identical; a rotation cannot be estimated")
    if sv[1] <= 1e-6 * sv[0]:
        raise InputError(f"{name}: all points lie on one line; the rotation about it cannot be estimated")


def voxel_downsample(points: np.ndarray, voxel: float, name: str = "cloud", min_points: int = 1) -> np.ndarray:
    """The centroids of the occupied cells of a voxel grid (Open3D), for evening out density.

    Args:
        points: (N, 3).
        voxel: cell size, in the points' units.
        name: how to call the cloud in error messages.
        min_points: fewest points accepted after downsampling.
    Returns:
        (N', 3) float64, N' <= N.
    Raises:
        InputError: fewer than ``min_points`` points are left (the voxel is too large).
    """
    from .refine import to_open3d  # Open3D only when a grid is asked for

    down = np.asarray(to_open3d(points).voxel_down_sample(voxel).points)
    if len(down) < min_points:
        raise InputError(
            f"{name}: {counted(len(down), 'point')} left on a voxel grid of {voxel:g} units, fewer than the {min_points} needed; use a smaller voxel"
        )
    return down


def isolated_points(points: np.ndarray, radius: float) -> np.ndarray:
    """(N,) True for the points of (N, 3) finite `points` with fewer than two other points within
    `radius` (cloud units, > 0): Open3D's radius outlier removal, found from each point's three
    nearest points (itself among them), which stay few where many lie within the radius.

    Raises:
        ValueError: `radius` is not positive.
    """
    from .refine import kd_tree  # pykdtree's: 2.3-2.6 times as fast as SciPy's here, the same points

    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    points = np.ascontiguousarray(points, dtype=np.float64)  # as the tree holds them: one copy at most
    nearest, _ = kd_tree(points).query(points, k=3, distance_upper_bound=radius)
    return ~np.isfinite(nearest[:, 2])


# A point farther from its cloud's median than this many times the cloud's reach (twice the distance
# within which 90 % of its points lie) counts in neither the cloud's size nor its centre: a few ghost
# returns 100 m out from a 2 m room would move its centroid by a metre and triple its scale. A
# scan's own points lie within 2 reaches (a street sweep's farthest: 1.8), a ModelNet40 shape's within 2.
FAR_REACH = 10.0


def near_points(points: np.ndarray) -> np.ndarray:
    """(N', 3) the (N, 3) finite points within :data:`FAR_REACH` times their cloud's reach of its
    median: the array itself where all are (:func:`_beyond_reach`)."""
    beyond = _beyond_reach(points, FAR_REACH)
    return points if beyond is None else points[~beyond]


def robust_extent(points: np.ndarray) -> np.ndarray:
    """(3,) sides of the box holding the central 98 % of the (N, 3) points along each axis (cloud
    units): a few stray far points do not change it."""
    lo, hi = np.percentile(points, [1, 99], axis=0)
    return hi - lo


def principal_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) the principal axes of (N, 3) points as columns, largest variance first."""
    centred = points - points.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)  # columns by increasing variance
    return axes[:, ::-1]


def principal_extents(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(3,) sides of the box holding the central 98 % of the (N, 3) finite points along each of
    their :func:`principal_axes`, longest first (cloud units), and (3, 3) those axes as columns, in
    the same order: a pipe 100 long and 0.1 across has sides (100, 0.1, 0.1) whichever way it lies."""
    sample = _every_kth(points)
    sample = sample[np.isfinite(sample).all(axis=1)]
    sample = near_points(sample)
    axes = principal_axes(sample)
    lo, hi = np.percentile((sample - sample.mean(axis=0)) @ axes, [1, 99], axis=0)
    return hi - lo, axes


FLAT = 1e-5  # a cloud whose thinnest principal side is at most this share of its size lies in a plane


def flat_normal(points: np.ndarray) -> Optional[np.ndarray]:
    """(3,) unit normal of the plane the (N, 3) points lie in, where their thinnest
    :func:`principal_extents` side is at most ``FLAT`` of the longest (a 2D laser scan saved with
    z = 0); None for clouds with a third dimension."""
    sides, axes = principal_extents(points)
    return axes[:, 2] if sides[2] <= FLAT * sides[0] else None


def scene_size(points: np.ndarray) -> float:
    """Diagonal of the :func:`robust_extent` box of the (N, 3) finite points' :func:`near_points`
    (cloud units)."""
    return float(np.linalg.norm(robust_extent(near_points(points))))


def _finite_sample(points: np.ndarray) -> np.ndarray:
    """The finite rows of :func:`_every_kth` of the (N, 3) points: a point near the middle of a
    cloud, or its size, is all a median or a percentile of them is asked for."""
    sample = _every_kth(points)
    return sample[np.isfinite(sample).all(axis=1)]


def sample_median(points: np.ndarray) -> np.ndarray:
    """(3,) the median of :func:`_finite_sample` of the (N, 3) points (all finite rows of clouds
    of up to 2 x 10^5); zeros where none is finite."""
    finite = _finite_sample(points)
    if len(finite) == 0:
        return np.zeros(3)
    with np.errstate(all="ignore"):
        return np.median(finite, axis=0)


def local_origin(points: np.ndarray) -> np.ndarray:
    """(3,) the median of the (N, 3) points' finite rows (every k-th of them on clouds of over 10^5,
    up to 2 x 10^5) where it lies farther from the origin than their :func:`scene_size` (clouds in
    a frame far from them: georeferenced scans); else zeros (the clouds as given, to the bit)."""
    finite = _finite_sample(points)
    if len(finite) < 2:
        return np.zeros(3)  # cleaning reports it, by name
    with np.errstate(all="ignore"):  # absurd coordinates too are cleaning's to report
        centre, size = np.median(finite, axis=0), scene_size(finite)
        far = bool(np.isfinite(size) and np.linalg.norm(centre) > size)
    return centre if far else np.zeros(3)


SPACING_SAMPLE = 2000  # points whose nearest neighbours give a cloud's spacing


def point_spacing(points: np.ndarray, sample: int = SPACING_SAMPLE, seed: int = 0) -> float:
    """Median distance from a point to its nearest neighbour (cloud units), over at most `sample`
    of the (N, 3) points."""
    return _median_spacing(points, sample_points(points, sample, seed))


# The grid is at least this many cells across a cloud's second-longest principal side, so that a
# pipe or a wire keeps its cross-section (docs/scans.md, "2D scans and thin structures").
CELLS_ACROSS = 10


def data_grid(source: np.ndarray, target: np.ndarray, share: float) -> Optional[float]:
    """A voxel grid of `share` of the smaller scene's size (:func:`scene_size`; cloud units), or
    finer, 1 / ``CELLS_ACROSS`` of a cloud's second-longest :func:`principal_extents` side, where
    one of the clouds is denser than half of it (its :func:`point_spacing`); None where both are
    sparser: they are registered as they are.

    So millimetre-spaced RGB-D fragments, LiDAR sweeps and dense object scans come down to a few
    thousand points each, in whatever unit, and sparse clouds (the network's 1,024-point shapes)
    keep every point.
    """
    if share <= 0:
        return None
    size = min(scene_size(source), scene_size(target))  # clouds in different units: the grid leaves both whole
    across = min(principal_extents(source)[0][1], principal_extents(target)[0][1])
    voxel = min(share * size, across / CELLS_ACROSS)  # a pipe or a wire keeps its cross-section
    return voxel if spaced_closer_than(source, 0.5 * voxel) or spaced_closer_than(target, 0.5 * voxel) else None


def spaced_closer_than(points: np.ndarray, spacing: float, subset: int = 50_000) -> bool:
    """Whether ``point_spacing(points) < spacing``, exactly, for (N, 3) distinct points.

    On clouds of more than `subset` points it is asked first of a random `subset` of them that
    holds point_spacing's sampled points: no point's nearest neighbour in a subset is nearer than
    in the whole cloud, so a subset spaced closer decides (a dense scan: 17 against 237 ms on 10^6
    points, where the whole cloud's tree is built only when the subset does not decide)."""
    if len(points) <= subset + SPACING_SAMPLE:
        return point_spacing(points) < spacing
    queries = sample_indices(len(points), SPACING_SAMPLE)  # point_spacing's own
    others = np.random.default_rng(1).integers(0, len(points), size=subset)
    taken = np.zeros(len(points), dtype=bool)
    taken[queries] = True
    others = others[~taken[others]]  # a query's own copy would be its nearest neighbour
    if _median_spacing(np.vstack([points[queries], points[others]]), points[queries]) < spacing:
        return True
    return point_spacing(points) < spacing


def _median_spacing(cloud: np.ndarray, queries: np.ndarray) -> float:
    """Median distance from each of the (Q, 3) `queries`, points of the (N, 3) `cloud`, to its
    nearest other point of the cloud (cloud units)."""
    from scipy.spatial import cKDTree

    # An unbalanced tree builds in half the time and answers these few queries as exactly.
    d, _ = cKDTree(cloud, balanced_tree=False, compact_nodes=False).query(queries, k=2)
    return float(np.median(d[:, 1]))


def sample_points(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """A random subset of n points (all of them, shuffled, when there are fewer than n).

    Args:
        points: (N, 3).
        n: number of points wanted.
        seed: seed of the generator, so that the same input always gives the same subset.
    Returns:
        (min(N, n), 3) array, same dtype.
    """
    return points[sample_indices(len(points), n, seed)]


def sample_indices(count: int, n: int, seed: int = 0) -> np.ndarray:
    """The (min(count, n),) indices of :func:`sample_points`' subset of `count` points."""
    rng = np.random.default_rng(seed)
    if count <= n:
        return rng.permutation(count)
    return rng.choice(count, size=n, replace=False)


class Normalisation(NamedTuple):
    """How a pair was normalised: x' = (x - centroid) / scale, each cloud on its own centroid."""

    source_centroid: np.ndarray  # (3,)
    target_centroid: np.ndarray  # (3,)
    scale: float


def normalisation_for(source: np.ndarray, target: np.ndarray) -> Normalisation:
    """Centroids of both clouds and one common scale: the larger of their radii about the centroid,
    where a cloud's radius is at most twice the distance within which 99 % of its points lie
    (so that a few stray far points do not shrink the scene); both of the points
    :func:`near_points` (ghost returns far out move neither)."""
    source, target = near_points(source), near_points(target)
    cs = source.mean(axis=0)
    ct = target.mean(axis=0)
    radius = max(_radius(source - cs), _radius(target - ct))
    return Normalisation(cs.astype(np.float64), ct.astype(np.float64), float(max(radius, 1e-12)))


def _radius(centred: np.ndarray) -> float:
    r = np.linalg.norm(centred, axis=1)
    return float(min(r.max(), 2.0 * np.percentile(r, 99)))


def normalise_pair(source: np.ndarray, target: np.ndarray, norm: Optional[Normalisation] = None) -> Tuple[np.ndarray, np.ndarray, Normalisation]:
    """Centre both clouds on their own centroid and divide by one common scale.

    Args:
        source: (N, 3); target: (M, 3).
        norm: a normalisation to apply; computed from these clouds when None.
    Returns:
        (source', target', norm) with the clouds in the normalised frame (radius ~1).
    """
    if norm is None:
        norm = normalisation_for(source, target)
    s = (source - norm.source_centroid) / norm.scale
    t = (target - norm.target_centroid) / norm.scale
    return s.astype(source.dtype, copy=False), t.astype(target.dtype, copy=False), norm


def denormalise_transform(T_norm: np.ndarray, norm: Normalisation) -> np.ndarray:
    """Map a transform between normalised clouds back to the original frames.

    With x' = (x - c) / s on both sides, q' = R p' + t' becomes q = R p + (c_t - R c_s + s t').
    """
    R = T_norm[:3, :3]
    return rigid(R, norm.target_centroid - R @ norm.source_centroid + norm.scale * T_norm[:3, 3])


def normalise_transform(T: np.ndarray, norm: Normalisation) -> np.ndarray:
    """The inverse of :func:`denormalise_transform`: a transform between original clouds -> normalised."""
    R = T[:3, :3]
    return rigid(R, (T[:3, 3] + R @ norm.source_centroid - norm.target_centroid) / norm.scale)


def same_profile_pvalue(source: np.ndarray, target: np.ndarray) -> float:
    """p-value of the hypothesis that both clouds are samplings of one complete shape, judged by
    their distances to their own centroids (two-sample Kolmogorov-Smirnov test; rotation and
    translation leave them unchanged). A small value means partial overlap (or two different
    shapes).

    Args:
        source: (N, 3); target: (M, 3), in any frames.
    Returns:
        p in [0, 1] (how often it falls below 0.01 for crops, independent samplings and noisy
        copies: docs/pipeline.md).
    """
    radial = [np.linalg.norm(c - c.mean(axis=0), axis=1) for c in (source, target)]
    scale = max(max(r.max() for r in radial), 1e-12)
    return float(ks_2samp(radial[0] / scale, radial[1] / scale, method="asymp").pvalue)
