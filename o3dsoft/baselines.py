"""The peers o3dsoft is compared with on the same pairs: Open3D's FPFH features matched by RANSAC
or by Fast Global Registration (FGR), and KISS-Matcher followed by small_gicp's GICP (optional
packages, :class:`KissConfig`).

Parameters follow Open3D's global registration tutorial, expressed relative to the pair's scale
(the larger radius of the two clouds around their centroids; 1 for ModelNet40 shapes) so that the
same settings serve unit-sphere objects and scans in metres: voxel 0.05, normals radius 2 voxels
(30 neighbours), FPFH radius 5 voxels (100 neighbours), RANSAC distance 1.5 voxels with the
edge-length (0.9) and distance checkers, 100,000 iterations at confidence 0.999, FGR distance
0.5 voxel. As in the tutorial, the normals keep the sign Open3D's estimate gives them, which
depends on the frame the cloud is given in, so the features of a rotated copy differ; the
search's feature match orients them (:class:`o3dsoft.search.FeatureMatchConfig`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple, Optional, Tuple

import numpy as np

from ._open3d import open3d as o3d
from .preprocess import local_origin, stray_points
from .refine import to_open3d
from .transforms import in_frame_at, rigid


@dataclass(frozen=True)
class GlobalConfig:
    """Settings of FPFH + RANSAC and FGR, each relative to the pair's scale.

    Attributes:
        voxel: voxel size of the downsampling before features.
        normal_radius, normal_max_nn: normal estimation (radius in voxels).
        fpfh_radius, fpfh_max_nn: FPFH feature neighbourhood (radius in voxels).
        ransac_distance: RANSAC inlier distance (in voxels).
        ransac_iterations, ransac_confidence, ransac_n, edge_length: RANSAC's criteria and checker.
        fgr_distance: FGR's maximum correspondence distance (in voxels).
        orient_normals: point every normal towards the downsampled cloud's centroid. FPFH
            depends on the normals' signs, and those Open3D's estimate gives follow the frame
            the cloud is given in; oriented, the features of two rotated copies of a cloud agree.
    """

    voxel: float = 0.05
    normal_radius: float = 2.0
    normal_max_nn: int = 30
    fpfh_radius: float = 5.0
    fpfh_max_nn: int = 100
    ransac_distance: float = 1.5
    ransac_iterations: int = 100_000
    ransac_confidence: float = 0.999
    ransac_n: int = 3
    edge_length: float = 0.9
    fgr_distance: float = 0.5
    orient_normals: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


class Features(NamedTuple):
    """A downsampled cloud (Open3D PointCloud with normals) and its FPFH features (33 x N')."""

    cloud: "o3d.geometry.PointCloud"
    fpfh: "o3d.pipelines.registration.Feature"


def fpfh_features(points: np.ndarray, scale: float, config: GlobalConfig = GlobalConfig()) -> Features:
    """Voxel-downsample (N, 3) points, estimate normals and compute FPFH features."""
    voxel = config.voxel * scale
    cloud = to_open3d(points).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=config.normal_radius * voxel, max_nn=config.normal_max_nn))
    if config.orient_normals:
        cloud.orient_normals_towards_camera_location(np.asarray(cloud.points).mean(axis=0))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=config.fpfh_radius * voxel, max_nn=config.fpfh_max_nn)
    )
    return Features(cloud, fpfh)


def ransac(source: Features, target: Features, scale: float, seed: int, config: GlobalConfig = GlobalConfig()) -> np.ndarray:
    """(4, 4) T_target_source from FPFH matches by RANSAC (Open3D), with Open3D's random seed set.

    Open3D runs RANSAC's hypotheses on several threads, so with the correspondence checkers the
    result can still differ between runs on the same input and seed (Open3D issue #7475); on the
    bunny scans bun000 -> bun090, seed 2 gave 24.9 deg off once and 112.0 deg three times.
    """
    reg = o3d.pipelines.registration
    distance = config.ransac_distance * config.voxel * scale
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        source.cloud,
        target.cloud,
        source.fpfh,
        target.fpfh,
        True,
        distance,
        reg.TransformationEstimationPointToPoint(False),
        config.ransac_n,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(config.edge_length), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(config.ransac_iterations, config.ransac_confidence),
    )
    return np.asarray(result.transformation).copy()


def fgr(source: Features, target: Features, scale: float, config: GlobalConfig = GlobalConfig()) -> np.ndarray:
    """(4, 4) T_target_source from FPFH matches by Fast Global Registration (Open3D)."""
    reg = o3d.pipelines.registration
    option = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=config.fgr_distance * config.voxel * scale)
    result = reg.registration_fgr_based_on_feature_matching(source.cloud, target.cloud, source.fpfh, target.fpfh, option)
    return np.asarray(result.transformation).copy()


def installed(*packages: str) -> bool:
    """Whether every one of these optional packages (``o3dsoft[peers]``) can be imported."""
    import importlib.util

    return all(importlib.util.find_spec(name) is not None for name in packages)


@dataclass(frozen=True)
class KissConfig:
    """KISS-Matcher (coarse) followed by small_gicp's GICP (fine): the pip packages
    ``kiss-matcher`` and ``small-gicp`` (``pip install o3dsoft[peers]``).

    Attributes:
        voxel: KISS-Matcher's voxel size, as a share of the scene's size (the diagonal of the box
            holding the central 98 % of the larger cloud): 0.01, i.e. 4 cm on a 4 m RGB-D
            fragment, 2 mm on a 20 cm object. KISS-Matcher's other settings are its defaults.
        gicp_downsampling: GICP's voxel grid, in KISS-Matcher voxels (0.5).
        gicp_distance: GICP's maximum correspondence distance, in KISS-Matcher voxels (2).
        threads: GICP's threads (2).
    """

    voxel: float = 0.01
    gicp_downsampling: float = 0.5
    gicp_distance: float = 2.0
    threads: int = 2

    def to_dict(self) -> dict:
        return asdict(self)


# KISS-Matcher is made for scans in metres: it refuses voxels below a few centimetres, and some of
# its thresholds are absolute (a 3DMatch fragment in millimetres fails where the same in metres
# does not, every setting scaled). Every scene is given to it scaled so that its voxel is this,
# and the result scaled back: its answer does not depend on the clouds' units.
_KISS_VOXEL = 0.05
# KISS-Matcher crashes the process (a segmentation fault) on clouds of a few hundred points or
# fewer: it is called only where each cloud keeps at least this many points on its voxel grid.
KISS_MIN_POINTS = 500
# It hashes integer voxel coordinates and takes float32 points: it crashes on coordinates more than
# about 2e9 voxels from the origin (georeferenced scans: 4e6 m of UTM northing over a 2 mm voxel),
# and float32 rounds them to metres. A cloud far from the origin is given to it about its own
# median (:func:`o3dsoft.preprocess.local_origin`), without its strays
# (:func:`o3dsoft.preprocess.stray_points`: without them a cloud spans at most about 10^5 voxels).


def kiss_matcher(
    source: np.ndarray, target: np.ndarray, voxel: float, normal_radius: Optional[float] = None, feature_radius: Optional[float] = None
) -> Optional[np.ndarray]:
    """(4, 4) T_target_source from KISS-Matcher at `voxel` (cloud units) on (N, 3) and (M, 3);
    None where either cloud keeps fewer than :data:`KISS_MIN_POINTS` points on a grid of `voxel`
    (too few for it). `normal_radius`, `feature_radius`: its normals' and FPFH features' radii in
    voxels (None: KISS-Matcher's own, 3 and 5)."""
    import kiss_matcher as km  # optional: o3dsoft[peers]
    from threadpoolctl import threadpool_limits

    (source, source_centre), (target, target_centre) = _local(source), _local(target)
    source, target = _kiss_grid(source, voxel), _kiss_grid(target, voxel)
    if min(len(source), len(target)) < KISS_MIN_POINTS:
        return None
    magnify = _KISS_VOXEL / voxel
    magnified_voxel = voxel * magnify
    # Its matching's OpenMP threads add matches in the order they finish, and its answer hangs on
    # that order: one thread, no slower. (A race between its TBB threads is left: about 1 call in
    # 100 still differs; docs/scans.md.)
    with threadpool_limits(1, user_api="openmp"):
        config = km.KISSMatcherConfig(magnified_voxel, use_voxel_sampling=False)
        if normal_radius is not None:
            config.normal_radius = normal_radius * magnified_voxel
        if feature_radius is not None:
            config.fpfh_radius = feature_radius * magnified_voxel
        matcher = km.KISSMatcher(config)
        solution = matcher.estimate((magnify * source).astype(np.float32), (magnify * target).astype(np.float32))
    # target - ct = R (source - cs) + t, so T_target_source's translation is t + ct - R cs.
    R = np.asarray(solution.rotation, dtype=np.float64)
    return rigid(R, np.asarray(solution.translation, dtype=np.float64).ravel() / magnify + target_centre - R @ source_centre)


def _kiss_grid(points: np.ndarray, voxel: float) -> np.ndarray:
    """(K, 3) the centroids of the (N, 3) points in each occupied cell of a grid of `voxel` with a
    corner at the origin, in the order of the cells' (z, y, x): KISS-Matcher's own grid, taken here
    because KISS-Matcher writes its threads' cells in the order they finish, and its answer hangs on
    that order."""
    if len(points) == 0:
        return np.empty((0, 3))
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if int(span[0]) * int(span[1]) * int(span[2]) < 2**62:  # one integer key per cell, z slowest
        _, inverse, counts = np.unique((cells[:, 2] * span[1] + cells[:, 1]) * span[0] + cells[:, 0], return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(cells[:, ::-1], axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    return np.column_stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)]) / counts[:, None]


def _local(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(N', 3) the points less their (3,) :func:`~o3dsoft.preprocess.local_origin`, without their
    :func:`~o3dsoft.preprocess.stray_points` and those with a non-finite coordinate; and that origin."""
    points = np.asarray(points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    origin = local_origin(points)
    return points[~stray_points(points)] - origin, origin


def small_gicp(source: np.ndarray, target: np.ndarray, init: np.ndarray, voxel: float, config: KissConfig = KissConfig()) -> np.ndarray:
    """(4, 4) T_target_source refined from `init` by small_gicp's GICP (both clouds moved by the
    target's :func:`~o3dsoft.preprocess.local_origin` first: its voxel grid hashes integer
    coordinates)."""
    import small_gicp as sg  # optional: o3dsoft[peers]

    origin = local_origin(target)
    result = sg.align(
        np.ascontiguousarray(target - origin, np.float64),
        np.ascontiguousarray(source - origin, np.float64),
        in_frame_at(init, origin),
        registration_type="GICP",
        downsampling_resolution=config.gicp_downsampling * voxel,
        max_correspondence_distance=config.gicp_distance * voxel,
        num_threads=config.threads,
    )
    return in_frame_at(result.T_target_source, -origin)
