"""ModelNet40 and the benchmark protocols of the literature (docs/results.md).

One definition of every protocol serves training and benchmarking. Every pair is drawn from a
generator seeded by (seed, index) alone, so a pair never depends on which worker made it or on
what was drawn before, and a run can be repeated digit for digit.

Nothing is ever downloaded: with no data present the error says where to get it and how to point
o3dsoft at it (``--data PATH`` or the ``O3DSOFT_DATA`` environment variable).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .errors import InputError, UsageError
from .transforms import axis_angle_to_matrix, euler_to_matrix, random_rotation, rigid, rotation_angle_deg

DATA_ENV = "O3DSOFT_DATA"
DEFAULT_POINTS_PER_SHAPE = 1024
_HOW_TO_GET = (
    "ModelNet40 in the modelnet40_ply_hdf5_2048 layout (ply_data_{train,test}*.h5, shape_names.txt), "
    "published by the PointNet authors, or the ModelNet40 OFF meshes (<category>/{train,test}/*.off) "
    "from Princeton's ModelNet page; download and unpack it yourself, then pass its folder "
    f"with --data PATH or set {DATA_ENV}=PATH"
)


# --------------------------------------------------------------------------------------------
# Protocols
# --------------------------------------------------------------------------------------------
_NOISE = dict(noise_std=0.01, noise_clip=0.05)  # per cloud, as dcp-noise and rpmnet-crop
_WIDE45 = dict(angle_min=-45.0, angle_max=45.0, translation=0.5)  # the shipped default's range
_NEAR = dict(angle_min=-10.0, angle_max=10.0, translation=0.1)  # what a further network pass sees


@dataclass(frozen=True)
class Protocol:
    """How a registration pair is made from one shape.

    Attributes:
        name: the protocol's name.
        rotation: "euler" (each axis angle uniform in [angle_min, angle_max] degrees, R = Rx Ry Rz)
            or "so3" (uniform on SO(3)).
        angle_min, angle_max: Euler angle range in degrees.
        translation: each component of t uniform in [-translation, translation].
        noise_std, noise_clip: Gaussian noise added to each cloud independently (0 = none).
        crop_keep: fraction of each cloud kept by its own random half-space (1 = no crop).
        num_points: points per cloud after cropping or the views (None = all points of the
            shape); each cloud draws its own points, so source and target are different samples
            of the shape.
        degraded_share: share of pairs that get the crop and the noise; the others stay complete
            and noise-free (still resampled to num_points). 1 = every pair, the benchmark setting.
        categories: "all", "seen" (labels 0-19) or "unseen" (labels 20-39) for the test split;
            training on an "unseen" protocol uses the seen half.
        disjoint_share: share of pairs whose source and target are disjoint subsets of the
            shape's points (no point in both, as between two scans); the others use the same
            points in both. 0 = never (the literature's protocols), 1 = every pair.
        source_share: share of the shape's points that go to the source of a disjoint pair; the
            target takes the rest.
        view_deg: each cloud is the part of its points a camera sees (:func:`seen_from`), as in
            two scans of one object: the source's camera in a random direction, the target's
            turned from it by an angle uniform in [0, view_deg] degrees about a random axis, both
            3 shape radii from the shape's centroid (None = each cloud whole).
    """

    name: str
    rotation: str = "euler"
    angle_min: float = 0.0
    angle_max: float = 45.0
    translation: float = 0.5
    noise_std: float = 0.0
    noise_clip: float = 0.0
    crop_keep: float = 1.0
    num_points: Optional[int] = None
    degraded_share: float = 1.0
    categories: str = "all"
    disjoint_share: float = 0.0
    source_share: float = 0.5
    view_deg: Optional[float] = None


PROTOCOLS: Dict[str, Protocol] = {
    p.name: p
    for p in (
        Protocol("paper", angle_min=-22.5, angle_max=22.5, translation=0.25),
        Protocol("dcp"),
        Protocol("dcp-unseen", categories="unseen"),
        Protocol("dcp-noise", **_NOISE),
        Protocol("rpmnet-crop", **_NOISE, crop_keep=0.7, num_points=717),
        Protocol("so3", rotation="so3"),
        Protocol("so3-crop", rotation="so3", **_NOISE, crop_keep=0.7, num_points=717),
        # The range the shipped default model is trained on: paper's +-22.5 and DCP's 0-45 inside.
        Protocol("wide45", **_WIDE45),
        # Training only: wide45 where half of the pairs are cropped and noisy like rpmnet-crop and
        # the rest complete, all independently resampled (so the weights w_i learn to down-weight
        # points without a partner while clean pairs stay in the mix).
        Protocol("wide45-partial", **_WIDE45, **_NOISE, crop_keep=0.7, num_points=717, degraded_share=0.5),
        # Training only: wide45 with every pair cropped and noisy like rpmnet-crop.
        Protocol("wide45-crop", **_WIDE45, **_NOISE, crop_keep=0.7, num_points=717),
        # Independent sampling: source and target are disjoint halves of the shape's points (512
        # each from the 1,024-point release, 1,024 each from the 2,048-point one).
        Protocol("incongruent", disjoint_share=1.0),
        Protocol("incongruent-noise", disjoint_share=1.0, **_NOISE),
        Protocol("incongruent-crop", disjoint_share=1.0, crop_keep=0.7, **_NOISE),
        Protocol("incongruent-so3", rotation="so3", disjoint_share=1.0),
        # Each half as a camera sees it, the two cameras up to 60 degrees apart (as turntable views).
        Protocol("incongruent-view", disjoint_share=1.0, view_deg=60.0, **_NOISE),
        # Training only: the components of the mixture "incongruent-mix" (see MIXTURES).
        Protocol("incongruent-wide", disjoint_share=1.0, **_WIDE45),
        Protocol("incongruent-wide-noise", disjoint_share=1.0, **_WIDE45, **_NOISE),
        Protocol("incongruent-wide-crop", disjoint_share=1.0, crop_keep=0.7, **_WIDE45, **_NOISE),
        Protocol("incongruent-wide-sparse", disjoint_share=1.0, source_share=0.3, **_WIDE45, **_NOISE),
        Protocol("incongruent-wide-dense", disjoint_share=1.0, source_share=0.7, **_WIDE45, **_NOISE),
        # (192 points per view, so that a batch's clouds have one size: a 512-point half's view has 130-350)
        Protocol("incongruent-wide-view", disjoint_share=1.0, view_deg=60.0, num_points=192, **_WIDE45, **_NOISE),
        # Views up to 120 degrees apart at 512 points, the overlaps of scans around an object: for
        # shapes of 4,096 points or more (o3dsoft.synthetic's objects; a 1,024-point shape's views
        # hold fewer points than that).
        Protocol("incongruent-far-view", disjoint_share=1.0, view_deg=120.0, num_points=512, **_WIDE45, **_NOISE),
        # Training only: the residual poses of a second network pass, for "incongruent-iterative".
        Protocol("incongruent-near", disjoint_share=1.0, **_NEAR),
        Protocol("incongruent-near-crop", disjoint_share=1.0, crop_keep=0.7, **_NEAR, **_NOISE),
    )
}


@dataclass(frozen=True)
class Mixture:
    """A training recipe: each batch is drawn from one protocol of `parts`, chosen with the given
    weights (all pairs of a batch then have the same point counts); `evaluate` names the protocol
    of the per-epoch evaluation."""

    name: str
    parts: Tuple[Tuple[str, float], ...]
    evaluate: str


# incongruent-mix's parts at about 69 % of their weights, for mixtures that add 31 % of their own.
_MIX_AT_69: Tuple[Tuple[str, float], ...] = (
    ("wide45", 0.1),
    ("wide45-partial", 0.07),
    ("incongruent-wide", 0.14),
    ("incongruent-wide-noise", 0.1),
    ("incongruent-wide-crop", 0.14),
    ("incongruent-wide-sparse", 0.07),
    ("incongruent-wide-dense", 0.07),
)

MIXTURES: Dict[str, Mixture] = {
    m.name: m
    for m in (
        # Independently sampled clouds at several densities and point counts, noisy and cropped,
        # with congruent pairs kept in the mix so that the literature's protocols stay covered.
        Mixture(
            "incongruent-mix",
            (
                ("wide45", 0.15),
                ("wide45-partial", 0.1),
                ("incongruent-wide", 0.2),
                ("incongruent-wide-noise", 0.15),
                ("incongruent-wide-crop", 0.2),
                ("incongruent-wide-sparse", 0.1),
                ("incongruent-wide-dense", 0.1),
            ),
            "incongruent",
        ),
        # incongruent-mix with 31 % of the batches partial views, for scans.
        Mixture("incongruent-view-mix", _MIX_AT_69 + (("incongruent-wide-view", 0.31),), "incongruent-wide-view"),
        # incongruent-mix with a third of the batches near the true pose (within 10 degrees per
        # axis), where further network passes (``coarse_iterations``) start.
        Mixture("incongruent-iterative", _MIX_AT_69 + (("incongruent-near", 0.18), ("incongruent-near-crop", 0.13)), "incongruent"),
        # For an overlap head (``NetConfig.overlap``): half of the batches partial overlaps at a
        # first pass's pose, a fifth at a later pass's, the rest complete or seen from a camera.
        Mixture(
            "incongruent-overlap-mix",
            (("incongruent-wide-crop", 0.3), ("incongruent-near-crop", 0.2), ("incongruent-wide-view", 0.3), ("incongruent-wide", 0.2)),
            "incongruent-crop",
        ),
    )
}


def training_parts(name: str) -> Tuple[Tuple[Protocol, float], ...]:
    """(protocol, weight) of a training recipe: a mixture's parts, or one protocol of weight 1."""
    if name in MIXTURES:
        return tuple((get_protocol(p), w) for p, w in MIXTURES[name].parts)
    return ((get_protocol(name), 1.0),)


def evaluation_protocol(name: str) -> Protocol:
    """The protocol a training recipe is evaluated on after each epoch."""
    return get_protocol(MIXTURES[name].evaluate if name in MIXTURES else name)


def get_protocol(name: str) -> Protocol:
    """The protocol of that name; InputError listing the valid names otherwise."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise UsageError(f"unknown protocol {name!r}; valid: {', '.join(PROTOCOLS)}") from None


def check_training_recipe(name: str) -> None:
    """InputError unless `name` is a protocol or a mixture."""
    if name not in PROTOCOLS and name not in MIXTURES:
        raise UsageError(f"unknown protocol {name!r}; valid: {', '.join(list(PROTOCOLS) + list(MIXTURES))}")


def _crop(points: np.ndarray, keep: float, rng: np.random.Generator) -> np.ndarray:
    """Keep the fraction `keep` of points farthest along a random direction (a random half-space)."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    order = np.argsort(-(points @ direction), kind="stable")
    return points[np.sort(order[: max(1, int(round(keep * len(points))))])]


# Hidden point removal's sphere, in distances of the farthest point from the camera: the larger,
# the more points count as seen (100: about half of a 512-point ModelNet40 half, as Open3D's
# examples use it).
VIEW_RADIUS = 100.0


def seen_from(points: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """The (V, 3) points of an (N, 3) cloud a camera at `camera` (3,) sees, in their order: hidden
    point removal (Katz, Tal and Basri, SIGGRAPH 2007), each point flipped about a sphere around
    the camera; the visible ones are those on the convex hull of the flipped points and the camera."""
    from scipy.spatial import ConvexHull  # noqa: WPS433 - only the view protocols need it

    offsets = points - camera
    norms = np.linalg.norm(offsets, axis=1, keepdims=True)
    flipped = offsets + 2.0 * (VIEW_RADIUS * norms.max() - norms) * offsets / norms
    vertices = ConvexHull(np.vstack([flipped, np.zeros((1, 3))])).vertices
    return points[np.sort(vertices[vertices < len(points)])]


def _views(source: np.ndarray, target: np.ndarray, centre: np.ndarray, max_deg: float, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """Each cloud as seen from its own camera, 3 radii from `centre` (3,), the target's turned
    from the source's by up to `max_deg` degrees (:attr:`Protocol.view_deg`)."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis = np.cross(direction, rng.normal(size=3))
    turn = axis_angle_to_matrix(np.radians(rng.uniform(0.0, max_deg)) * axis / np.linalg.norm(axis))
    radius = max(np.linalg.norm(source - centre, axis=1).max(), np.linalg.norm(target - centre, axis=1).max())
    return seen_from(source, centre + 3.0 * radius * direction), seen_from(target, centre + 3.0 * radius * turn @ direction)


def _resample(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    replace = len(points) < n
    return points[rng.choice(len(points), size=n, replace=replace)]


def _noise(points: np.ndarray, p: Protocol, rng: np.random.Generator) -> np.ndarray:
    if p.noise_std <= 0:
        return points
    eps = np.clip(rng.normal(scale=p.noise_std, size=points.shape), -p.noise_clip, p.noise_clip)
    return points + eps


class Pair(NamedTuple):
    """One registration problem: target ~ transform @ source.

    source: (N, 3) float32; target: (M, 3) float32 (shuffled); transform: (4, 4) float64
    T_target_source; index: pair index; label: category of the shape; angle: the rotation angle
    of the ground truth in degrees.
    """

    source: np.ndarray
    target: np.ndarray
    transform: np.ndarray
    index: int
    label: int
    angle: float


def make_pair(points: np.ndarray, protocol: Protocol, seed: int, index: int, label: int = -1) -> Pair:
    """Build the pair number `index` of a protocol from one shape, deterministically.

    Args:
        points: (N, 3) the shape.
        protocol: how to perturb it.
        seed: run seed; with `index` it fixes every random draw.
        index: pair index (usually the shape's index in its split).
        label: category, carried along.
    """
    rng = np.random.default_rng([seed, index])
    p = protocol
    if p.rotation == "so3":
        R = random_rotation(rng)
    else:
        R = euler_to_matrix(rng.uniform(p.angle_min, p.angle_max, size=3))
    t = rng.uniform(-p.translation, p.translation, size=3)
    src = points.astype(np.float64)
    tgt = src.copy()
    # Drawn only for mixed protocols, so that the pairs of the others stay as they were.
    degraded = p.degraded_share >= 1.0 or rng.random() < p.degraded_share
    disjoint = p.disjoint_share >= 1.0 or (p.disjoint_share > 0.0 and rng.random() < p.disjoint_share)
    if disjoint:
        order = rng.permutation(len(src))
        cut = min(max(1, int(round(p.source_share * len(src)))), len(src) - 1)
        src, tgt = src[order[:cut]], src[order[cut:]]
    if degraded and p.view_deg is not None:
        src, tgt = _views(src, tgt, points.mean(axis=0), p.view_deg, rng)
    if degraded and p.crop_keep < 1.0:
        src = _crop(src, p.crop_keep, rng)
        tgt = _crop(tgt, p.crop_keep, rng)
    if p.num_points is not None:
        src = _resample(src, p.num_points, rng)
        tgt = _resample(tgt, p.num_points, rng)
    if degraded:
        src = _noise(src, p, rng)
        tgt = _noise(tgt, p, rng)
    tgt = tgt @ R.T + t
    tgt = tgt[rng.permutation(len(tgt))]
    if disjoint:  # in random order too, so that any first n points are a random subset
        src = src[rng.permutation(len(src))]
    return Pair(src.astype(np.float32), tgt.astype(np.float32), rigid(R, t), index, label, rotation_angle_deg(R))


# --------------------------------------------------------------------------------------------
# ModelNet40
# --------------------------------------------------------------------------------------------
class Shapes(NamedTuple):
    """A split of ModelNet40: points (S, N, 3) float32, labels (S,) int64, names (S,) and categories."""

    points: np.ndarray
    labels: np.ndarray
    names: List[str]
    categories: List[str]


def resolve_data_root(path: Optional[str], option: str = "--data") -> Path:
    """The ModelNet40 folder: the given path, else $O3DSOFT_DATA, else a UsageError saying how to
    get it (`option`: the command-line option that gives the folder, named in the error); a
    UsageError too where the path is no folder (the CLI exits 2, as for a missing file)."""
    chosen = path or os.environ.get(DATA_ENV)
    how = _HOW_TO_GET.replace("--data PATH", f"{option} PATH")
    if not chosen:
        raise UsageError(f"no ModelNet40 data given. {how}")
    root = Path(chosen).expanduser()
    if not root.is_dir():
        raise UsageError(f"{root}: {'not a folder' if root.exists() else 'no such folder'}. {how}")
    return root


def folder_fingerprint(root: Path) -> str:
    """sha256 of the names (relative to `root`) and sizes of the files under it: the same data
    wherever it is copied or however its path is written, without reading it."""
    import hashlib

    root = Path(root)
    listing = sorted((str(path.relative_to(root)), path.stat().st_size) for path in root.rglob("*") if path.is_file())
    return hashlib.sha256(json.dumps(listing).encode()).hexdigest()


def load_modelnet40(root: Path, split: str, categories: str = "all", points_per_shape: Optional[int] = DEFAULT_POINTS_PER_SHAPE) -> Shapes:
    """Read one split of ModelNet40 from the official HDF5 layout or from a folder of OFF meshes.

    The layout is recognised from the folder's content: ``ply_data_{split}*.h5`` with
    ``shape_names.txt`` (modelnet40_ply_hdf5_2048, or our 1024-point copy), or
    ``<category>/{split}/*.off`` (the ModelNet40 meshes, sampled uniformly on their faces).

    Args:
        root: the data folder.
        split: "train" or "test".
        categories: "all", "seen" (labels 0-19) or "unseen" (labels 20-39).
        points_per_shape: points per shape: the first N of each HDF5 shape (as DCP and its
            successors take 1024 of the 2048), or N samples on each mesh. None: all HDF5 points.
    Raises:
        InputError: neither layout found, missing shape names, wrong keys or shapes, a shape with
            fewer points than asked for, an unreadable mesh.
    """
    if split not in ("train", "test"):
        raise InputError(f"split must be 'train' or 'test', got {split!r}")
    if any(root.glob(f"ply_data_{split}*.h5")):
        shapes = _load_hdf5(root, split)
    elif any(root.glob(f"*/{split}/*.off")):
        shapes = _load_off_folder(root, split, points_per_shape or DEFAULT_POINTS_PER_SHAPE)
    else:
        raise InputError(f"{root}: no ModelNet40 {split} split here (ply_data_{split}*.h5 and shape_names.txt, or <category>/{split}/*.off). {_HOW_TO_GET}")
    if points_per_shape is not None:
        if shapes.points.shape[1] < points_per_shape:
            raise InputError(f"{root}: shapes have {shapes.points.shape[1]} points, fewer than the {points_per_shape} asked for")
        shapes = shapes._replace(points=shapes.points[:, :points_per_shape])
    if shapes.labels.max(initial=0) >= len(shapes.categories):
        raise InputError(f"{root}: labels go up to {shapes.labels.max()} but there are {len(shapes.categories)} categories")
    keep = _category_mask(shapes.labels, categories)
    return Shapes(shapes.points[keep], shapes.labels[keep], [n for n, k in zip(shapes.names, keep) if k], shapes.categories)


def _load_hdf5(root: Path, split: str) -> Shapes:
    import h5py

    names_file = root / "shape_names.txt"
    if not names_file.is_file():
        raise InputError(f"{root}: ply_data_{split}*.h5 found but no shape_names.txt beside them. {_HOW_TO_GET}")
    files = sorted(root.glob(f"ply_data_{split}*.h5"), key=lambda f: _trailing_int(f.stem))
    categories_list = [line.strip() for line in names_file.read_text().splitlines() if line.strip()]
    points, labels, names = [], [], []
    for f in files:
        try:
            with h5py.File(f, "r") as h5:
                if "data" not in h5 or "label" not in h5:
                    raise InputError(f"{f}: expected datasets 'data' and 'label', found {sorted(h5.keys())}")
                data = np.asarray(h5["data"], dtype=np.float32)
                label = np.asarray(h5["label"]).reshape(-1).astype(np.int64)
        except OSError as e:
            raise InputError(f"{f}: not a readable HDF5 file ({e})") from None
        if data.ndim != 3 or data.shape[2] < 3 or len(label) != len(data):
            raise InputError(f"{f}: 'data' must be (S, N, 3) with one label per shape, got {data.shape} and {label.shape}")
        bad = np.flatnonzero(~np.isfinite(data[:, :, :3]).all(axis=(1, 2)))
        if len(bad):
            raise InputError(f"{f}: shape {bad[0]} (of {len(bad)} such) has NaN or infinite coordinates")
        if points and data.shape[1] != points[0].shape[1]:
            raise InputError(f"{f}: {data.shape[1]} points per shape, but {files[0].name} has {points[0].shape[1]}")
        points.append(data[:, :, :3])
        labels.append(label)
        id_file = root / f"ply_data_{split}_{_trailing_int(f.stem)}_id2file.json"
        names += json.loads(id_file.read_text()) if id_file.is_file() else [f"{f.name}:{i}" for i in range(len(data))]
    return Shapes(np.concatenate(points), np.concatenate(labels), names, categories_list)


def _load_off_folder(root: Path, split: str, n: int) -> Shapes:
    """Sample n points on each mesh of <category>/<split>/*.off, centred and scaled into the unit sphere.

    Categories are the sorted folder names (ModelNet40's shape_names.txt order). Mesh i of the
    sorted list is sampled with seed i, so the points repeat from run to run.
    """
    import trimesh

    from .io import sample_mesh

    categories_list = sorted(d.name for d in root.iterdir() if d.is_dir() and any((d / split).glob("*.off")))
    points, labels, names = [], [], []
    for label, category in enumerate(categories_list):
        for f in sorted((root / category / split).glob("*.off")):
            try:
                # trimesh also reads ModelNet's known malformed header ("OFF490 518 0" on one line).
                mesh = trimesh.load(str(f), file_type="off", process=False, force="mesh")
                vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
            except Exception as e:  # trimesh raises many types on malformed files
                raise InputError(f"{f}: not a readable OFF mesh ({e})") from None
            if len(faces) == 0 or not np.isfinite(vertices).all():
                raise InputError(f"{f}: the mesh has no faces or non-finite vertices; points are sampled on faces")
            pts = sample_mesh(vertices, faces, n, seed=len(points))
            pts -= pts.mean(axis=0)
            radius = np.linalg.norm(pts, axis=1).max()
            if radius <= 0:
                raise InputError(f"{f}: all faces have zero area")
            points.append((pts / radius).astype(np.float32))
            labels.append(label)
            names.append(f"{category}/{split}/{f.name}")
    return Shapes(np.stack(points), np.asarray(labels, dtype=np.int64), names, categories_list)


def _category_mask(labels: np.ndarray, categories: str) -> np.ndarray:
    if categories == "all":
        return np.ones(len(labels), dtype=bool)
    if categories == "seen":
        return labels < 20
    if categories == "unseen":
        return labels >= 20
    raise InputError(f"categories must be 'all', 'seen' or 'unseen', got {categories!r}")


def _trailing_int(stem: str) -> int:
    digits = ""
    for ch in reversed(stem):
        if not ch.isdigit():
            break
        digits = ch + digits
    return int(digits) if digits else 0


class PairDataset:
    """Map-style dataset of protocol pairs over one split; pair i is a pure function of (seed, i).

    Usable with torch's DataLoader (any number of workers): ``__getitem__`` never touches global
    random state and never changes the dataset.
    """

    def __init__(self, shapes: Shapes, protocol: Protocol, seed: int = 0) -> None:
        self.shapes = shapes
        self.protocol = protocol
        self.seed = seed

    def __len__(self) -> int:
        return len(self.shapes.points)

    def __getitem__(self, index: int) -> Pair:
        return make_pair(self.shapes.points[index], self.protocol, self.seed, int(index), int(self.shapes.labels[index]))


def split_categories(protocol: Protocol, split: str) -> str:
    """Which categories a split uses under a protocol (unseen protocols train on the seen half)."""
    if protocol.categories == "unseen":
        return "unseen" if split == "test" else "seen"
    return protocol.categories


def load_pairs(root: Optional[str], split: str, protocol: Protocol, seed: int = 0, points_per_shape: Optional[int] = DEFAULT_POINTS_PER_SHAPE) -> PairDataset:
    """The pairs of a protocol over a split of the ModelNet40 found at `root` (or $O3DSOFT_DATA)."""
    shapes = load_modelnet40(resolve_data_root(root), split, split_categories(protocol, split), points_per_shape)
    return PairDataset(shapes, protocol, seed)


def stack_pairs(pairs: Sequence[Pair]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B, N, 3) sources, (B, M, 3) targets and (B, 4, 4) transforms of same-sized pairs."""
    return (
        np.stack([p.source for p in pairs]),
        np.stack([p.target for p in pairs]),
        np.stack([p.transform for p in pairs]),
    )
