"""Benchmark harness: every method on the very same pairs, scored with the literature's metrics
(:mod:`o3dsoft.metrics`; the protocols and metrics are described in docs/results.md).

Pairs come from ModelNet40 under the protocols of :mod:`o3dsoft.data`, from real scans with a
``.conf`` of ground-truth poses (:func:`scan_pairs`), or from a pairs file
(:func:`import_pairs`). Each pair is run through the chosen methods; one row per (pair, method)
holds the errors and the time of each stage. :func:`run` writes the run folder (per-pair CSV,
JSON summary, the config, versions, plots).
"""

from __future__ import annotations

import csv
import functools
import json
import os
import platform
import signal
import subprocess
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from . import baselines
from . import refine as refine_stage
from .coarse import CoarseModel, sha256_of, weights_file
from .data import DEFAULT_POINTS_PER_SHAPE, get_protocol, load_pairs
from .errors import InputError, O3dsoftError, UsageError, counted, first_line, release_interrupt, spawn_context, terminate_as_interrupt
from .io import atomic_output, make_folder
from .metrics import MODELNET_RECALL, PairErrors, input_chamfer_distance, modified_chamfer_distance, pair_errors, summarise, within
from .pair import are_scans, icp_for_pair, registration_grid
from .pipeline import RegisterConfig, register
from .preprocess import clean_points, local_origin, normalisation_for, scene_size, voxel_downsample
from .transforms import apply_transform, in_frame_at, random_rotation, rigid, rotation_angle_deg

METHODS: Dict[str, str] = {
    "oracle": "Open3D ICP started at the ground truth (the floor the sampling sets)",
    "o3dsoft-coarse": "o3dsoft network alone",
    "o3dsoft": "o3dsoft network + ICP",
    "icp": "Open3D ICP from the identity",
    "fpfh-ransac": "Open3D FPFH + RANSAC",
    "fpfh-ransac+icp": "Open3D FPFH + RANSAC + ICP",
    "fgr": "Open3D FPFH + FGR",
    "fgr+icp": "Open3D FPFH + FGR + ICP",
    "kiss-matcher": "KISS-Matcher",
    "kiss-matcher+gicp": "KISS-Matcher + small_gicp GICP",
}
# Methods from optional packages (pip install 'o3dsoft[peers]'), left out unless asked for.
PEER_METHODS = ("kiss-matcher", "kiss-matcher+gicp")
CORE_METHODS = tuple(m for m in METHODS if m not in PEER_METHODS)
# ModelNet40 categories whose shapes are (nearly) rotationally symmetric, where a rotation error
# about the axis is meaningless; excluded in the second row of each protocol, as OMNet does.
SYMMETRIC_CATEGORIES = ("bottle", "bowl", "cone", "cup", "flower_pot", "lamp", "tent", "vase")
# A failure whose input Chamfer distance is at most this many times the oracle's fits the clouds as
# well as the truth does (right results of complete, independently sampled pairs reach 1.06-1.08 at
# the 99th percentile; on partial overlaps the parts without a partner dominate the distance and
# right results reach 1.22, so there the count says less; docs/incongruent.md).
AS_TRUTH = 1.1
# The literature's protocols, then the same with independently sampled clouds (no point shared).
BENCH_PROTOCOLS = (
    "paper",
    "dcp",
    "dcp-unseen",
    "dcp-noise",
    "rpmnet-crop",
    "so3",
    "so3-crop",
    "incongruent",
    "incongruent-noise",
    "incongruent-crop",
    "incongruent-so3",
)
STAGES = ("features", "coarse", "search", "ransac", "fgr", "kiss", "icp", "total")
PAIRS_FORMAT = "o3dsoft-pairs"


@dataclass
class BenchConfig:
    """Settings of a benchmark run (saved as config.json in the run folder).

    Attributes:
        methods: names from METHODS, in the order of the table.
        register: o3dsoft's settings (its ICP, point-to-plane on scans as in ``register``, is
            also the one after every '+icp' baseline and the oracle's: :func:`peer_settings`).
        identity_icp: Open3D ICP from the identity: correspondence distance, relative to the
            pair's scale, refined over the same schedule.
        global_: FPFH + RANSAC / FGR settings (on scans their voxel is the grid ``register``
            uses: :func:`peer_settings`).
        kiss: KISS-Matcher + small_gicp settings.
        seed: seed of the pairs and of RANSAC.
        recall: (degrees, distance in cloud units) thresholds of the recall columns, tightest
            first; the last is the test of success for the confidence's ROC AUC and false alarms.
        recall_by_protocol: other thresholds for some protocols (real scans of each kind).
    """

    methods: Tuple[str, ...] = CORE_METHODS
    register: RegisterConfig = field(default_factory=RegisterConfig)
    identity_icp: refine_stage.ICPConfig = field(default_factory=lambda: refine_stage.ICPConfig(distance=0.2))
    global_: baselines.GlobalConfig = field(default_factory=baselines.GlobalConfig)
    kiss: baselines.KissConfig = field(default_factory=baselines.KissConfig)
    seed: int = 0
    recall: Tuple[Tuple[float, float], ...] = MODELNET_RECALL
    recall_by_protocol: Dict[str, Tuple[Tuple[float, float], ...]] = field(default_factory=dict)

    def recall_for(self, protocol: str) -> Tuple[Tuple[float, float], ...]:
        return self.recall_by_protocol.get(protocol, self.recall)

    def to_dict(self) -> dict:
        return asdict(self)


def check_methods(names: Sequence[str]) -> Tuple[str, ...]:
    """The names, checked; UsageError listing the valid ones, or naming the missing package of a
    peer's method, otherwise."""
    bad = [n for n in names if n not in METHODS]
    if bad:
        raise UsageError(f"unknown method {bad[0]!r}; valid: {', '.join(METHODS)}")
    if set(names) & set(PEER_METHODS) and not peers_installed():
        raise UsageError("the KISS-Matcher methods need the packages kiss-matcher and small-gicp: pip install 'o3dsoft[peers]'")
    return tuple(dict.fromkeys(names))


def peers_installed() -> bool:
    """Whether the optional packages of :data:`PEER_METHODS` can be imported."""
    return baselines.installed("kiss_matcher", "small_gicp")


class BenchPair(NamedTuple):
    """One problem: target ~ transform @ source.

    source (N, 3), target (M, 3); transform (4, 4) T_target_source; protocol and index name the
    pair; category is the shape's (or the scan pair's) name; clean_target (L, 3): the complete,
    noise-free target for the modified Chamfer distance (None: the target itself); origin (3,):
    the point the errors are measured about, as :func:`o3dsoft.metrics.pair_errors` takes it
    (None: the frame's origin, as the literature measures ModelNet40's pairs; scans: the
    target's :func:`~o3dsoft.preprocess.local_origin`, their median where they lie far from it).
    """

    protocol: str
    index: int
    source: np.ndarray
    target: np.ndarray
    transform: np.ndarray
    category: str
    clean_target: Optional[np.ndarray] = None
    origin: Optional[np.ndarray] = None

    @property
    def initial_angle(self) -> float:
        return rotation_angle_deg(self.transform[:3, :3])


# --------------------------------------------------------------------------------------------
# Pair sources
# --------------------------------------------------------------------------------------------
def modelnet_pairs(
    data: Optional[str], protocols: Sequence[str], limit: Optional[int], seed: int, points_per_shape: Optional[int] = DEFAULT_POINTS_PER_SHAPE
) -> Tuple[int, Iterator[BenchPair]]:
    """(count, iterator) of the test pairs of each protocol, the first `limit` of each, from the
    first `points_per_shape` points of each shape (None: all; the incongruent protocols split them
    in two)."""
    datasets = []
    for name in protocols:
        protocol = get_protocol(name)
        ds = load_pairs(data, "test", protocol, seed, points_per_shape)
        if len(ds) == 0:
            unseen = (
                f" (it takes the test shapes of the second half of 40 categories, labels 20-39; the data has {len(ds.shapes.categories)})"
                if protocol.categories == "unseen"
                else ""
            )
            raise InputError(f"protocol {name!r} has no test pairs in this data{unseen}; leave it out (--protocol)")
        datasets.append((name, ds, len(ds) if limit is None else min(limit, len(ds))))

    def generate() -> Iterator[BenchPair]:
        for name, ds, n in datasets:
            for i in range(n):
                p = ds[i]
                clean = apply_transform(p.transform, ds.shapes.points[i].astype(np.float64))
                yield BenchPair(name, i, p.source, p.target, p.transform, ds.shapes.categories[p.label], clean)

    return sum(n for _, _, n in datasets), generate()


class ScanFolder(NamedTuple):
    """The pairs of one folder of real scans and how they are judged.

    name: the folder's name. pairs: every pair to run (protocol: the name). kind: a name of
    :data:`o3dsoft.scans.KINDS`. recall: its thresholds in the scans' units. table: every
    candidate pair, with its ground-truth overlap and whether it was kept. left_out: (file name,
    count) of the points with a non-finite coordinate each scan had (every method gets the rest).
    """

    name: str
    pairs: List[BenchPair]
    kind: str
    recall: Tuple[Tuple[float, float], ...]
    table: List[dict]
    left_out: Tuple[Tuple[str, int], ...] = ()
    guessed_from: Optional[float] = None  # the first scan's size (units) `kind` was guessed from; None: given
    path: str = ""  # the folder, absolute: where a run's scans came from


def scan_folder(folder: Path, min_overlap: float = 0.3, kind: str = "auto", unit: str = "m") -> ScanFolder:
    """The pairs of a folder of real scans: those its ``pairs.txt`` lists, or, with a Stanford
    ``.conf`` instead, every ordered pair whose ground-truth overlap is at least `min_overlap`.

    Overlap = share of the source's points within 0.01 x scale (1 mm on the bunny) of a target
    point once placed by the ground truth. `kind` "auto": from the size of the first scan
    (:func:`o3dsoft.scans.guess_kind`). `unit`: the scans' unit, a name of
    :data:`o3dsoft.scans.UNITS` (the RGB-D and LiDAR tests are in metres).
    """
    from scipy.spatial import cKDTree

    from .io import read_points, read_transform
    from .scans import UNITS, guess_kind, read_conf, read_pairs_file, recall_thresholds, relative_pose

    folder = Path(folder)
    if unit not in UNITS:
        raise UsageError(f"unknown unit {unit!r}; valid: {', '.join(UNITS)}")
    if not folder.is_dir():
        raise UsageError(f"{folder}: no such folder of scans")
    name = folder.resolve().name
    listed = folder / "pairs.txt"
    if listed.is_file():
        clouds: Dict[Path, np.ndarray] = {}
        candidates = []
        first: Dict[Tuple[Path, Path], int] = {}  # the line of each pair
        for entry in read_pairs_file(listed):
            key = (entry.source.resolve(), entry.target.resolve())
            if key[0] == key[1]:
                raise InputError(f"{listed}, line {entry.line}: pairs {entry.source.name} with itself")
            if key in first:  # it would count twice in every recall
                raise InputError(f"{listed}, line {entry.line}: the pair of line {first[key]} again")
            first[key] = entry.line
            for path in (entry.source, entry.target):
                if path not in clouds:
                    clouds[path] = read_points(path)
            candidates.append((entry.source, entry.target, read_transform(entry.transform, local_origin(clouds[entry.source]))))
    else:
        confs = sorted(folder.glob("*.conf"))
        if len(confs) != 1:
            raise InputError(f"{folder}: expected a pairs.txt or one .conf file of scan poses, found {len(confs)} .conf files")
        poses = read_conf(confs[0])
        clouds, names = {}, {}
        for scan in poses:
            path = folder / scan if Path(scan).suffix else folder / f"{scan}.ply"
            if not path.is_file():
                raise InputError(f"{confs[0]}: scan {scan!r} has no file {path.name} in {folder}")
            clouds[path], names[scan] = read_points(path), path
        candidates = [(names[s], names[t], relative_pose(poses, s, t)) for s in poses for t in poses if s != t]
    # Organised scans (a depth image's pixels without a return) carry NaN rows; register's clean
    # stage drops them, and every method here gets the same finite points.
    finite = {path: np.isfinite(points).all(axis=1) for path, points in clouds.items()}
    left_out = tuple((path.name, int((~keep).sum())) for path, keep in finite.items() if not keep.all())
    clouds = {path: points[finite[path]] for path, points in clouds.items()}
    empty = [path.name for path, points in clouds.items() if len(points) == 0]
    if empty:
        raise InputError(f"{folder}: {empty[0]} holds no point with finite coordinates")
    trees = {path: cKDTree(points) for path, points in clouds.items()}
    stems = [path.stem for path in clouds]
    label = {path: path.stem if stems.count(path.stem) == 1 else _relative_name(path, folder) for path in clouds}  # a/scan.ply, b/scan.ply
    pairs, table = [], []
    for s, t, T in candidates:
        scale = normalisation_for(clouds[s], clouds[t]).scale
        d, _ = trees[t].query(apply_transform(T, clouds[s]), distance_upper_bound=0.01 * scale)
        overlap = float(np.mean(np.isfinite(d)))
        keep = listed.is_file() or overlap >= min_overlap
        table.append({"source": label[s], "target": label[t], "overlap": overlap, "kept": keep})
        if keep:
            pairs.append(BenchPair(name, len(pairs), clouds[s], clouds[t], T, f"{label[s]}->{label[t]}", origin=local_origin(clouds[t])))
    size = scene_size(next(iter(clouds.values())))  # of the first scan
    guessed = size if kind == "auto" else None
    kind = guess_kind(size * UNITS[unit]) if kind == "auto" else kind
    return ScanFolder(name, pairs, kind, recall_thresholds(kind, size, UNITS[unit]), table, left_out, guessed, str(Path(folder).resolve()))


def _relative_name(path: Path, folder: Path) -> str:
    """`path` without its suffix, relative to `folder` where it lies in it: "a/scan"."""
    try:
        return path.resolve().relative_to(folder.resolve()).with_suffix("").as_posix()
    except ValueError:
        return path.with_suffix("").as_posix()


def turned_pairs(pairs: Sequence[BenchPair], turns: int, seed: int = 0) -> List[BenchPair]:
    """`turns` copies of each pair, the source turned about its centroid by a uniform random
    rotation (seeded by `seed`, the pair's index and the turn) and the ground truth turned with it,
    under the protocol ``"<protocol> turned"``: scans come in the frames their scanner saved them
    in, and what a method does on a few pairs can hang on those frames (voxel grids and normal
    signs follow them). Indices count the turned pairs of each protocol from 0."""
    turned = []
    for p in pairs:
        centre = p.source.mean(axis=0)
        for k in range(turns):
            R = random_rotation(np.random.default_rng([seed, p.index, k]))
            M = rigid(R, centre - R @ centre)  # source' = M source
            source = apply_transform(M, p.source.astype(np.float64)).astype(p.source.dtype)
            turned.append(p._replace(protocol=turned_protocol(p.protocol), index=p.index * turns + k, source=source, transform=p.transform @ np.linalg.inv(M)))
    return turned


def turned_protocol(protocol: str) -> str:
    """The protocol name of `protocol`'s turned pairs (:func:`turned_pairs`)."""
    return f"{protocol} turned"


def noisy_pairs(pairs: Sequence[BenchPair], sigma: float, seed: int = 0) -> List[BenchPair]:
    """A copy of each pair with Gaussian noise of standard deviation `sigma` x the target's
    :func:`~o3dsoft.preprocess.scene_size` added to every coordinate of both clouds (seeded by
    `seed` and the pair's index; the truth unchanged), under the protocol ``"<protocol> noise
    <100 sigma> %"``: how each method and its confidence hold up on noisier sensors than the
    folder's. Indices as in the pairs; none for `sigma` 0."""
    if sigma <= 0:
        return []
    noisy = []
    for p in pairs:
        rng = np.random.default_rng([seed, p.index])
        scale = sigma * scene_size(p.target)
        source, target = (c + rng.normal(scale=scale, size=c.shape).astype(c.dtype) for c in (p.source, p.target))
        noisy.append(p._replace(protocol=noise_protocol(p.protocol, sigma), source=source, target=target))
    return noisy


def noise_protocol(protocol: str, sigma: float) -> str:
    """The protocol name of `protocol`'s pairs with noise `sigma` (:func:`noisy_pairs`)."""
    return f"{protocol} noise {100 * sigma:g} %"


def export_pairs(path: Path, pairs: Sequence[BenchPair]) -> None:
    """Write pairs to an .npz any tool can read: points concatenated with offsets.

    Keys: format, source_points (sum N, 3), source_offsets (P + 1), target_points, target_offsets,
    transform (P, 4, 4) T_target_source, protocol (P,) str, index (P,), category (P,) str, and
    (when every pair has one) clean_target_points / clean_target_offsets: the complete, noise-free
    target of the modified Chamfer distance.
    """

    def offsets(clouds):
        return np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)

    clean = {}
    if pairs and all(p.clean_target is not None for p in pairs):
        clean = {
            "clean_target_points": np.concatenate([p.clean_target for p in pairs]).astype(np.float32),
            "clean_target_offsets": offsets([p.clean_target for p in pairs]),
        }
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(
                f,
                format=np.array(PAIRS_FORMAT),
                source_points=np.concatenate([p.source for p in pairs]).astype(np.float32),
                source_offsets=offsets([p.source for p in pairs]),
                target_points=np.concatenate([p.target for p in pairs]).astype(np.float32),
                target_offsets=offsets([p.target for p in pairs]),
                transform=np.stack([p.transform for p in pairs]).astype(np.float64),
                protocol=np.array([p.protocol for p in pairs]),
                index=np.array([p.index for p in pairs], dtype=np.int64),
                category=np.array([p.category for p in pairs]),
                **clean,
            )


def import_pairs(path: Path) -> List[BenchPair]:
    """Read a pairs file written by :func:`export_pairs` (or by any tool in that format).

    Raises:
        UsageError: no such file.
        InputError: not an .npz, a missing key, or arrays of inconsistent shapes (named).
    """
    from .scans import check_pairs_file

    path = Path(path)
    check_pairs_file(path)
    with open(path, "rb") as f:
        head = f.read(6)
    if not head.startswith(b"PK") and head != b"\x93NUMPY":  # neither a zip of arrays nor one array
        raise InputError(f"{path}: not a pairs file (.npz: a zip of named arrays, as --export-pairs writes)")
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises several types for non-npz files
        raise InputError(f"{path}: not a pairs file (.npz): {e}") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: a single array, not a pairs file (.npz with named arrays)")
    try:
        return _pairs_from_npz(path, z)
    except InputError:
        raise
    except ValueError as e:  # object arrays, which need pickle, and other unreadable entries
        raise InputError(f"{path}: unreadable pairs file ({e})") from None


def _pairs_from_npz(path: Path, z) -> List[BenchPair]:
    need = ("source_points", "source_offsets", "target_points", "target_offsets", "transform", "protocol", "index")
    missing = [k for k in need if k not in z.files]
    if missing:
        raise InputError(f"{path}: missing array(s) {', '.join(missing)}; a pairs file has {', '.join(need)}")
    P = len(z["transform"])
    for side in ("source", "target"):
        pts, off = z[f"{side}_points"], z[f"{side}_offsets"]
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"{path}: {side}_points must be (N, 3), got {pts.shape}")
        if off.shape != (P + 1,) or off[0] != 0 or off[-1] != len(pts) or np.any(np.diff(off) <= 0):
            raise InputError(f"{path}: {side}_offsets must rise from 0 to {len(pts)} in {P + 1} steps")
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            first = int(np.searchsorted(off, np.argmax(bad), side="right")) - 1
            raise InputError(
                f"{path}: pair {first}'s {side} has points with a non-finite coordinate ({int(bad.sum())} in all); a pairs file holds finite points"
            )
    if z["transform"].shape != (P, 4, 4) or z["protocol"].shape != (P,) or z["index"].shape != (P,):
        raise InputError(f"{path}: transform must be (P, 4, 4) with one protocol and index per pair")
    category = z["category"] if "category" in z.files else np.array([""] * P)
    if category.shape != (P,):
        raise InputError(f"{path}: category must hold one name per pair ({P}), got shape {category.shape}")
    s_off, t_off = z["source_offsets"], z["target_offsets"]
    clean = None
    if "clean_target_points" in z.files and "clean_target_offsets" in z.files:
        clean, c_off = z["clean_target_points"], z["clean_target_offsets"]
        if c_off.shape != (P + 1,) or c_off[-1] != len(clean):
            raise InputError(f"{path}: clean_target_offsets must have {P + 1} entries ending at {len(clean)}")
    return [
        BenchPair(
            str(z["protocol"][i]),
            int(z["index"][i]),
            z["source_points"][s_off[i] : s_off[i + 1]].astype(np.float64),
            z["target_points"][t_off[i] : t_off[i + 1]].astype(np.float64),
            z["transform"][i].astype(np.float64),
            str(category[i]),
            None if clean is None else clean[c_off[i] : c_off[i + 1]].astype(np.float64),
        )
        for i in range(P)
    ]


# --------------------------------------------------------------------------------------------
# Running the methods
# --------------------------------------------------------------------------------------------
class MethodResult(NamedTuple):
    """One method on one pair: its estimate, the time of each stage (ms), and o3dsoft's
    confidence in it, whether its search ran and why (None for methods that give none)."""

    method: str
    transform: np.ndarray
    times_ms: Dict[str, float]
    confidence: Optional[float] = None
    searched: Optional[bool] = None
    search_reason: Optional[str] = None
    error: Optional[str] = None  # why the method raised on this pair: then the pose as given (identity) is scored


def peer_settings(source: np.ndarray, target: np.ndarray, config: BenchConfig, scale: float) -> Tuple[refine_stage.ICPConfig, baselines.GlobalConfig]:
    """How the oracle and the peers run on one pair of (N, 3) and (M, 3) clouds of `scale` (the
    larger radius, cloud units): the ICP method ``register`` decides for such a pair
    (point-to-plane on scans, :func:`o3dsoft.pair.icp_for_pair`), run on the clouds as given
    (normals from the nearest points, as off a grid); and the FPFH settings, on scans on the grid
    ``register`` would use (Open3D's tutorial takes 5 cm on RGB-D fragments in metres, where that
    grid is 3.7 cm and 0.05 of the scale 9-10 cm), else 0.05 of the scale.

    Raises:
        InputError: a cloud ``register`` would refuse (fewer than two distinct finite points, ...).
    """
    cleaned = (clean_points(source, "source", min_points=2).points, clean_points(target, "target", min_points=2).points)
    grid = registration_grid(cleaned, config.register)
    scans = are_scans(cleaned, grid)
    target = cleaned[1] if grid is None else voxel_downsample(cleaned[1], grid, "target")  # flat or not, as register sees it
    icp = icp_for_pair(config.register.icp, target, None, scans)
    global_ = replace(config.global_, voxel=grid / scale) if scans and grid is not None else config.global_
    return icp, global_


def peer_icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, distance: float, config: refine_stage.ICPConfig) -> np.ndarray:
    """(4, 4) T_target_source: ICP from `init` on (N, 3) and (M, 3), both moved by the target's
    :func:`~o3dsoft.preprocess.local_origin` first as ``register`` moves them: point-to-plane ICP
    linearises the rotation about the origin, and on georeferenced clouds that lies far off."""
    origin = local_origin(target)
    T = refine_stage.icp(source - origin, target - origin, in_frame_at(init, origin), distance, config).transformation
    return in_frame_at(T, -origin)


def run_methods(pair: BenchPair, config: BenchConfig, model: Optional[CoarseModel], search_model: Optional[CoarseModel] = None) -> List[MethodResult]:
    """Run every method of `config` on one pair (`search_model`: o3dsoft's search network, else
    loaded when needed)."""
    methods = config.methods
    src, tgt = pair.source.astype(np.float64), pair.target.astype(np.float64)
    scale = normalisation_for(src, tgt).scale
    icp_distance = config.register.icp.distance_for(scale)
    out: Dict[str, MethodResult] = {}

    def clock() -> float:
        return time.perf_counter() * 1000.0

    def each(names: Sequence[str], run: Callable[[], None]) -> None:
        """run() adds the results of the methods `names` (those asked) to `out`; where it raises on
        this pair, each of them it did not add is scored as the pose as given, with the error."""
        asked = [m for m in names if m in methods]
        if not asked:
            return
        t0 = clock()
        try:
            run()
        except (O3dsoftError, RuntimeError) as e:
            for m in (m for m in asked if m not in out):  # those done before it raised keep theirs; o3dsoft's confidence is 0
                out[m] = MethodResult(m, np.eye(4), {"total": clock() - t0}, 0.0 if m == "o3dsoft" else None, error=first_line(e))

    def o3dsoft_methods() -> None:
        t0 = clock()
        result = register(src, tgt, config.register, model=model, search_model=search_model)
        wall_ms = clock() - t0  # the whole call: its stages and what lies between them (the degeneracy test, the result)
        t = result.timings_ms
        coarse_ms = {"coarse": t["clean"] + t["sample_normalise"] + t.get("coarse", 0.0), **({"search": t["search"]} if "search" in t else {})}
        # The network's own estimate; where the network did not run (a feature match tried
        # first found a confident result), the estimate the result was refined from.
        network = result.network_transformation if result.network_transformation is not None else result.coarse_transformation
        out["o3dsoft-coarse"] = MethodResult("o3dsoft-coarse", network, {**coarse_ms, "total": sum(coarse_ms.values())})
        fine_ms = t["refine"] + t["score"]  # ICP and the confidence, over every refined estimate
        out["o3dsoft"] = MethodResult(
            "o3dsoft", result.transformation, {**coarse_ms, "icp": fine_ms, "total": wall_ms}, result.confidence, result.searched, result.search_reason
        )

    @functools.cache
    def peer() -> Tuple[refine_stage.ICPConfig, baselines.GlobalConfig]:
        """The oracle's and the peers' settings on this pair, found once, outside their timings
        (called within :func:`each`, which reports a pair it refuses)."""
        return peer_settings(src, tgt, config, scale)

    def oracle() -> None:
        icp_config = peer()[0]
        t0 = clock()
        T = peer_icp(src, tgt, pair.transform, icp_distance, icp_config)
        out["oracle"] = MethodResult("oracle", T, {"icp": clock() - t0, "total": clock() - t0})

    def icp() -> None:
        t0 = clock()
        T = refine_stage.icp(src, tgt, np.eye(4), config.identity_icp.distance_for(scale), config.identity_icp).transformation
        out["icp"] = MethodResult("icp", T, {"icp": clock() - t0, "total": clock() - t0})

    def feature_methods() -> None:
        icp_config, global_config = peer()
        t0 = clock()
        fs = baselines.fpfh_features(src, scale, global_config)
        ft = baselines.fpfh_features(tgt, scale, global_config)
        features_ms = clock() - t0
        for name, solve in (
            ("fpfh-ransac", lambda: baselines.ransac(fs, ft, scale, config.seed + pair.index, global_config)),
            ("fgr", lambda: baselines.fgr(fs, ft, scale, global_config)),
        ):
            if name not in methods and f"{name}+icp" not in methods:
                continue
            stage = "ransac" if name == "fpfh-ransac" else "fgr"
            t0 = clock()
            T = solve()
            solve_ms = clock() - t0
            out[name] = MethodResult(name, T, {"features": features_ms, stage: solve_ms, "total": features_ms + solve_ms})
            if f"{name}+icp" in methods:
                t0 = clock()
                T_fine = peer_icp(src, tgt, T, icp_distance, icp_config)
                icp_ms = clock() - t0
                out[f"{name}+icp"] = MethodResult(
                    f"{name}+icp", T_fine, {"features": features_ms, stage: solve_ms, "icp": icp_ms, "total": features_ms + solve_ms + icp_ms}
                )

    def peer_methods() -> None:
        voxel = config.kiss.voxel * max(scene_size(src), scene_size(tgt))
        t0 = clock()
        T = baselines.kiss_matcher(src, tgt, voxel)
        T = np.eye(4) if T is None else T  # too few points for it: no estimate, the pose as given
        kiss_ms = clock() - t0
        out["kiss-matcher"] = MethodResult("kiss-matcher", T, {"kiss": kiss_ms, "total": kiss_ms})
        if "kiss-matcher+gicp" in methods:
            t0 = clock()
            T_fine = baselines.small_gicp(src, tgt, T, voxel, config.kiss)
            gicp_ms = clock() - t0
            out["kiss-matcher+gicp"] = MethodResult("kiss-matcher+gicp", T_fine, {"kiss": kiss_ms, "icp": gicp_ms, "total": kiss_ms + gicp_ms})

    each(("o3dsoft-coarse", "o3dsoft"), o3dsoft_methods)
    each(("oracle",), oracle)
    each(("icp",), icp)
    each(("fpfh-ransac", "fpfh-ransac+icp", "fgr", "fgr+icp"), feature_methods)
    each(PEER_METHODS, peer_methods)
    errors = {r.error for r in out.values()}
    if None not in errors:  # no method could run on the pair: the pair, not a method, is at fault
        raise InputError(next(iter(errors)) or "no method ran")
    return [out[m] for m in methods]


def score(pair: BenchPair, result: MethodResult) -> Tuple[dict, PairErrors]:
    """The CSV row of one method on one pair, and its errors."""
    e = pair_errors(result.transform, pair.transform, pair.origin)
    chamfer = modified_chamfer_distance(pair.source, pair.target, result.transform, pair.transform, pair.clean_target)
    row = {
        "protocol": pair.protocol,
        "index": pair.index,
        "category": pair.category,
        "symmetric": pair.category in SYMMETRIC_CATEGORIES,
        "initial_angle_deg": round(pair.initial_angle, 4),
        "method": result.method,
        "rotation_deg": e.rotation_deg,
        "translation": e.translation,
        "rotation_l1": e.rotation_l1,
        "rotation_l2": e.rotation_l2,
        "translation_l1": e.translation_l1,
        "translation_l2": e.translation_l2,
        "euler_abs_x_deg": e.euler_abs_deg[0],
        "euler_abs_y_deg": e.euler_abs_deg[1],
        "euler_abs_z_deg": e.euler_abs_deg[2],
        "chamfer": chamfer,
        "input_chamfer": input_chamfer_distance(pair.source, pair.target, result.transform),
        "confidence": "" if result.confidence is None else result.confidence,
        "searched": "" if result.searched is None else result.searched,
        "search_reason": result.search_reason or "",
        "error": result.error or "",
    }
    for stage in STAGES:
        row[f"time_{stage}_ms"] = result.times_ms.get(stage, "")
    row["transform"] = " ".join(f"{v:.17g}" for v in result.transform.reshape(-1))  # every bit: georeferenced scans
    return row, e


def score_pair(pair: BenchPair, results: Sequence[MethodResult]) -> List[Tuple[dict, PairErrors]]:
    """The CSV rows and errors of every method on one pair; each row also carries the oracle's
    input Chamfer distance on this pair ("" without the oracle), which the summaries compare with."""
    scored = [score(pair, r) for r in results]
    oracle = next((row["input_chamfer"] for row, _ in scored if row["method"] == "oracle"), "")
    for row, _ in scored:
        row["oracle_input_chamfer"] = oracle
    return scored


# --------------------------------------------------------------------------------------------
# Summaries, table, files
# --------------------------------------------------------------------------------------------
def summarise_rows(rows: Sequence[dict], errors: Sequence[PairErrors], config: BenchConfig) -> List[dict]:
    """One summary per (protocol, subset, method); subsets: all categories, and without the
    symmetric ones where the protocol has any."""
    out = []
    protocols = list(dict.fromkeys(r["protocol"] for r in rows))
    for protocol in protocols:
        idx = [i for i, r in enumerate(rows) if r["protocol"] == protocol]
        subsets = [("all", idx)]
        if any(rows[i]["symmetric"] for i in idx):
            subsets.append(("no symmetric", [i for i in idx if not rows[i]["symmetric"]]))
        for subset, chosen in subsets:
            for method in config.methods:
                sel = [i for i in chosen if rows[i]["method"] == method]
                if not sel:
                    continue
                total = np.array([rows[i]["time_total_ms"] for i in sel], dtype=float)
                recall = config.recall_for(protocol)
                summary = {"protocol": protocol, "subset": subset, "method": method, "recall_thresholds": [list(r) for r in recall]}
                summary.update(summarise([errors[i] for i in sel], recall))
                summary["raised"] = sum(1 for i in sel if rows[i]["error"])  # pairs scored as the pose as given
                if summary["raised"]:
                    summary["first_error"] = next(rows[i]["error"] for i in sel if rows[i]["error"])
                summary["chamfer_mean"] = float(np.mean([rows[i]["chamfer"] for i in sel]))
                summary["time_ms_median"] = float(np.median(total))
                summary["time_ms_p90"] = float(np.percentile(total, 90))
                scores = [rows[i]["confidence"] for i in sel if rows[i]["confidence"] != ""]
                if len(scores) == len(sel):
                    success = within([errors[i].rotation_deg for i in sel], [errors[i].translation for i in sel], recall[-1])
                    summary["confidence_auc"] = roc_auc(np.array(scores), success)
                    summary["likely_failed_share"] = float(np.mean(np.array(scores) < config.register.confidence.likely_failed_below))
                    # False alarms: right alignments flagged likely failed (share of the right ones).
                    right = np.array(scores)[success]
                    summary["false_alarm_share"] = float(np.mean(right < config.register.confidence.likely_failed_below)) if len(right) else None
                    summary.update(_failures_as_truth(rows, sel, success, np.array(scores)))
                searched = [rows[i]["searched"] for i in sel if rows[i]["searched"] != ""]
                if len(searched) == len(sel):
                    summary["searched_share"] = float(np.mean(searched))
                    reasons = [rows[i]["search_reason"] for i in sel if rows[i]["search_reason"]]
                    summary["search_reasons"] = {why: reasons.count(why) for why in sorted(set(reasons))}  # pairs per reason
                for stage in STAGES[:-1]:
                    values = [rows[i][f"time_{stage}_ms"] for i in sel if rows[i][f"time_{stage}_ms"] != ""]
                    if values:
                        summary[f"time_{stage}_ms_median"] = float(np.median(values))
                out.append(summary)
    return out


def _failures_as_truth(rows: Sequence[dict], sel: Sequence[int], success: np.ndarray, scores: np.ndarray) -> dict:
    """Of the failures among rows `sel`, those whose estimate fits the input clouds as well as the
    oracle's (ICP from the ground truth) on the same pair: input Chamfer distance at most AS_TRUTH
    times the oracle's. The clouds cannot tell such a pose from the truth (mostly a symmetric copy
    of the shape; also a near miss where the oracle itself misses), so no confidence measured on
    them can rank it below a right result; the ROC AUC over the right results and the other
    failures says how well the confidence does where it could. Empty without the oracle's rows."""
    fits = [rows[i].get("oracle_input_chamfer", "") for i in sel]
    if any(f == "" for f in fits):
        return {}
    as_truth = np.array([rows[i]["input_chamfer"] <= AS_TRUTH * f for i, f in zip(sel, fits)]) & ~success
    return {
        "failures": int((~success).sum()),
        "failures_as_truth": int(as_truth.sum()),
        "confidence_auc_distinct": roc_auc(scores[~as_truth], success[~as_truth]),
    }


def roc_auc(score: np.ndarray, success: np.ndarray) -> Optional[float]:
    """Area under the ROC curve of `score` separating successes from failures (0.5: chance, 1:
    perfect; higher is better); None when either class is empty."""
    pos, neg = score[success], score[~success]
    if len(pos) == 0 or len(neg) == 0:
        return None
    diff = pos[:, None] - neg[None, :]
    return float(np.mean((diff > 0) + 0.5 * (diff == 0)))


def recall_keys(summary: dict) -> List[str]:
    """The recall entries of one summary row, in the order of their thresholds."""
    return [k for k in summary if k.startswith("recall_") and k != "recall_thresholds"]


def format_table(summaries: Sequence[dict], titles: Optional[Dict[str, str]] = None, units: Optional[Dict[str, str]] = None) -> str:
    """The table a person reads: one block per protocol and subset, one row per method, with the
    recall columns of that protocol's thresholds (``recall_thresholds`` of each summary).
    `titles`: a longer title for some protocols (a folder of scans and its kind); `units`: the
    name of some protocols' distance unit (e.g. "m"), else "units"."""
    lines = [
        "Errors and times: lower is better; recall: higher is better. Translation in the clouds' units (m where the column says so). "
        "Euler RMSE: ModelNet40's measure, '-' on scans (their poses lie near its gimbal lock)."
    ]
    block = None
    for s in summaries:
        recall = [tuple(r) for r in s["recall_thresholds"]]
        if (s["protocol"], s["subset"]) != block:
            block = (s["protocol"], s["subset"])
            title = (titles or {}).get(s["protocol"], s["protocol"])
            if s["subset"] != "all":
                title += " (without symmetric categories: " + ", ".join(SYMMETRIC_CATEGORIES) + ")"
            head = (
                f"{'method':18s} {'pairs':>5s} {'rot mean':>9s} {'rot med':>9s} {'trans mean':>10s} {'Euler RMSE':>10s} "
                + "".join(f" {f'recall {d:g}d/{t:.3g}':>14s}" for d, t in recall)
                + f" {'ms median':>9s} {'ms p90':>8s}"
            )
            unit = (units or {}).get(s["protocol"], "units")
            under = f"{'':18s} {'':>5s} {'deg':>9s} {'deg':>9s} {unit:>10s} {'deg':>10s}" + "".join(f" {'%':>14s}" for _ in recall) + f" {'':>9s} {'':>8s}"
            lines += ["", title, head, under]
        # DCP's Euler measure is ModelNet40's (turns of up to 45 degrees per axis); scans' poses come
        # near its gimbal lock, where a 0.1 degree turn reads as tens of degrees per angle.
        euler = "-" if s["protocol"] in (titles or {}) else f"{s['euler_rmse_deg']:.3g}"
        lines.append(
            f"{s['method']:18s} {int(s['pairs']):>5d} {s['rotation_deg_mean']:>9.3g} {s['rotation_deg_median']:>9.3g} "
            f"{s['translation_mean']:>10.3g} {euler:>10s}"
            + "".join(f" {100 * s[k]:>14.1f}" for k in recall_keys(s))
            + f" {s['time_ms_median']:>9.1f} {s['time_ms_p90']:>8.1f}"
        )
        if s.get("raised"):
            first = f" (the first: {s['first_error']})" if s.get("first_error") else ""
            lines.append(f"{'':18s} raised an error on {counted(s['raised'], 'pair')}{first}: scored as the pose as given (identity); pairs.csv says why")
        if "confidence_auc" in s:
            d5, t5 = recall[-1]
            auc = "n/a (no failures or no successes)" if s["confidence_auc"] is None else f"{s['confidence_auc']:.3f}"
            alarms = "n/a" if s.get("false_alarm_share") is None else f"{100 * s['false_alarm_share']:.1f} %"
            lines.append(
                f"{'':18s} confidence vs success at {d5:g} deg / {t5:.3g} {(units or {}).get(s['protocol'], 'units')}: ROC AUC {auc} (higher is better); "
                f"flagged likely failed: {100 * s['likely_failed_share']:.1f} %; right ones flagged: {alarms} (lower is better)"
                + (f"; searched: {100 * s['searched_share']:.1f} % (lower is faster)" if "searched_share" in s else "")
            )
            if s.get("failures"):
                distinct = "n/a" if s["confidence_auc_distinct"] is None else f"{s['confidence_auc_distinct']:.3f}"
                lines.append(
                    f"{'':18s} failures that fit the clouds as well as the oracle's pose (input Chamfer distance within "
                    f"{AS_TRUTH:g} times its): {s['failures_as_truth']} of {s['failures']}; "
                    f"ROC AUC without them: {distinct} (higher is better)"
                )
    return "\n".join(lines)


def source_commit(here: Optional[Path] = None) -> Optional[str]:
    """The git commit o3dsoft (or the folder `here`) runs from, with "+changes" when tracked files
    differ from it; None when it is not run from a git checkout (an installed wheel) or git is
    missing. Read only: ``--no-optional-locks`` keeps ``git status`` from rewriting the index."""
    here = here or Path(__file__).resolve().parent
    git = ["git", "--no-optional-locks", "-C", str(here)]
    try:
        head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def load_average() -> Optional[float]:
    """The 1-minute load average (None where the system has none)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def cpu_conditions() -> Dict[str, Optional[float]]:
    """What sets a run's times besides the code, before it: torch's threads, OMP_NUM_THREADS and
    the :func:`load_average`."""
    import torch

    omp = os.environ.get("OMP_NUM_THREADS")
    return {"torch_threads": torch.get_num_threads(), "OMP_NUM_THREADS": int(omp) if omp and omp.isdigit() else None, "load_average_before": load_average()}


def versions() -> Dict[str, str]:
    """Versions of o3dsoft and what it runs on (and the git commit, from a checkout)."""
    import open3d
    import torch

    from . import __version__

    out = {
        "o3dsoft": __version__,
        "torch": torch.__version__,
        "open3d": open3d.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": f"{platform.machine()}, {platform.system()}, {os.cpu_count()} logical CPUs",
    }
    commit = source_commit()
    if commit:
        out["commit"] = commit
    return out


def write_csv(path: Path, rows: Sequence[dict]) -> None:
    with atomic_output(path) as tmp:
        with open(tmp, "w", newline="") as f:
            if rows:
                writer = csv.DictWriter(f, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)


def plot(folder: Path, rows: Sequence[dict], config: BenchConfig, units: Optional[Dict[str, str]] = None) -> List[Path]:
    """cdf_rotation_error.png and recall_vs_angle.png: one panel per protocol, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    protocols = list(dict.fromkeys(r["protocol"] for r in rows))
    if not protocols:
        return []
    paths = []
    for kind in ("cdf_rotation_error", "recall_vs_angle"):
        fig, axes = plt.subplots(1, len(protocols), figsize=(4.5 * len(protocols), 3.8), squeeze=False)
        for ax, protocol in zip(axes[0], protocols):
            for method in config.methods:
                sel = [r for r in rows if r["protocol"] == protocol and r["method"] == method]
                if not sel:
                    continue
                if kind == "cdf_rotation_error":
                    err = np.sort(np.maximum([r["rotation_deg"] for r in sel], 1e-6))
                    ax.step(np.r_[err[0], err], np.arange(len(err) + 1) / len(err), where="post", label=method)  # from 0: no pair below the least
                    ax.set_ylim(0.0, 1.02)
                    ax.set_xscale("log")
                    ax.set_xlabel("rotation error (deg, lower is better; below 1e-6 drawn at 1e-6)")
                    ax.set_ylabel("share of pairs with at most this error")
                else:
                    angle = np.array([r["initial_angle_deg"] for r in sel])
                    deg, dist = config.recall_for(protocol)[0]
                    ok = within([r["rotation_deg"] for r in sel], [r["translation"] for r in sel], (deg, dist))
                    edges = np.linspace(0, max(180.0 if angle.max() > 90 else 90.0, angle.max() + 1e-9), 10)
                    which = np.clip(np.digitize(angle, edges) - 1, 0, len(edges) - 2)
                    centres, recall = [], []
                    for b in range(len(edges) - 1):
                        if np.any(which == b):
                            centres.append(0.5 * (edges[b] + edges[b + 1]))
                            recall.append(100 * ok[which == b].mean())
                    ax.plot(centres, recall, marker="o", label=method)
                    ax.set_xlabel("initial rotation angle (deg)")
                    ax.set_ylabel(f"recall ({deg:g} deg, {dist:.3g} {(units or {}).get(protocol, 'units')}) %, higher is better")
                    ax.set_ylim(-2.0, 102.0)
            ax.set_title(protocol)
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=7)
        fig.tight_layout()
        path = folder / f"{kind}.png"
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


class BenchRun(NamedTuple):
    """What a run produced: the summaries, the folder, and whether Ctrl-C cut it short."""

    summaries: List[dict]
    folder: Path
    interrupted: bool
    table: str


def prepare_folder(out: Path, overwrite: bool) -> Path:
    """Create the run folder; refuse an existing one that holds anything unless `overwrite`."""
    out = Path(out)
    held = out.is_dir() and any(out.iterdir())  # empty: made beforehand, or left by a run killed before it wrote
    if held and not overwrite:
        raise UsageError(f"{out}: the output folder exists; choose another --out or pass --overwrite")
    return make_folder(out)  # a file of that name: refused, as every command refuses it


class PairOutcome(NamedTuple):
    """One pair through every method: its scored rows, or why it could not be run."""

    protocol: str
    index: int
    scored: List[Tuple[dict, PairErrors]]
    error: Optional[str]


def run_pair(pair: BenchPair, config: BenchConfig, model: Optional[CoarseModel], search_model: Optional[CoarseModel] = None) -> PairOutcome:
    """Every method of `config` on one pair, scored; an unusable pair (or an Open3D failure) is
    reported in ``error``, not raised."""
    try:
        return PairOutcome(pair.protocol, pair.index, score_pair(pair, run_methods(pair, config, model, search_model)), None)
    except (O3dsoftError, RuntimeError) as e:
        return PairOutcome(pair.protocol, pair.index, [], str(e))


# A worker process's settings and models (see _start_worker).
_WORKER: Dict[str, object] = {}


def _start_worker(config: BenchConfig, weights: Optional[str], search_weights: Optional[str], device: str, threads: int) -> None:

    import torch

    from .coarse import load_model

    release_interrupt(signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    torch.set_num_threads(threads)
    _WORKER.update(
        config=config, model=load_model(weights, device) if weights else None, search_model=load_model(search_weights, device) if search_weights else None
    )


def _run_in_worker(pair: BenchPair) -> PairOutcome:
    return run_pair(pair, _WORKER["config"], _WORKER["model"], _WORKER["search_model"])  # type: ignore[arg-type]


def run_pairs(
    pairs: Iterator[BenchPair], config: BenchConfig, model: Optional[CoarseModel], search_model: Optional[CoarseModel] = None, jobs: int = 1
) -> Iterator[PairOutcome]:
    """:func:`run_pair` on each pair, in order; with `jobs` > 1 in as many worker processes, each
    with its share of the CPU's threads (the models are loaded again in each, from their files).

    For machines with many cores: one process already keeps two cores busy (docs/speed.md).
    """
    if jobs == 1:
        for pair in pairs:
            yield run_pair(pair, config, model, search_model)
        return

    threads = max(1, (os.cpu_count() or 1) // jobs)
    device = config.register.device
    args = (config, str(model.path) if model else None, str(search_model.path) if search_model else None, device, threads)
    # "spawn": a forked copy of a process whose OpenMP threads have run can hang. The workers
    # inherit OMP_NUM_THREADS, which also holds Open3D's OpenMP loops (RANSAC, FGR) to their share.
    before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        pool = spawn_context().Pool(jobs, _start_worker, args)
    finally:
        if before is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = before
    with pool:
        yield from pool.imap(_run_in_worker, pairs)


def _weights_record(weights: Union[str, Path, None]) -> Optional[dict]:
    """The model file that `weights` names (a file or a shipped model's name), with its checksum;
    None for no model."""
    if weights is None:
        return None
    path = weights_file(weights)
    return {"path": str(path), "sha256": sha256_of(path)}


def run(
    pairs: Iterator[BenchPair],
    count: int,
    config: BenchConfig,
    model: Optional[CoarseModel],
    out: Path,
    description: dict,
    progress: bool = True,
    log: Callable[[str], None] = print,
    search_model: Optional[CoarseModel] = None,
    jobs: int = 1,
    titles: Optional[Dict[str, str]] = None,
    units: Optional[Dict[str, str]] = None,
) -> BenchRun:
    """Run the methods of `config` on every pair and write the run folder `out` (already created).

    titles: a longer title for some protocols in the table; units: the distance unit's name of
    some protocols (:func:`format_table`).
    jobs: pairs run at once, in as many processes (:func:`run_pairs`). Each method's time is
    then measured with that process's share of the CPU, the same for every method.
    On Ctrl-C or SIGTERM, the pairs finished so far are summarised and written, and
    ``interrupted`` is set.
    """
    from tqdm import tqdm

    rows: List[dict] = []
    errors: List[PairErrors] = []
    interrupted = False
    ran_with = versions()  # before the run: the checkout may change while it runs, the loaded code not
    cpu = cpu_conditions()
    if cpu["load_average_before"] is not None and cpu["load_average_before"] >= 0.75 * (os.cpu_count() or 1):
        log(
            f"Note: the CPU is busy (load average {cpu['load_average_before']:.1f} on {os.cpu_count()} logical CPUs before the run): "
            "times are not comparable with a run on an idle machine, and torch's threads slow most (docs/speed.md)"
        )
    t_start = time.monotonic()
    bar = tqdm(total=count, unit="pair", disable=None if progress else True, dynamic_ncols=True)  # None: only on a terminal
    failed: List[dict] = []
    try:
        with terminate_as_interrupt():
            for outcome in run_pairs(pairs, config, model, search_model, jobs):
                if outcome.error is not None:
                    failed.append({"protocol": outcome.protocol, "index": outcome.index, "error": outcome.error})
                    log(f"pair {outcome.protocol}/{outcome.index} skipped: {outcome.error}")
                for row, e in outcome.scored:  # appended only once every method is done: no half pairs
                    rows.append(row)
                    errors.append(e)
                bar.set_postfix_str(outcome.protocol, refresh=False)
                bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
    summaries = summarise_rows(rows, errors, config)
    table = format_table(summaries, titles, units)
    write_csv(out / "pairs.csv", rows)
    summary_doc = {
        "description": description,
        "interrupted": interrupted,
        "pairs_completed": len(rows) // max(len(config.methods), 1),
        "pairs_failed": failed,
        "seconds": round(time.monotonic() - t_start, 1),
        "jobs": jobs,
        "weights": _weights_record(model.path if model is not None else None),
        "search_weights": _weights_record(search_model.path if search_model is not None else None),
        "second_weights": _weights_record(config.register.second_network.weights) if model is not None else None,
        "versions": ran_with,
        "cpu": {**cpu, "load_average_after": load_average()},
        "recall_thresholds": {p: [{"rotation_deg": d, "translation": t} for d, t in config.recall_for(p)] for p in dict.fromkeys(r["protocol"] for r in rows)},
        "methods": {m: METHODS[m] for m in config.methods},
        "summaries": summaries,
    }
    with atomic_output(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary_doc, indent=2))
    with atomic_output(out / "config.json") as tmp:
        tmp.write_text(json.dumps({**description, "bench": config.to_dict()}, indent=2))
    if interrupted:  # a table read later says it is a part of the run
        table = f"Interrupted: {counted(summary_doc['pairs_completed'], 'pair')} completed; the table holds those only.\n\n{table}"
    with atomic_output(out / "table.txt") as tmp:
        tmp.write_text(table + "\n")
    plot(out, rows, config, units)
    return BenchRun(summaries, out, interrupted, table)
