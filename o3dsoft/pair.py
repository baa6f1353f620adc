"""The pair of clouds as the pipeline works on it: cleaned, at each resolution, normalised for
the network, with what the stages share computed once (KD-trees and point spacings of the
scorers, the FPFH features)."""

from __future__ import annotations

import math
import os
from dataclasses import replace
from functools import cached_property
from typing import TYPE_CHECKING, Dict, Iterable, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
from pykdtree.kdtree import KDTree

from . import confidence as confidence_stage
from . import refine as refine_stage
from .clock import StageClock
from .config import RegisterConfig
from .errors import InputError
from .io import host_array
from .preprocess import (
    CleanReport,
    clean_points,
    data_grid,
    flat_normal,
    isolated_points,
    normalisation_for,
    normalise_pair,
    point_spacing,
    same_profile_pvalue,
    sample_points,
    scene_size,
    voxel_downsample,
)
from .search import FeatureMatch
from .transforms import apply_transform

if TYPE_CHECKING:
    import open3d
    import torch

CloudLike = Union[np.ndarray, "open3d.geometry.PointCloud", "open3d.t.geometry.PointCloud", "torch.Tensor"]
Clouds = Tuple[np.ndarray, np.ndarray]  # (N, 3) source, (M, 3) target

# Clouds with more points than this are scans even off a grid: above any ModelNet40 release (2,048 per shape).
SCAN_POINTS = 4096


def as_points(cloud: CloudLike, name: str) -> np.ndarray:
    """An Open3D PointCloud (legacy or tensor), a torch or Open3D tensor, an (N, 3) array-like or
    an (N,) structured array with fields x, y, z (ROS's point_cloud2.read_points) -> (N, 3)
    float64 array."""
    if isinstance(cloud, (str, os.PathLike)):
        raise InputError(f"{name}: got the file name {str(cloud)!r}, not points: read it first, o3dsoft.read_points(path)")
    if hasattr(cloud, "points") and not isinstance(cloud, np.ndarray):
        return np.asarray(cloud.points, dtype=np.float64)
    if hasattr(cloud, "point") and hasattr(cloud, "to_legacy"):  # open3d.t.geometry.PointCloud
        if "positions" not in cloud.point:
            raise InputError(f"{name}: an Open3D tensor PointCloud without positions")
        return cloud.point.positions.cpu().numpy().astype(np.float64)
    cloud = host_array(cloud)
    try:
        arr = np.asarray(cloud)
    except ValueError as e:  # ragged nested lists
        raise InputError(f"{name}: expected points of shape (N, 3), got rows of different lengths ({e})") from None
    if arr.dtype.names is not None:  # one record per point: x, y, z and others (intensity, ring, ...)
        if not {"x", "y", "z"} <= set(arr.dtype.names):
            raise InputError(f"{name}: a structured array needs fields x, y and z, got {', '.join(arr.dtype.names)}")
        arr = np.stack([arr[c].reshape(-1).astype(np.float64) for c in "xyz"], axis=1)
    if arr.ndim == 0:  # not an array at all (e.g. a mesh)
        raise InputError(f"{name}: expected an Open3D PointCloud, a tensor or (N, 3) points, got a {type(cloud).__module__}.{type(cloud).__qualname__}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected points of shape (N, 3), got {arr.shape}")
    if np.iscomplexobj(arr) or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected real numeric points, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


def named_clouds(clouds: Iterable[CloudLike], names: Optional[Sequence[str]], noun: str, command: str) -> Tuple[List[CloudLike], Tuple[str, ...]]:
    """The clouds of a command of many (`command`: "multiway", "odometry"), as a list, and their
    names (default `noun`0, `noun`1, ...).

    Raises:
        InputError: fewer than two clouds, or not one name per cloud.
    """
    clouds = list(clouds)  # any iterable of clouds
    names = tuple(names) if names is not None else tuple(f"{noun}{i}" for i in range(len(clouds)))
    if len(clouds) < 2:
        raise InputError(f"{command} needs at least two {noun}s, got {len(clouds)}")
    if len(names) != len(clouds):
        raise InputError(f"{len(names)} names for {len(clouds)} {noun}s")
    return clouds, names


# Isolated grid points are left out only where they are at least this share of a cloud: a clean
# scan's few (under 0.2 % of the 3DMatch fragments on their grid) do not disturb its registration,
# and leaving them in keeps the work that depends on every point (sampling, features) the same.
ISOLATED_MIN_SHARE = 0.01
# Off a grid, a cloud whose isolated points are more than this share of it is sparse in places (a
# LiDAR sweep's far returns), not scattered (docs/scans.md).
ISOLATED_MAX_SHARE_OFF_GRID = 0.1
# ... and so is one whose isolated points lie out: their median distance from the cloud's median
# point over this many times the cloud's own (a LiDAR sweep's far returns; scattered points in the
# cloud's box lie about as far out as its surfaces).
ISOLATED_FAR_OUT = 2.0
# Two clouds on their registration grid (odometry's steps) are worked on whole up to this many
# times ``attempt_points``: a trusted step then refines and scores once instead of twice, but a
# searched step refines its estimates on them too (on maps of 50,000-90,000 points such steps
# took 2-5 times as long; docs/multiway.md).
GRID_WORK_ATTEMPTS = 3


def registration_grid(clouds: Clouds, config: RegisterConfig) -> Optional[float]:
    """The voxel grid (cloud units) the (N, 3) and (M, 3) cleaned clouds are registered on: the
    config's (0: none), else :func:`~o3dsoft.preprocess.data_grid` where a cloud has more than
    ``config.attempt_points`` points (smaller clouds are tried whole); None: no grid."""
    if config.voxel is not None:
        return config.voxel or None
    if max(map(len, clouds)) > config.attempt_points:
        return data_grid(*clouds, config.data_voxel)
    return None


def are_scans(clouds: Clouds, voxel: Optional[float]) -> bool:
    """Whether the (N, 3) and (M, 3) clouds are scans: registered on the grid `voxel` (None:
    none), or with more points than any ModelNet40 shape has (clouds a user downsampled already:
    the data's grid leaves them as they are)."""
    return voxel is not None or max(map(len, clouds)) > SCAN_POINTS


def icp_for_pair(icp: refine_stage.ICPConfig, target: np.ndarray, voxel: Optional[float], scans: bool) -> refine_stage.ICPConfig:
    """ICP's settings for one pair: normals within a few point spacings only where the grid
    `voxel` (None: none) spaced the points evenly, and method "auto" decided: point-to-plane on
    `scans`, the paper's point-to-point on the rest and where the (M, 3) `target` is flat (a 2D
    scan, whose normals all leave its plane: they hold no motion within it)."""
    if voxel is None:
        icp = replace(icp, normal_within=0.0)
    if icp.method == "auto":
        icp = replace(icp, method="plane" if scans and flat_normal(target) is None else "point")
    return icp


class GridCloud(NamedTuple):
    """One cloud cleaned and on a voxel grid as :class:`PreparedPair` registers it (:func:`on_grid`),
    for a caller that registers the same cloud many times (odometry: each sweep once as the
    source, then in the maps of the sweeps after it).

    Attributes:
        points: (N, 3) the grid's points, without the isolated ones (cloud units).
        cleaned: what cleaning removed from the cloud (its points: `points`, whose size stands
            for the cleaned cloud's).
        isolated: how many grid points were left out as scattered outliers.
        voxel: the grid's cell size (cloud units).
    """

    points: np.ndarray
    cleaned: CleanReport
    isolated: int
    voxel: float

    def moved(self, transformation: np.ndarray) -> "GridCloud":
        """The cloud moved by the (4, 4) `transformation`."""
        points = apply_transform(transformation, self.points)
        return self._replace(points=points, cleaned=self.cleaned._replace(points=points))


def on_grid(report: CleanReport, voxel: float, config: RegisterConfig, k: int, name: str) -> GridCloud:
    """The cleaned cloud of `report` on the grid `voxel` (cloud units), without its isolated points
    (at ``config.isolated_radius`` cells) only where the grid merged its points: there a scattered
    point keeps a cell of its own while a surface shares its cells (a sparse cloud's points are no
    outliers).

    Raises:
        InputError: the grid leaves fewer than `k` points.
    """
    grid = voxel_downsample(report.points, voxel, name, min_points=k)
    isolated = 0
    if config.isolated_radius > 0 and len(grid) <= len(report.points) // 2:
        grid, isolated = _without_isolated(grid, config.isolated_radius * voxel, k)
    return GridCloud(grid, report._replace(points=grid), isolated, voxel)


def _without_isolated(cloud: np.ndarray, radius: float, k: int, most: float = 0.5, far_out: float = math.inf) -> Tuple[np.ndarray, int]:
    """(N', 3) `cloud` without its :func:`~o3dsoft.preprocess.isolated_points` at `radius`
    (cloud units) where they are at least :data:`ISOLATED_MIN_SHARE` of it, unless they are
    more than the share `most` of it, would leave it fewer than `k` points, or lie out from
    its median point over `far_out` times as far as the cloud does (medians; then it is
    sparse, not scattered); and how many points it lost."""
    if not radius > 0:  # no spacing to measure by (coordinates so close that their distances underflow)
        return cloud, 0
    isolated = isolated_points(cloud, radius)
    n = int(isolated.sum())
    if n < ISOLATED_MIN_SHARE * len(cloud) or n > math.ceil(most * len(cloud)) or len(cloud) - n < k:
        return cloud, 0
    if math.isfinite(far_out):
        out = np.linalg.norm(cloud - np.median(cloud, axis=0), axis=1)
        if np.median(out[isolated]) > far_out * np.median(out):
            return cloud, 0
    return cloud[~isolated], n


class PreparedPair:
    """Both clouds at every resolution the pipeline uses, in their original frames:

    - ``full``: cleaned (no NaN/inf, no duplicates) and on the voxel grid ``voxel`` (the
      config's, or one from the data, :func:`o3dsoft.preprocess.data_grid`; None: none), without
      its scattered outliers (``isolated``: how many per cloud; ``config.isolated_radius`` on a
      grid, ``config.isolated_spacings`` off one): what is registered, and where the kept estimate is refined
      and scored last;
    - ``work``: ``full`` voxel-downsampled to at most ``config.attempt_points`` each, where every
      estimate is refined and scored; ``full`` itself for two :class:`GridCloud` of at most
      :data:`GRID_WORK_ATTEMPTS` times as many points (and ``icp.max_points``) each: odometry's
      steps, most of which refine one guess, where a second grid would double their normals,
      ICP and scoring;
    - ``screen``: ``work`` on a grid of at most ``config.search.screen.points`` each (an even
      spacing, which the confidence relies on; smaller clouds whole, shuffled), where the
      search's estimates, and the network's on scans, are tried first on large clouds;
    - ``net``: ``config.num_points`` random samples of ``full`` for the network, and
      ``net_normalised`` the same centred on their own centroids and divided by one scale.

    ``scans``: the clouds are scans, registered on a voxel grid or of more than
    :data:`SCAN_POINTS` points (point-to-plane ICP, KISS-Matcher in the search, no second network).
    ``config`` is the pipeline's settings with ICP's method decided for this pair (``"auto"``:
    point-to-plane on scans), and ``icp.normal_within`` 0 off a grid (normals from the nearest
    points, however far: a cloud not on a grid is spaced unevenly).

    Args:
        source: (N, 3) array or Open3D PointCloud; target: (M, 3), in the same units. Or two
            :class:`~o3dsoft.preprocess.CleanReport` of clouds cleaned already; or two
            :class:`GridCloud` on one grid, cleaned and gridded already (the config's grid and
            isolated-point settings are then not read).
        config: the pipeline's settings.
        k: the network's neighbourhood size (the fewest points a cloud may have).
        names: how to call the clouds in error messages.
        clock: charged for "clean" and "sample_normalise".
    Raises:
        InputError: a cloud is degenerate, or the voxel grid leaves too few points.
    """

    def __init__(
        self,
        source: Union[CloudLike, CleanReport, GridCloud],
        target: Union[CloudLike, CleanReport, GridCloud],
        config: RegisterConfig,
        k: int,
        names: Tuple[str, str] = ("source", "target"),
        clock: Optional[StageClock] = None,
    ) -> None:
        clock = clock or StageClock()
        prepared = False  # on the grid by the caller
        if isinstance(source, GridCloud) or isinstance(target, GridCloud):
            prepared = True
            if not (isinstance(source, GridCloud) and isinstance(target, GridCloud) and source.voxel == target.voxel):
                raise ValueError("prepared clouds come in pairs on one grid: two GridClouds of the same voxel")
            self.cleaned: Tuple[CleanReport, CleanReport] = (source.cleaned, target.cleaned)
            self.voxel: Optional[float] = source.voxel
            self.full: Clouds = (source.points, target.points)
            self.isolated: Tuple[int, int] = (source.isolated, target.isolated)
        else:
            if isinstance(source, CleanReport) and isinstance(target, CleanReport):  # cleaned by the caller
                self.cleaned = (source, target)
            elif isinstance(source, CleanReport) or isinstance(target, CleanReport):
                raise ValueError("cleaned clouds come in pairs: two CleanReports")
            else:
                # Clean: drop NaN/inf rows and duplicates; reject degenerate clouds; even out the density.
                self.cleaned = (
                    clean_points(as_points(source, names[0]), names[0], min_points=k),
                    clean_points(as_points(target, names[1]), names[1], min_points=k),
                )
            self.full = (self.cleaned[0].points, self.cleaned[1].points)
            self.voxel = registration_grid(self.full, config)
            self.isolated = (0, 0)  # points left out as scattered outliers, per cloud
            if self.voxel is not None:
                grids = [on_grid(report, self.voxel, config, k, name) for report, name in zip(self.cleaned, names)]
                self.full, self.isolated = (grids[0].points, grids[1].points), (grids[0].isolated, grids[1].isolated)
        self.scans = are_scans(self.full, self.voxel)
        if self.scans and self.voxel is None and config.voxel is None and config.isolated_spacings > 0:
            # Scans off a grid: isolated by each cloud's own spacing; where more than
            # ISOLATED_MAX_SHARE_OFF_GRID of a cloud is, or they lie out (ISOLATED_FAR_OUT), it is
            # sparse in places, not scattered.
            src, tgt = (_without_isolated(c, config.isolated_spacings * point_spacing(c), k, ISOLATED_MAX_SHARE_OFF_GRID, ISOLATED_FAR_OUT) for c in self.full)
            self.full, self.isolated = (src[0], tgt[0]), (src[1], tgt[1])
        self.config = config = replace(config, icp=icp_for_pair(config.icp, self.full[1], self.voxel, self.scans))
        clock.lap("clean")
        # The network's samples, normalised together (own centroids, one common scale).
        self.norm = normalisation_for(*self.full)
        self.distance = config.icp.distance_for(self.norm.scale)  # ICP's d, cloud units
        self.net: Clouds = (
            sample_points(self.full[0], config.num_points, seed=config.seed),
            sample_points(self.full[1], config.num_points, seed=config.seed + 1),
        )
        src_norm, tgt_norm, _ = normalise_pair(*self.net, self.norm)
        self.net_normalised: Clouds = (src_norm, tgt_norm)
        clock.lap("sample_normalise")
        self.work: Clouds = self.full
        if not (prepared and max(map(len, self.full)) <= min(GRID_WORK_ATTEMPTS * config.attempt_points, config.icp.max_points)):
            self.work = (refine_stage.downsample(self.full[0], config.attempt_points), refine_stage.downsample(self.full[1], config.attempt_points))
        self._scorers: Dict[Tuple[str, bool], confidence_stage.Scorer] = {}
        self._normals: Dict[str, np.ndarray] = {}
        self._trees: Dict[str, KDTree] = {}

    @cached_property
    def size_ratio(self) -> float:
        """The larger cleaned cloud's :func:`~o3dsoft.preprocess.scene_size` over the smaller's:
        far from 1 for clouds in different units, or unrelated ones."""
        sizes = [scene_size(report.points) for report in self.cleaned]
        return max(sizes) / max(min(sizes), 1e-300)

    @property
    def reduced(self) -> bool:
        """The work clouds are smaller than the full ones (the kept estimate is refined again)."""
        return any(len(w) < len(f) for w, f in zip(self.work, self.full))

    @property
    def screening(self) -> bool:
        """The search's estimates, and the network's on scans, are tried on the screen clouds
        first (large work clouds)."""
        return self.config.refine and max(map(len, self.work)) > self.config.search.screen.points

    @cached_property
    def screen(self) -> Clouds:
        limit, seed = self.config.search.screen.points, self.config.seed
        src, tgt = (
            refine_stage.downsample(c, limit) if len(c) > limit else sample_points(c, limit, seed=seed + offset)
            for offset, c in ((4, self.work[0]), (5, self.work[1]))
        )
        return src, tgt

    def clouds(self, level: str) -> Clouds:
        """The clouds at `level`: "full", "work" or "screen"."""
        if level not in ("full", "work", "screen"):
            raise ValueError(f"level must be full, work or screen, got {level!r}")
        return getattr(self, level)

    def target_normals(self, level: str) -> Optional[np.ndarray]:
        """(M, 3) normals of the target at `level` for point-to-plane ICP (and, on scans, the
        confidence's planar share), estimated once; None when ICP is point-to-point."""
        if self.config.icp.method != "plane":
            return None
        if level not in self._normals:
            self._normals[level] = refine_stage.normals(self.clouds(level)[1], self.config.icp.normal_neighbours, self.config.icp.normal_within)
        return self._normals[level]

    def target_tree(self, level: str) -> Optional[KDTree]:
        """The target's :func:`~o3dsoft.refine.kd_tree` at `level`, for point-to-plane ICP's
        pairs, built once; None when ICP is point-to-point, or downsamples the target first
        (above ``icp.max_points``)."""
        if self.config.icp.method != "plane" or len(self.clouds(level)[1]) > self.config.icp.max_points:
            return None
        if level not in self._trees:
            self._trees[level] = refine_stage.kd_tree(self.clouds(level)[1])
        return self._trees[level]

    def scorer(self, level: str, reverse: bool = False) -> confidence_stage.Scorer:
        """The confidence's scorer of the clouds at `level`, built once; `reverse`: of the target
        onto the source (the alignment seen from the target's side; call it with the inverse
        pose), without the planar share."""
        key = (level, reverse)
        if key not in self._scorers:
            d = self.config.confidence.distance * self.norm.scale  # the confidence's own d, whatever ICP's
            source, target = self.clouds(level)
            if reverse:
                self._scorers[key] = confidence_stage.Scorer(target, source, d, self.config.icp.max_points, self.config.confidence)
            else:
                normals = self.target_normals(level) if self.scans else None  # for the scan confidence's planar share
                self._scorers[key] = confidence_stage.Scorer(source, target, d, self.config.icp.max_points, self.config.confidence, normals)
        return self._scorers[key]

    @cached_property
    def feature_match(self) -> FeatureMatch:
        """FPFH features of the full clouds, matched by the search's RANSAC (computed once)."""
        return FeatureMatch(*self.full, self.norm.scale, self.config.search.features.match)

    @cached_property
    def looks_partial(self) -> bool:
        """The clouds' distances to their centroids differ (a partial overlap, most likely)."""
        return same_profile_pvalue(*self.net) < self.config.search.partial_pvalue

    @property
    def complete(self) -> bool:
        """Both clouds look like complete samplings of one shape: not scans, and the same profile
        of distances to their centroids (:attr:`looks_partial` false)."""
        return not self.scans and not self.looks_partial
