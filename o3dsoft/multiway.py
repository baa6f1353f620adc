"""``multiway``: many scans of one scene into one frame.

    choose the pairs that may overlap (all of them for a few scans; neighbours in sequence or by
    position for many)
    -> register each pair (:func:`o3dsoft.register`, from the two scans' initial poses where
       the caller has them), keeping its transform and confidence
    -> connect the scans through their most confident edges (a maximum spanning tree)
    -> optimise the pose graph (Open3D's Levenberg-Marquardt with a line process, which prunes
       wrong loop closures)
    -> one pose per scan, world_T_scan, the first joined scan being the world frame (placed at
       its initial pose, where it has one: the result stays in the initial poses' frame).

Edges flagged likely failed are left out of the graph; scans that no trusted edge reaches are
reported and left out of the merged cloud. Where they have initial poses, they are placed by them
relative to the nearest joined scan (unverified); otherwise they have no pose.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from ._modules import callable_as_its_function
from ._open3d import quietly
from .config import RegisterConfig, check_settings
from .errors import InputError, UsageError
from .io import as_rigid
from .pair import CloudLike, as_points, named_clouds
from .pipeline import SIZE_RATIO_NOTE, RegistrationResult, register_cleaned
from .preprocess import Cleaning, clean_each, clean_points, scene_size, voxel_downsample
from .transforms import apply_transform

NEIGHBOUR_RULES = ("auto", "all", "sequence", "near")


@dataclass(frozen=True)
class MultiwayConfig:
    """Settings of :func:`multiway`.

    Attributes:
        neighbours: which pairs are registered: "all" (every pair), "sequence" (each scan with the
            next `window` scans, for scans taken in order), "near" (each scan with its `near`
            nearest by centroid, for scans already roughly placed, e.g. georeferenced; where those
            pairs leave groups of scans apart, the nearest pair across is added), or "auto"
            (default: "all" up to `all_up_to` scans; beyond, "near" where every scan has an
            initial pose, else "sequence").
        all_up_to: "auto" registers every pair of at most this many scans (default 12: 66 pairs).
        window: "sequence": how many following scans each scan is paired with (default 3).
        near: "near": how many nearest scans each scan is paired with (default 4).
        prune_below: a loop-closure edge whose line-process weight ends below this is pruned
            (Open3D's ``edge_prune_threshold``, default 0.25).
        loop_closure_preference: weight of loop-closure edges against the spanning tree's in the
            optimisation (Open3D's ``preference_loop_closure``, default 1.0).
        voxel: grid of the merged cloud (scan units); None: the pairs' registration grid, or
            every point where they had none.
        init_max_rotation: a pair registered from the scans' initial poses is held within this
            many degrees of the turn between them (``RegisterConfig.max_rotation``, where
            `register` sets none): odometry is seldom that far off, and on scans that overlap
            little the search can find and trust a turn far from it (docs/multiway.md); None: no
            bound.
        register: settings of every pairwise registration.
    """

    neighbours: str = "auto"
    all_up_to: int = 12
    window: int = 3
    near: int = 4
    prune_below: float = 0.25
    loop_closure_preference: float = 1.0
    voxel: Optional[float] = None
    init_max_rotation: Optional[float] = 45.0
    register: RegisterConfig = field(default_factory=RegisterConfig)

    def validate(self) -> None:
        """Raise InputError for settings :func:`multiway` cannot run with."""
        check_settings(self)
        if self.neighbours not in NEIGHBOUR_RULES:
            raise InputError(f"neighbours={self.neighbours!r}; valid: {', '.join(NEIGHBOUR_RULES)}")
        for name, value in (("all_up_to", self.all_up_to), ("window", self.window), ("near", self.near)):
            if value < 1:
                raise InputError(f"{name} must be at least 1, got {value}")
        if not 0 <= self.prune_below < 1:
            raise InputError(f"prune_below must be in [0, 1), got {self.prune_below}")
        if self.voxel is not None and not self.voxel > 0:
            raise InputError(f"voxel must be positive, got {self.voxel}")
        if self.init_max_rotation is not None and not 0 < self.init_max_rotation <= 180:
            raise InputError(f"init_max_rotation must be in (0, 180] degrees, got {self.init_max_rotation}")


@dataclass(frozen=True, eq=False)  # compared by identity: arrays have no single truth value
class Edge:
    """One registered pair: ``transformation`` (4, 4) is T_target_source (maps scan `source` onto
    scan `target`, indices into the scans).

    Attributes:
        confidence: the registration's confidence (0-1, higher is better).
        used: the edge entered the pose graph (not flagged likely failed).
        in_tree: it is one of a spanning tree's edges (of the world scan's group, or of a group
            placed by initial poses), which place the scans before the optimisation (never
            pruned).
        pruned: the optimisation's line process rejected it as a wrong loop closure.
        seconds: time of the pairwise registration (s, lower is better).
        searched: the global search ran on this pair: with the search mode "auto", the quick
            search's feature match on scans that look like a partial overlap, and the whole
            search on those of scans that no quick alignment joined.
    """

    source: int
    target: int
    transformation: np.ndarray
    confidence: float
    fitness: float
    likely_failed: bool
    failure_reason: Optional[str]
    seconds: float
    searched: bool = False
    used: bool = False
    in_tree: bool = False
    pruned: bool = False

    def to_dict(self, names: Sequence[str]) -> dict:
        return {
            "source": names[self.source],
            "target": names[self.target],
            "T_target_source": np.asarray(self.transformation).tolist(),
            "confidence": self.confidence,
            "fitness": self.fitness,
            "likely_failed": self.likely_failed,
            "failure_reason": self.failure_reason,
            "used": self.used,
            "in_tree": self.in_tree,
            "pruned": self.pruned,
            "seconds": self.seconds,
            "searched": self.searched,
        }


@dataclass(frozen=True, eq=False)  # compared by identity: arrays have no single truth value
class MultiwayResult:
    """Poses of many scans in one frame.

    Attributes:
        names: the scans' names, in input order.
        poses: (4, 4) world_T_scan per scan (maps the scan's points into the world frame), or
            None (the world scan has the identity, or its initial pose where it was given one).
        placed_by: per scan, how its pose was found: "registration" (the world scan, and the
            scans trusted alignments join to it), "initial pose" (a group of scans that no
            trusted alignment joins to the world scan's, placed by the initial pose of its scan k
            nearest to a joined scan a that has one, world_T_k = world_T_a @ inv(init_a) @
            init_k, its other scans by their alignments to k; unverified), or None (no pose:
            neither the group nor the joined scans have initial poses).
        world: index of the scan that fixes the world frame: the first of the largest group of
            scans joined by trusted alignments (the first scan when none is).
        edges: every registered pair.
        timings_s: "clean" (each scan cleaned once), "pairs" (all pairwise registrations),
            "optimise", "total" (s, lower is better).
        voxel: the grid the information matrices were computed on, and the merged cloud's
            default (scan units); None: every point.
    """

    names: Tuple[str, ...]
    poses: Tuple[Optional[np.ndarray], ...]
    placed_by: Tuple[Optional[str], ...]
    world: int
    edges: Tuple[Edge, ...]
    timings_s: Dict[str, float]
    voxel: Optional[float] = None

    @property
    def joined(self) -> Tuple[bool, ...]:
        """Per scan: it is the world scan, or trusted edges connect it to it."""
        return tuple(p == "registration" for p in self.placed_by)

    def to_dict(self) -> dict:
        """JSON-ready dict: world frame, per-scan poses and per-edge results."""
        return {
            "world": self.names[self.world],
            "scans": [
                {"name": name, "joined": by == "registration", "placed_by": by, "world_T_scan": None if pose is None else pose.tolist()}
                for name, pose, by in zip(self.names, self.poses, self.placed_by)
            ],
            "edges": [e.to_dict(self.names) for e in self.edges],
            "timings_s": self.timings_s,
            "voxel": self.voxel,
        }


def choose_pairs(clouds: Sequence[np.ndarray], config: MultiwayConfig, init_poses: Optional[Sequence[Optional[np.ndarray]]] = None) -> List[Tuple[int, int]]:
    """The pairs (i, j), i < j, that are registered: see :attr:`MultiwayConfig.neighbours`.

    `init_poses`: per scan a (4, 4) world_T_scan guess or None; "near" compares the centroids
    where the guesses put them."""
    n = len(clouds)
    poses = list(init_poses) if init_poses is not None else [None] * n
    if len(poses) != n:
        raise InputError(f"{len(poses)} initial poses for {n} scans")
    rule = config.neighbours
    if rule == "auto":
        rule = "all" if n <= config.all_up_to else "near" if all(p is not None for p in poses) else "sequence"
    if rule == "all":
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    if rule == "sequence":
        return [(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + config.window))]
    d = _distances([_centre(c, p) for c, p in zip(clouds, poses)])
    pairs = set()
    for i in range(n):
        for j in np.argsort(d[i])[1 : config.near + 1]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs | _joining(d, pairs))


def _joining(d: np.ndarray, pairs: set) -> set:
    """The pairs, nearest first, that join the groups `pairs` leaves apart into one (Kruskal's
    rule over the (n, n) centroid distances `d`): the nearest neighbours of the scans on either
    side of a gap in a sequence all lie on their own side."""
    n = len(d)
    group = list(range(n))
    for i, j in pairs:
        group[_root(group, i)] = _root(group, j)
    added = set()
    for flat in np.argsort(d, axis=None, kind="stable"):
        i, j = divmod(int(flat), n)
        if i < j and _root(group, i) != _root(group, j):
            group[_root(group, i)] = _root(group, j)
            added.add((i, j))
    return added


def _root(group: List[int], i: int) -> int:
    """The root of item i in the union-find forest `group` (parent per item), halving the path."""
    while group[i] != i:
        group[i] = group[group[i]]
        i = group[i]
    return i


@quietly
def multiway(
    clouds: Sequence[CloudLike],
    config: Optional[MultiwayConfig] = None,
    names: Optional[Sequence[str]] = None,
    model=None,
    progress: Optional[Callable[[int, int], None]] = None,
    init_poses: Optional[Sequence[Optional[np.ndarray]]] = None,
) -> MultiwayResult:
    """Register every scan of a scene into the frame of the first one.

    Args:
        clouds: the scans, (N_i, 3) arrays or Open3D point clouds, in the same units.
        config: the settings (None: the defaults).
        names: how to call the scans (file names); default scan0, scan1, ...
        model: an already loaded network (else loaded once from ``config.register.weights``).
        progress: called as progress(pairs done, pairs in all) after each registration.
        init_poses: per scan, a (4, 4) guess of its world_T_scan (odometry, a GPS/IMU track, an
            earlier run) or None where there is none. A pair of scans that both have one is
            registered from the pose between them (``register(init=...)``: where ICP from it is
            trusted, nothing else runs); the world scan keeps its guess, so the result is in the
            guesses' frame; "near" pairs scans by where the guesses put them; scans that no
            trusted alignment joins to the world scan are placed by their guesses relative to
            the nearest joined scan (``placed_by``).
    Returns:
        MultiwayResult.
    Raises:
        InputError: fewer than two scans, a scan that cannot be registered (empty, degenerate),
            or an initial pose that is not a rigid 4x4 transform.
    """
    from .coarse import check_loaded, load_model

    config = MultiwayConfig() if config is None else config
    if not isinstance(config, MultiwayConfig):
        raise UsageError(f"config must be an o3dsoft.MultiwayConfig (its register field holds a RegisterConfig), got {type(config).__name__}")
    config.validate()
    check_loaded(model, "model", "MultiwayConfig(register=RegisterConfig(weights=...))")
    names = tuple(names) if names is not None else None  # any iterable of names
    if names is not None and len(set(names)) != len(names):
        raise InputError(f"two scans share the name {next(n for n in names if names.count(n) > 1)!r}; give each its own")
    clouds, names = named_clouds(clouds, names, "scan", "multiway")
    points = [as_points(c, name) for c, name in zip(clouds, names)]
    guesses = _checked_poses(init_poses, names)
    model = model if model is not None else load_model(config.register.weights, config.register.device)
    t_start = time.perf_counter()
    # Each scan cleaned once, and every one checked before the first pair is registered.
    cleaning = clean_each(points, names, model.config.k)
    t_clean = time.perf_counter()

    # Register the pairs that may overlap (T_i_j maps scan j onto scan i), first with the quick
    # search (the feature match on pairs that look like a partial overlap, then the network):
    # most pairs of a scene either align at once or do not overlap at all. Without the feature
    # match, the network's wrong poses of rooms alike were trusted and kept the search away.
    pairs = choose_pairs(points, config, guesses)
    quick = config.register
    if quick.search.mode == "auto":  # flagged edges are left out or registered again: no full-resolution ICP for them
        quick = replace(quick, search=replace(quick.search, mode="quick"), refine_flagged=False)
    found: Dict[Tuple[int, int], Tuple[Edge, RegistrationResult]] = {}
    for done, (i, j) in enumerate(pairs, start=1):
        found[i, j] = _register_edge(points, cleaning, names, i, j, quick, model, guesses, config.init_max_rotation)
        if progress is not None:
            progress(done, len(pairs))
    # Then the search, only on the pairs of scans that no trusted edge reaches yet, until each joins.
    if quick is not config.register:
        group_of = _group_of(len(points), [e for e, _ in found.values()])
        # Nearest in the sequence first: a scan's next one overlaps it most, and the first
        # trusted search joins it (docs/multiway.md).
        for i, j in sorted(pairs, key=lambda pair: (pair[1] - pair[0], pair)):
            if group_of[i] != group_of[j] and found[i, j][0].likely_failed:
                found[i, j] = _register_edge(points, cleaning, names, i, j, config.register, model, guesses, config.init_max_rotation)
                if not found[i, j][0].likely_failed:  # two groups joined
                    group_of = _group_of(len(points), [e for e, _ in found.values()])
    edges = [e for e, _ in found.values()]
    results = [r for _, r in found.values()]
    t_pairs = time.perf_counter()

    # Connect the scans through their most confident edges, then optimise the graph: the world
    # scan's group, then each group that no trusted edge joins to it, placed by the initial poses
    # relative to the nearest placed scan, as one body.
    groups = _groups(len(points), edges)
    world = groups[0][0]
    poses: List[Optional[np.ndarray]] = [None] * len(points)
    placed_by: List[Optional[str]] = [None] * len(points)
    grid = _merge_grid(config, results)
    trusted = [r.tight_distance for r in results if not r.likely_failed]
    distance = float(np.median(trusted)) if trusted else 0.0  # the graph's distance (no graph without trusted edges)
    info_clouds: List[np.ndarray] = []  # built for the first graph
    tree_edges, pruned = set(), set()
    for g, group in enumerate(groups):
        if g == 0:  # the world scan, held at its initial pose where it has one
            anchor: Optional[Tuple[int, np.ndarray]] = (world, guesses[world] if guesses[world] is not None else np.eye(4))
        else:
            anchor = _anchor(points, poses, guesses, group)
        if anchor is None:
            continue
        root, root_pose = anchor
        tree = _tree(group, root, edges)
        placed = {root: root_pose}
        if tree:
            if not info_clouds:
                cleaned = (c.of(p).points for c, p in zip(cleaning, points))
                info_clouds = [voxel_downsample(c, grid, name) if grid else c for c, name in zip(cleaned, names)]
            placed, cut = _optimise(info_clouds, edges, root, root_pose, tree, distance, config)
            tree_edges.update((e.source, e.target) for _, e in tree.values())
            pruned.update(cut)
        for k, pose in placed.items():
            poses[k], placed_by[k] = pose, "registration" if g == 0 else "initial pose"
    edges = [replace(e, used=not e.likely_failed, in_tree=(e.source, e.target) in tree_edges, pruned=(e.source, e.target) in pruned) for e in edges]
    t_end = time.perf_counter()
    timings = {"clean": t_clean - t_start, "pairs": t_pairs - t_clean, "optimise": t_end - t_pairs, "total": t_end - t_start}
    return MultiwayResult(names, tuple(poses), tuple(placed_by), world, tuple(edges), timings, grid)


def _centre(cloud: np.ndarray, pose: Optional[np.ndarray]) -> np.ndarray:
    """(3,) centroid of the finite points of `cloud`, moved by the (4, 4) `pose` where given."""
    centre = cloud[np.isfinite(cloud).all(axis=1)].mean(axis=0)
    return centre if pose is None else apply_transform(pose, centre[None])[0]


def _distances(centres: Sequence[np.ndarray]) -> np.ndarray:
    """(n, n) Euclidean distances between the (3,) `centres`."""
    c = np.asarray(centres)
    return np.linalg.norm(c[:, None] - c[None], axis=-1)


def _anchor(
    points: Sequence[np.ndarray], poses: Sequence[Optional[np.ndarray]], guesses: Sequence[Optional[np.ndarray]], group: Sequence[int]
) -> Optional[Tuple[int, np.ndarray]]:
    """Where the initial poses place `group` (scans no trusted edge joins to the placed ones):
    (its scan k nearest to a placed scan a that has a guess, by the centroids the guesses place,
    and world_T_k = world_T_a @ inv(guess_a) @ guess_k), so that the correction made at a carries
    over to k as odometry would; None where the group or the placed scans have no guess.

    Args:
        points: (N_i, 3) per scan; poses: (4, 4) world_T_scan per placed scan, else None;
        guesses: (4, 4) initial world_T_scan per scan, else None.
    """
    placed = [a for a, pose in enumerate(poses) if pose is not None and guesses[a] is not None]
    members = [k for k in group if guesses[k] is not None]
    if not placed or not members:
        return None
    d = _distances([_centre(points[k], guesses[k]) for k in members + placed])[: len(members), len(members) :]
    row, col = np.unravel_index(int(np.argmin(d)), d.shape)
    k, a = members[row], placed[col]
    pose_a, guess_a, guess_k = poses[a], guesses[a], guesses[k]
    assert pose_a is not None and guess_a is not None and guess_k is not None
    return k, pose_a @ np.linalg.inv(guess_a) @ guess_k


def _checked_poses(init_poses: Optional[Sequence[Optional[np.ndarray]]], names: Sequence[str]) -> List[Optional[np.ndarray]]:
    """The initial world_T_scan poses as (4, 4) float64 arrays (None: no guess), checked rigid."""
    if init_poses is None:
        return [None] * len(names)
    if len(init_poses) != len(names):
        raise InputError(f"{len(init_poses)} initial poses for {len(names)} scans")
    poses: List[Optional[np.ndarray]] = []
    for pose, name in zip(init_poses, names):
        poses.append(None if pose is None else as_rigid(pose, f"{name}: initial pose"))
    return poses


def _register_edge(
    points: Sequence[np.ndarray],
    cleaning: Sequence[Cleaning],
    names: Sequence[str],
    i: int,
    j: int,
    config: RegisterConfig,
    model,
    guesses: Sequence[Optional[np.ndarray]],
    bound: Optional[float],
) -> Tuple[Edge, RegistrationResult]:
    """Register scan j onto scan i, each as its `cleaning` keeps it (from T_i_j = inv(world_T_i)
    @ world_T_j where both have an initial pose, then within `bound` degrees of it where `config`
    sets no rotation prior): the edge j -> i and the full result."""
    t0 = time.perf_counter()
    init = np.linalg.inv(guesses[i]) @ guesses[j] if guesses[i] is not None and guesses[j] is not None else None
    if init is not None and config.max_rotation is None and bound is not None:
        config = replace(config, max_rotation=bound)
    r = register_cleaned(cleaning[j].of(points[j]), cleaning[i].of(points[i]), config, model, names[j], names[i], init)
    return Edge(j, i, r.transformation, r.confidence, r.fitness, r.likely_failed, r.failure_reason, time.perf_counter() - t0, r.searched), r


def _groups(n: int, edges: Sequence[Edge]) -> List[List[int]]:
    """The groups of scans that trusted edges connect (a scan alone is a group), each in scan
    order, the largest first (of equal sizes, the one with the first scan)."""
    members: Dict[int, List[int]] = {}
    for k, label in enumerate(_group_of(n, edges)):
        members.setdefault(label, []).append(k)
    return sorted(members.values(), key=lambda g: (-len(g), g[0]))


def _tree(group: Sequence[int], root: int, edges: Sequence[Edge]) -> Dict[int, Tuple[int, Edge]]:
    """A maximum-confidence spanning tree of `group` over its trusted edges, from `root` (Prim's
    algorithm): {scan: (its parent, the edge between)}; {} for a scan alone."""
    inside = set(group)
    trusted = [e for e in edges if not e.likely_failed and e.source in inside and e.target in inside]
    tree: Dict[int, Tuple[int, Edge]] = {}
    reached = {root}
    while len(reached) < len(inside):
        best = max((e for e in trusted if (e.source in reached) != (e.target in reached)), key=lambda e: e.confidence)
        new, parent = (best.target, best.source) if best.source in reached else (best.source, best.target)
        tree[new] = (parent, best)
        reached.add(new)
    return tree


def _group_of(n: int, edges: Sequence[Edge]) -> List[int]:
    """Per scan, a label of its group: scans joined through the trusted ones of `edges` share it
    (union-find)."""
    group = list(range(n))
    for e in edges:
        if not e.likely_failed:
            group[_root(group, e.source)] = _root(group, e.target)
    return [_root(group, k) for k in range(n)]


def units_note(clouds: Sequence[np.ndarray], names: Sequence[str]) -> Optional[str]:
    """A warning, where the largest of the (N_i, 3) scans is over ``SIZE_RATIO_NOTE`` times the
    size of the smallest (:func:`~o3dsoft.preprocess.scene_size` of the finite points): scans
    in different units, whose pairs are never trusted; else None."""
    finite = [c[np.isfinite(c).all(axis=1)] for c in clouds]
    sizes = [scene_size(c) if len(c) > 1 else 0.0 for c in finite]
    measured = [k for k, size in enumerate(sizes) if size > 0]  # the others are refused later, by name
    if len(measured) < 2:
        return None
    big, small = max(measured, key=lambda k: sizes[k]), min(measured, key=lambda k: sizes[k])
    if not sizes[big] > SIZE_RATIO_NOTE * sizes[small]:
        return None
    return (
        f"{names[big]} is {sizes[big] / sizes[small]:.3g} times the size of {names[small]} "
        f"({sizes[big]:.4g} against {sizes[small]:.4g} units): are the scans in the same units? "
        "Scans in different units are not joined"
    )


def _merge_grid(config: MultiwayConfig, results: Sequence[RegistrationResult]) -> Optional[float]:
    """The merged cloud's (and the information matrices') grid: the config's, else the finest
    grid the trusted pairs were registered on (any pairs where none is trusted: a scan that joins
    none, registered on a finer grid of its own, does not set it); None: every point."""
    if config.voxel is not None:
        return config.voxel
    trusted = [r for r in results if not r.likely_failed] or results
    grids = [r.voxel for r in trusted if r.voxel is not None]
    return min(grids) if grids else None


def _optimise(
    clouds: Sequence[np.ndarray],
    edges: Sequence[Edge],
    world: int,
    start: np.ndarray,
    tree: Dict[int, Tuple[int, Edge]],
    distance: float,
    config: MultiwayConfig,
) -> Tuple[Dict[int, np.ndarray], set]:
    """Open3D's pose-graph optimisation of the scans of `tree` over the trusted `edges` among
    them (the tree's certain, the others loop closures), from the tree's poses, the scan `world`
    held at (4, 4) `start`: ({scan: world_T_scan}, {(source, target) of the pruned edges})."""
    from ._open3d import open3d as o3d
    from .refine import to_open3d

    reg = o3d.pipelines.registration
    # Poses along the tree: world_T_child = world_T_parent @ parent_T_child.
    pose = {world: start}
    order = [world]
    while len(order) < len(tree) + 1:
        for child, (parent, edge) in tree.items():
            if child not in pose and parent in pose:
                T_parent_child = edge.transformation if edge.source == child else np.linalg.inv(edge.transformation)
                pose[child] = pose[parent] @ T_parent_child
                order.append(child)
    node_of = {scan: k for k, scan in enumerate(order)}
    certain = {(e.source, e.target) for _, e in tree.values()}  # the tree's edges; the other trusted ones are loop closures
    graph = reg.PoseGraph()
    for scan in order:
        graph.nodes.append(reg.PoseGraphNode(pose[scan]))
    o3d_clouds = {scan: to_open3d(clouds[scan]) for scan in order}
    graph_edges = []
    for e in edges:
        if e.likely_failed or e.source not in node_of or e.target not in node_of:
            continue
        info = reg.get_information_matrix_from_point_clouds(o3d_clouds[e.source], o3d_clouds[e.target], distance, e.transformation)
        graph.edges.append(reg.PoseGraphEdge(node_of[e.source], node_of[e.target], e.transformation, info, uncertain=(e.source, e.target) not in certain))
        graph_edges.append((e.source, e.target))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=distance,
        edge_prune_threshold=config.prune_below,
        preference_loop_closure=config.loop_closure_preference,
        reference_node=node_of[world],
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option)
    kept = {(order[e.source_node_id], order[e.target_node_id]) for e in graph.edges}
    pruned = {pair for pair in graph_edges if pair not in kept}
    return {scan: np.asarray(graph.nodes[node_of[scan]].pose).copy() for scan in order}, pruned


class Merged(NamedTuple):
    """points: (P, 3) the joined scans in the world frame; scans: (P,) the index of the scan each
    point came from (the first scan's in a voxel holding several); colors: (P, 3) in 0-1, where
    every joined scan has colours, else None."""

    points: np.ndarray
    scans: np.ndarray
    colors: Optional[np.ndarray] = None


def merged_cloud(
    clouds: Sequence[CloudLike], result: MultiwayResult, voxel: Optional[float] = None, colors: Optional[Sequence[Optional[np.ndarray]]] = None
) -> Merged:
    """The joined scans in the world frame, on a voxel grid of `voxel` (None: every point; a
    voxel's point and colour are the means of those in it); scans placed by their initial pose
    alone are left out. `colors`: per scan, (N_k, 3) in 0-1 row for row with its cloud, or None."""
    parts, labels, tints = [], [], []
    for k, (cloud, pose, joined) in enumerate(zip(clouds, result.poses, result.joined)):
        if not joined:
            continue
        kept = clean_points(as_points(cloud, result.names[k]), result.names[k])
        parts.append(apply_transform(pose, kept.points))
        labels.append(np.full(len(kept.points), k))
        tint = None if colors is None else colors[k]
        tints.append(None if tint is None else np.asarray(tint, dtype=np.float64)[kept.rows])
    points, label = np.concatenate(parts), np.concatenate(labels)
    color = np.concatenate(tints) if all(t is not None for t in tints) else None
    if voxel:
        keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
        sides = keys.max(axis=0) + 1
        if float(np.prod(sides.astype(np.float64))) < 2.0**62:  # one integer per cell, row-major: sorts 10 times as fast as rows
            _, first, inverse = np.unique((keys[:, 0] * sides[1] + keys[:, 1]) * sides[2] + keys[:, 2], return_index=True, return_inverse=True)
        else:
            _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        counts = np.bincount(inverse, minlength=len(first))[:, None]

        def mean(values: np.ndarray) -> np.ndarray:
            sums = np.zeros((len(first), 3))
            np.add.at(sums, inverse, values)
            return sums / counts

        return Merged(mean(points), label[first], None if color is None else mean(color))
    return Merged(points, label, color)


callable_as_its_function(__name__)
