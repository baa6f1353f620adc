"""Fine stage: ICP (Open3D's point-to-point; point-to-plane in Open3D's steps, run here), and scoring of a transform.

ICP (point-to-point, or point-to-plane for scans) runs coarse to fine over a distance schedule
(by default d, 0.3 d, 0.1 d): the first stage pulls in an estimate a few degrees off; the last ones
keep only close pairs, so that parts of one cloud with no partner in the other (partial overlap)
stop biasing the result. With point-to-point ICP the last stage's distance never falls below
``noise_factor`` times the residual of the stage before it (:func:`residual`), so that noisy
clouds keep their true pairs, and ICP ends with one float64 Procrustes step on its final pairs
(:func:`polish`), since Open3D's ICP stops about 1e-5 degrees short of the least-squares optimum.
Point-to-plane ICP runs Open3D's steps here (:func:`plane_steps`): Open3D sums its normal
equations over threads in no fixed order, so that one pair gave another pose at each call where
the surfaces hold the pose loosely. Clouds above ``max_points`` are voxel-downsampled first.
The measurements behind these choices are in docs/pipeline.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from typing import NamedTuple, Optional, Tuple

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from ._open3d import open3d as o3d
from .preprocess import point_spacing, robust_extent
from .procrustes import rigid_fit
from .transforms import apply_transform, rigid

RELATIVE_DISTANCE = 0.1  # ICP's default correspondence distance, a share of the pair's scale


@dataclass(frozen=True)
class ICPConfig:
    """Settings of the fine stage.

    Attributes:
        distance: max correspondence distance, relative to the pair's scale (the larger radius
            of the two clouds) unless `absolute` is set; None: :data:`RELATIVE_DISTANCE` of the
            scale (with `absolute`, a distance must be given). Fitness and inlier RMSE are
            reported at it.
        schedule: ICP runs once per entry, at distance * entry, in this order.
        absolute: `distance` is in the clouds' own units.
        max_iterations, relative_fitness, relative_rmse: Open3D's convergence criteria (of the
            last stage, see `early_relative`).
        early_relative: the stages before the last stop when their fitness and RMSE change by
            less than this share from one iteration to the next (only the last, which goes on
            from there, needs to converge tightly).
        plane_relative: point-to-plane ICP's last stage (of the schedule in use, also the quick
            one's) stops at this share instead of `relative_fitness` / `relative_rmse`: it
            converges in a few iterations, and at 1e-7 the pairs that flicker in and out at the
            tight distance keep it iterating up to `max_iterations` (docs/scans.md).
        max_points: clouds above this size are voxel-downsampled before ICP.
        polish: end with one float64 point-to-point step at the last distance (:func:`polish`).
        noise_factor: point-to-point ICP's last stage's distance is at least this many times the
            residual of the stage before it (:func:`residual`), so that noisy clouds keep their
            true pairs; 0: off. Not for point-to-plane ICP: the residual is a point-to-point
            distance, on independently sampled scans set by their spacing, not by their noise.
        noise_rounds: the last stage re-runs up to this many times while that bound tightens
            (point-to-point ICP).
        tight_from: the tight stages (:meth:`tight`) are those from this share of the distance on;
            they refine an estimate that is already nearly right without the loose first stage,
            which pulls it towards parts with no partner.
        method: "point" (point-to-point, the paper's), "plane" (point-to-plane, against the
            target's :func:`normals`: far fewer iterations on sampled surfaces, and not limited
            by their sampling; Open3D's steps with sums in one order, :func:`plane_steps`), or "auto": plane on scans (clouds registered on a voxel grid, or of
            more than 4,096 points), point otherwise (:class:`o3dsoft.pair.PreparedPair` decides).
        normal_neighbours, normal_within: point-to-plane ICP's normals fit the `normal_neighbours`
            nearest points within `normal_within` point spacings (:func:`normals`; 0: the
            nearest, however far). The pipeline bounds them on clouds on a voxel grid only,
            whose spacing is even; a random sample is sparse in places.
    """

    distance: Optional[float] = None
    schedule: Tuple[float, ...] = (1.0, 0.3, 0.1)
    absolute: bool = False
    max_iterations: int = 100
    relative_fitness: float = 1e-7
    relative_rmse: float = 1e-7
    early_relative: float = 1e-4
    plane_relative: float = 1e-5
    max_points: int = 100_000
    polish: bool = True
    noise_factor: float = 2.5
    noise_rounds: int = 3
    tight_from: float = 0.3
    method: str = "auto"
    normal_neighbours: int = 20
    normal_within: float = 5.0

    def distance_for(self, scale: float) -> float:
        """The correspondence distance in cloud units for a pair of this scale."""
        if self.distance is None:
            if self.absolute:
                raise ValueError("ICPConfig(absolute=True) needs a distance, in the clouds' units")
            return RELATIVE_DISTANCE * scale
        return self.distance if self.absolute else self.distance * scale

    def starting_at(self, factor: float) -> "ICPConfig":
        """The schedule for an estimate already within distance * `factor` of its partners: the
        first stage moved down to `factor` (when below it), and later stages not below it dropped."""
        if factor >= self.schedule[0]:
            return self
        return replace(self, schedule=(factor,) + tuple(f for f in self.schedule[1:] if f < factor))

    def tight(self) -> "ICPConfig":
        """The schedule's tight stages only: :meth:`starting_at` `tight_from`."""
        return self.starting_at(self.tight_from)

    def final(self) -> "ICPConfig":
        """For an estimate that has converged through the whole schedule on coarser clouds (the
        work clouds' result, refined at full resolution): the last stage only, at its own
        distance. The wider stages would pull it again towards the parts with no partner and cost
        the most on many points."""
        return replace(self, schedule=self.schedule[-1:])

    def quick(self, max_iterations: int) -> "ICPConfig":
        """A cheaper ICP for ranking estimates: without the last stage (when there are several),
        the noise rounds and the polish, each stage at most `max_iterations`."""
        schedule = self.schedule[:-1] if len(self.schedule) > 1 else self.schedule
        return replace(self, schedule=schedule, polish=False, noise_factor=0.0, max_iterations=max_iterations)


class ICPResult(NamedTuple):
    """transformation: (4, 4) T_target_source; fitness: share of source points with a target
    point within the distance (0-1, higher is better); inlier_rmse: RMS distance of those pairs
    (cloud units, lower is better)."""

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float


def to_open3d(points: np.ndarray) -> "o3d.geometry.PointCloud":
    """(N, 3) array -> Open3D point cloud."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def downsample(points: np.ndarray, max_points: int) -> np.ndarray:
    """Voxel-downsample (N, 3) points to at most `max_points` (unchanged if already small enough)."""
    if len(points) <= max_points:
        return points
    cloud = to_open3d(points)
    extent = robust_extent(points)  # stray far points aside
    # Surface-like data: the count falls with the square of the voxel size. Start from the voxel
    # that a surface filling the bounding box's largest face would need, then grow until it fits.
    dims = np.sort(extent)[1:]
    voxel = float(np.sqrt(dims[0] * dims[1] / max_points))
    for _ in range(20):
        down = np.asarray(cloud.voxel_down_sample(voxel).points)
        if len(down) <= max_points:
            return down
        voxel *= max(1.05, float(np.sqrt(len(down) / max_points)))
    return down


# Open3D's covariance of a point with fewer than 3 neighbours within the search radius.
_NO_SPREAD = np.eye(3)
# A neighbourhood follows a line (one ring of a sparse LiDAR sweep) where its spread across the
# line is at most this share of its spread along it (variances): the plane through it turns freely
# about the line, and point-to-plane ICP slides the rings of one sweep onto the other's.
LINE_SHARE = 0.01
# Such a neighbourhood is widened to this many times the nearest points, in turn, until it spans a
# plane (on a sweep of 8 rings the next ring lies past a few hundred points of the ring's own).
WIDER = (4, 16)


def normals(points: np.ndarray, neighbours: int, within: float = 0.0) -> np.ndarray:
    """(N, 3) unit normals (sign arbitrary) of an (N, 3) cloud: of the plane through each point's
    `neighbours` nearest points that lie within `within` times the cloud's point spacing
    (:func:`o3dsoft.preprocess.point_spacing`); through all `neighbours` nearest where fewer
    than 3 do or where `within` is 0; and where those follow a line (:data:`LINE_SHARE`), through
    the :data:`WIDER` times as many nearest. For point-to-plane ICP: estimate once, pass to :func:`icp`.

    Why the bound: where a cloud is sparse (a LiDAR frame on a coarse grid) the nearest points
    reach across edges onto other surfaces, and ICP's planes tilt with them (docs/scans.md)."""
    points = np.asarray(points, dtype=np.float64)
    cloud = to_open3d(points)
    radius = within * point_spacing(points) if within > 0 and len(points) >= 3 and neighbours >= 3 else 0.0
    bounded = bool(np.isfinite(radius) and radius > 0)  # not where no bound is asked, or there is no spacing to bound by
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=neighbours) if bounded else o3d.geometry.KDTreeSearchParamKNN(neighbours)
    cloud.estimate_covariances(search)
    cloud.estimate_normals(search)  # from those covariances
    out, spread = np.asarray(cloud.normals).copy(), np.asarray(cloud.covariances)
    values = np.linalg.eigvalsh(spread)
    loose = np.flatnonzero(np.all(spread == _NO_SPREAD, axis=(1, 2)) | (values[:, 1] <= LINE_SHARE * values[:, 2]))
    tree = cKDTree(points) if len(loose) else None
    for k in ((1,) if bounded else ()) + WIDER:  # the nearest however far, then wider
        k = min(k * neighbours, len(points))
        if not len(loose) or k < 3:
            break
        _, nearest = tree.query(points[loose], k=k)
        values, vectors = local_spread(points[nearest])
        out[loose] = vectors[:, :, 0]  # the direction of least spread
        loose = loose[values[:, 1] <= LINE_SHARE * values[:, 2]]
    return out


def local_spread(groups: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """How each of the (G, K, 3) groups of points spreads about its mean: (G, 3) eigenvalues of
    its scatter, increasing, and (G, 3, 3) their unit eigenvectors as columns (the first: the
    normal of the least-squares plane; the last: the direction of a line)."""
    centred = groups - groups.mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("gki,gkj->gij", centred, centred))
    return values, vectors


def icp(
    source: np.ndarray,
    target: np.ndarray,
    init: np.ndarray,
    distance: float,
    config: ICPConfig = ICPConfig(),
    target_normals: Optional[np.ndarray] = None,
    target_tree: Optional[KDTree] = None,
) -> ICPResult:
    """ICP from `init`, point-to-point or point-to-plane (``config.method``), over the distance
    schedule of `config`.

    Args:
        source: (N, 3); target: (M, 3) in their original frames.
        init: (4, 4) initial T_target_source.
        distance: max correspondence distance in cloud units (the schedule's multipliers apply).
        target_normals: (M, 3) the target's :func:`normals` (``config.normal_neighbours``,
            ``config.normal_within``), when
            point-to-plane ICP runs on it often (estimated here otherwise, and when the target is
            downsampled first).
        target_tree: the target's :func:`kd_tree`, where point-to-plane ICP runs on it often
            (built here otherwise, and when the target is downsampled first).
    Returns:
        ICPResult with the refined transform, and the fitness and inlier RMSE at `distance`.
    """
    reg = o3d.pipelines.registration
    src = to_open3d(downsample(source, config.max_points))
    tgt = to_open3d(downsample(target, config.max_points))
    plane = config.method == "plane"
    fitness, rmse = (config.plane_relative, config.plane_relative) if plane else (config.relative_fitness, config.relative_rmse)
    last = reg.ICPConvergenceCriteria(relative_fitness=fitness, relative_rmse=rmse, max_iteration=config.max_iterations)
    early = reg.ICPConvergenceCriteria(relative_fitness=config.early_relative, relative_rmse=config.early_relative, max_iteration=config.max_iterations)
    T = np.asarray(init, dtype=np.float64)
    distances = [distance * factor for factor in config.schedule]
    src_points, tgt_points = np.asarray(src.points), np.asarray(tgt.points)
    whole = len(target) <= config.max_points  # the target as given: what the caller's normals and tree are of
    tree = None if plane else cKDTree(tgt_points)  # for the noise rounds and the polish, point-to-point only
    tgt_normals, plane_tree = None, None
    if plane:
        given = target_normals is not None and len(target_normals) == len(target) and whole
        tgt_normals = np.asarray(target_normals, dtype=np.float64) if given else normals(tgt_points, config.normal_neighbours, config.normal_within)
        plane_tree = target_tree if target_tree is not None and whole and target_tree.n == len(target) else kd_tree(tgt_points)

    def run(T: np.ndarray, stage_distance: float, criteria) -> np.ndarray:
        if plane:
            return plane_steps(src_points, tgt_points, tgt_normals, T, stage_distance, criteria, plane_tree)
        result = reg.registration_icp(src, tgt, stage_distance, T, reg.TransformationEstimationPointToPoint(), criteria)
        return np.asarray(result.transformation).copy()

    for stage, stage_distance in enumerate(distances):
        last_stage = stage == len(distances) - 1
        if last_stage and stage > 0 and config.noise_factor > 0 and not plane:
            # The residual is the noise plus what is left of the misalignment: as the fit
            # tightens, so does the distance, while it shrinks by more than a tenth.
            wider = distances[stage - 1]
            for round_ in range(config.noise_rounds):
                proposed = max(stage_distance, config.noise_factor * residual(src_points, tree, T, wider))
                if round_ > 0 and proposed > 0.9 * wider:
                    break
                T, wider = run(T, proposed, last), proposed
                if proposed <= stage_distance:
                    break  # at the floor: no later proposal can be lower (clean clouds, at once)
            distances[stage] = wider
        else:
            T = run(T, stage_distance, last if last_stage else early)
    if config.polish and not plane:  # the polish is a point-to-point step
        T = polish(src_points, tgt_points, T, distances[-1], tree)
    scored = reg.evaluate_registration(src, tgt, distance, T)
    if scored.fitness == 0:
        # No point within d at the end: ICP ran off its few partners (point-to-plane steps on a
        # handful of points can go thousands of scene sizes away); where the start had some, it stands.
        start = reg.evaluate_registration(src, tgt, distance, np.asarray(init, dtype=np.float64))
        if start.fitness > 0:
            return ICPResult(np.asarray(init, dtype=np.float64).copy(), float(start.fitness), float(start.inlier_rmse))
    return ICPResult(T, float(scored.fitness), float(scored.inlier_rmse))


def kd_tree(points: np.ndarray) -> KDTree:
    """A KD-tree of the (N, 3) points for :func:`plane_steps`' pairs and isolated points (pykdtree's: its queries run
    in OpenMP threads, each point's on its own, so the pairs are the same in any thread; about
    three times as fast as SciPy's here). From then on, a process forked from this one runs
    OpenMP on one thread (a fork inherits no thread of the pool)."""
    _PAIRED[0] = True
    return KDTree(np.ascontiguousarray(points, dtype=np.float64))


_PAIRED = [False]  # whether this process has built a pykdtree tree (and may have queried it in threads)


def _one_openmp_thread_after_fork() -> None:
    # A forked child inherits libgomp's thread pool without its threads: its first parallel
    # query waits forever. With one thread the child runs each query itself (as torch's are,
    # o3dsoft.coarse); the limit holds every OpenMP library of the child, torch's among them.
    if _PAIRED[0]:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1, user_api="openmp")


os.register_at_fork(after_in_child=_one_openmp_thread_after_fork)


def plane_steps(
    source: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    transformation: np.ndarray,
    distance: float,
    criteria: "o3d.pipelines.registration.ICPConvergenceCriteria",
    tree: Optional[KDTree] = None,
) -> np.ndarray:
    """Point-to-plane ICP at one correspondence distance: Open3D's ``registration_icp`` with
    ``TransformationEstimationPointToPlane``, step for step (each source point paired with its
    nearest target point within `distance`; a Gauss-Newton step on the linearised residuals
    (p - q) . n, its turn taken as Euler angles z-y-x; until fitness and inlier RMSE change by
    less than the criteria's, at most its ``max_iteration`` steps), with every sum in one fixed
    order: on one machine the same clouds give the same pose to the bit. Where the normal
    equations nearly hold no motion (a flat cloud, a handful of pairs), a step follows rounding,
    in Open3D's as in these.

    Args:
        source: (N, 3); target: (M, 3); target_normals: (M, 3) unit normals of `target`.
        transformation: (4, 4) the start, T_target_source. distance: cloud units.
        criteria: Open3D's convergence criteria. tree: `target`'s :func:`kd_tree`, if built already.
    Returns:
        (4, 4) float64 T_target_source.
    """
    tree = tree if tree is not None else kd_tree(target)
    partners = np.hstack([target, target_normals])  # (M, 6): a pair's point and normal in one gather
    T = np.array(transformation, dtype=np.float64)
    moved = apply_transform(T, source)

    def pairs(moved: np.ndarray) -> Tuple[np.ndarray, np.ndarray, Tuple[float, float]]:
        squared, j = tree.query(moved, distance_upper_bound=distance, sqr_dists=True)
        paired = np.isfinite(squared)
        n = int(paired.sum())
        return paired, j, (n / max(len(moved), 1), float(np.sqrt(np.sum(squared[paired]) / n)) if n else 0.0)

    paired, j, score = pairs(moved)
    for _ in range(criteria.max_iteration):
        if not paired.any():
            break  # Open3D's step is the identity here, and the scores repeat
        rows = np.flatnonzero(paired)
        p, qn = moved[rows], partners[j[rows]]
        q, n = qn[:, :3], qn[:, 3:]
        J = np.empty((len(p), 6))  # d residual / d (turn about x, y, z; shift): (p x n, n)
        J[:, 0] = p[:, 1] * n[:, 2] - p[:, 2] * n[:, 1]
        J[:, 1] = p[:, 2] * n[:, 0] - p[:, 0] * n[:, 2]
        J[:, 2] = p[:, 0] * n[:, 1] - p[:, 1] * n[:, 0]
        J[:, 3:] = n
        r = np.einsum("ij,ij->i", p - q, n)
        JTJ, JTr = J.T @ J, J.T @ r
        try:
            x = np.linalg.solve(JTJ, -JTr)
        except np.linalg.LinAlgError:  # exactly singular (normals along the axes of a flat cloud): no motion along what no pair holds
            x = np.linalg.lstsq(JTJ, -JTr, rcond=None)[0]
        step = rigid(_euler_zyx(x[:3]), x[3:])
        T = step @ T
        moved = apply_transform(step, moved)
        before = score
        paired, j, score = pairs(moved)
        if abs(before[0] - score[0]) < criteria.relative_fitness and abs(before[1] - score[1]) < criteria.relative_rmse:
            break
    return T


def _euler_zyx(angles: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation Rz(c) Ry(b) Rx(a) of `angles` (3,) = (a, b, c) in radians: Open3D's
    reading of a point-to-plane step's turn."""
    (ca, cb, cc), (sa, sb, sc) = np.cos(angles), np.sin(angles)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    Ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    Rz = np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def residual(source: np.ndarray, tree: cKDTree, transformation: np.ndarray, distance: float) -> float:
    """Median distance from a moved source point to its nearest target point, over the points
    with one within `distance` (0 if none): the noise level of an aligned pair, ~0 for identical
    point sets.

    Args:
        source: (N, 3); tree: KD-tree of the (M, 3) target; transformation: (4, 4) T_target_source.
    """
    dist, _ = tree.query(apply_transform(np.asarray(transformation, dtype=np.float64), source), distance_upper_bound=distance)
    near = dist[np.isfinite(dist)]
    return float(np.median(near)) if len(near) else 0.0


def polish(source: np.ndarray, target: np.ndarray, transformation: np.ndarray, distance: float, tree: Optional[cKDTree] = None) -> np.ndarray:
    """One exact point-to-point step: the float64 least-squares transform of the nearest-neighbour
    pairs within `distance`, returned only if it lowers their RMS distance (else `transformation`).

    Args:
        source: (N, 3); target: (M, 3); transformation: (4, 4) T_target_source.
        distance: max pair distance, cloud units.
        tree: a KD-tree of `target`, if one is built already.
    Returns:
        (4, 4) float64 T_target_source.
    """
    T = np.asarray(transformation, dtype=np.float64)
    dist, j = (tree if tree is not None else cKDTree(target)).query(apply_transform(T, source), distance_upper_bound=distance)
    keep = np.isfinite(dist)
    if keep.sum() < 3:
        return T
    p, q = source[keep], target[j[keep]]
    T_new = rigid(*rigid_fit(p, q))
    before = np.mean(dist[keep] ** 2)
    after = np.mean(np.sum((apply_transform(T_new, p) - q) ** 2, axis=1))
    return T_new if after < before else T


def evaluate(source: np.ndarray, target: np.ndarray, transformation: np.ndarray, distance: float, max_points: int = ICPConfig.max_points) -> ICPResult:
    """Score a transform without optimising it (Open3D's evaluate_registration)."""
    result = o3d.pipelines.registration.evaluate_registration(
        to_open3d(downsample(source, max_points)),
        to_open3d(downsample(target, max_points)),
        distance,
        np.asarray(transformation, dtype=np.float64),
    )
    return ICPResult(np.asarray(transformation, dtype=np.float64).copy(), float(result.fitness), float(result.inlier_rmse))
