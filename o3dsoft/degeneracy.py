"""Whether the geometry determines the pose: a registration of clouds that slide on themselves
(planes, lines, spheres, cylinders) or that fill a volume has no one answer, however well it
fits, and is flagged rather than trusted. Two measurements:

``constraint`` is the smallest over the largest eigenvalue of the point-to-plane normal equations
  at the result, H = mean_i J_i^T J_i with J_i = [(c_i x n_i)^T, n_i^T], c_i a matched point
relative to the matched points' centre over the pair's scale and n_i its partner's surface
normal. A direction of motion (rotation or translation) that moves no point off the other
cloud's surface has eigenvalue 0, as in degeneracy-aware ICP (Zhang, Kaess and Singh, ICRA 2016).

``flatness`` is how well the clouds still fit with the source turned 30 degrees about its centre,
about each axis either way: the best of those six consistencies (scaled down by any overlap
lost) over the result's own. Points that fill a volume, or a ball, fit about as well at any
turn (0.85-1.0); surfaces that fix the pose lose most of their fit (0.2-0.55 on real scans).

Clouds that share their points (benchmark pairs cut from one point set) are held to neither:
their points fix the pose where the surface alone does not, so neither is measured there. Evenly
spaced clouds (a depth camera's pixels on a wall, cells of a voxel grid) are never taken to share
their points: on a lattice, points coincide at many poses, so coinciding says nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, List, NamedTuple, Optional, Tuple

import numpy as np
from scipy.spatial import cKDTree

from . import refine as refine_stage
from .confidence import Features, Scorer
from .preprocess import flat_normal
from .transforms import apply_transform, axis_angle_to_matrix, euler_to_matrix, rigid


@dataclass(frozen=True)
class DegeneracyConfig:
    """Settings of :func:`assess`.

    Attributes:
        min_constraint: results whose ``constraint`` is below this are flagged (0-1), unless
            the two clouds share their points: then the points, not the surface, fix the pose.
        max_flatness: results whose ``flatness`` reaches this are flagged (0-1).
        turn_deg: the turn of the source that ``flatness`` tries (degrees).
        shared_below: the clouds are taken to share points when the confidence's spacing ratio
            (median distance to the nearest partner over the point spacing) is below this: 0
            for identical points, about 1 for two samplings of one surface.
        regular_below: a cloud whose nearest-neighbour distances vary by less than this
            (standard deviation over mean) is a lattice, and the spacing ratio does not make
            it share points (0.07 on a depth camera's wall, 0.4-0.6 on ModelNet40's shapes).
        neighbours: points of a local plane (its normal).
        line_neighbours: points of a local line of a flat cloud's outline (its normal within
            the plane): fewer, so that two walls of a corridor a few spacings apart stay apart.
        max_points: the clouds are voxel-downsampled to about this many points first.
        held_from: from a caller's guess, on a flagged result (``constraint`` below
            ``min_constraint``), the directions of motion whose eigenvalue is below this share of
            the largest are left at the guess (:func:`held_motion`); 0: off.
        probe_below: a trusted result whose ``constraint`` is below this (and at least
            ``min_constraint``) is probed along the motion its surfaces hold least
            (:func:`probe_starts`; a mug's body turns freely on the other view while its handle,
            which fixes the pose, finds no partner); 0: off.
        probe_steps: how far the probe moves the pose each way, in radians of turn or shares of
            the pair's scale of shift.
    """

    min_constraint: float = 2e-3
    max_flatness: float = 0.85
    turn_deg: float = 30.0
    shared_below: float = 0.5
    regular_below: float = 0.2
    neighbours: int = 20
    line_neighbours: int = 6
    max_points: int = 5000
    held_from: float = 0.1
    probe_below: float = 0.015
    probe_steps: Tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)


class Degeneracy(NamedTuple):
    """constraint: smallest / largest eigenvalue of the point-to-plane normal equations (0-1,
    higher is better; 0: some motion leaves the fit unchanged); flatness: the best fit 30 degrees
    away over the result's (0-1, lower is better; about 1: any turn fits as well); both None where
    the clouds share their points (not measured); reason: why the pose is not determined, in
    words, or None; loosest: (6,) the unit motion the surfaces hold least (the normal equations'
    parameters: rotation times the pair's scale, then translation, in the target's frame) and
    centre: (3,) the centre of the matched points it turns about, where measured."""

    constraint: Optional[float]
    flatness: Optional[float]
    reason: Optional[str]
    loosest: Optional[np.ndarray] = None
    centre: Optional[np.ndarray] = None


# Clouds that share their points: their points fix the pose, and neither measurement is taken.
SHARED_POINTS = Degeneracy(None, None, None)


def assess(
    source: np.ndarray,
    target: np.ndarray,
    transformation: np.ndarray,
    distance: float,
    scale: float,
    spacing_ratio: float = 1.0,
    config: DegeneracyConfig = DegeneracyConfig(),
    make_scorer: Optional[Callable[[], Callable[[np.ndarray], Features]]] = None,
) -> Degeneracy:
    """How well the geometry of the pair determines the pose `transformation`.

    Args:
        source: (N, 3); target: (M, 3); transformation: (4, 4) T_target_source.
        distance: points farther than this (cloud units) from the other cloud are not matched.
        scale: the pair's scale (cloud units), which makes rotations and translations comparable.
        spacing_ratio: the confidence's spacing ratio at `transformation`: below
            ``config.shared_below``, on clouds that are not lattices (:func:`is_lattice`), the
            clouds share their points, and :data:`SHARED_POINTS` is returned without measuring.
        config: thresholds and sizes.
        make_scorer: returns the confidence's measurements of an alignment of these clouds, e.g.
            a scorer built already (default: a new :class:`~o3dsoft.confidence.Scorer`); called
            only where the clouds do not share their points.
    """
    if spacing_ratio < config.shared_below and not is_lattice(target, config.regular_below):  # clouds that share points are both lattices or neither
        return SHARED_POINTS
    source = refine_stage.downsample(np.asarray(source, dtype=np.float64), config.max_points)
    target = refine_stage.downsample(np.asarray(target, dtype=np.float64), config.max_points)
    moved = apply_transform(transformation, source)
    plane = flat_normal(target)
    equations = _normal_equations(moved, target, distance, scale, config, plane)
    constraint, free, loosest, centre = 0.0, "", None, None
    if equations is not None:
        basis = np.eye(6) if plane is None else _within(plane)
        eigenvalues, vectors = np.linalg.eigh(basis.T @ equations[0] @ basis)
        constraint = float(max(eigenvalues[0], 0.0) / max(eigenvalues[-1], 1e-300))
        loosest, centre = basis @ vectors[:, 0], equations[1]
        loose = eigenvalues < config.min_constraint * max(eigenvalues[-1], 1e-300)
        free = ", ".join(_motion_in_words(basis @ v) for v in vectors[:, loose].T)
        free = f"; the surfaces hold no {free} (target frame)" if free else ""
    scorer = make_scorer() if make_scorer is not None else Scorer(source, target, distance)
    base = scorer(transformation)
    flatness = _flatness(scorer, transformation, base, moved.mean(axis=0), config.turn_deg)
    slide = _slide(scorer, transformation, base, plane) if plane is not None else None
    reason = None
    if equations is None:  # a correspondence distance far below the clouds' spacing (set by hand)
        reason = f"under 6 points lie within {distance:.3g} units of the other cloud (ICP's correspondence distance): whether the surfaces fix the pose is not measured"
    elif constraint < config.min_constraint:
        reason = f"the clouds can slide on each other (planes, lines, spheres, cylinders), or only a few of their points hold the pose (an object on a table): the pose is not determined (constraint {constraint:.1e}, below {config.min_constraint:g}){free}"
    elif slide is not None and slide[0] >= config.max_flatness:
        # The outline's normals come from a few points each, which noise tilts: the fit itself says whether a shift keeps it.
        fit, shift, along = slide
        reason = (
            f"the clouds slide on each other within their plane (a 2D scan): shifted {shift:.3g} units along "
            f"({along[0]:.2f}, {along[1]:.2f}, {along[2]:.2f}) they fit {fit:.2f} as well (from {config.max_flatness:g}: not determined)"
        )
    elif flatness >= config.max_flatness:
        reason = (
            f"the clouds fit about as well turned {config.turn_deg:g} degrees (flatness {flatness:.2f}): the pose is not determined "
            "(points that fill a volume or a ball, or a pose where the clouds meet only on a patch such as the ground)"
        )
    return Degeneracy(constraint, flatness, reason, loosest, centre)


def probe_starts(transformation: np.ndarray, loosest: np.ndarray, centre: np.ndarray, scale: float, steps: Tuple[float, ...]) -> List[np.ndarray]:
    """(4, 4) poses to start ICP from: `transformation` moved each way by each of `steps` along
    the (6,) motion `loosest` (:attr:`Degeneracy.loosest`: rotation times `scale`, then
    translation), turning about `centre` (3,) in the target's frame."""
    starts = []
    for step in steps:
        for sign in (1.0, -1.0):
            m = sign * step * scale * loosest
            R = axis_angle_to_matrix(m[:3] / scale)
            starts.append(rigid(R, centre - R @ centre + m[3:]) @ transformation)
    return starts


LINE_SPREAD = 0.25  # a flat cloud's points follow a line where their spread across it is at most this share of along it (variances)


def _motion_in_words(motion: np.ndarray) -> str:
    """The (6,) motion of the normal equations' parameters (rotation times the length it is scaled
    by, translation) in words, by its larger part: "shift along (x, y, z)" or "turn about (x, y,
    z)", its axis in the target's frame (sign arbitrary)."""
    turn, shift = np.linalg.norm(motion[:3]), np.linalg.norm(motion[3:])
    kind, axis = ("shift along", motion[3:] / shift) if shift >= turn else ("turn about", motion[:3] / turn)
    axis = np.round(axis if axis[np.argmax(np.abs(axis))] > 0 else -axis, 2) + 0.0  # no "-0.00"
    return f"{kind} ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f})"


def _within(plane: np.ndarray) -> np.ndarray:
    """(6, 3) the motions within the plane of unit normal `plane` (3,), as columns of the normal
    equations' parameters (rotation, translation): the turn about its normal and two shifts along
    it. On two flat clouds (2D scans) the motions out of the plane are held by both lying in it."""
    u = np.cross(plane, [1.0, 0.0, 0.0] if abs(plane[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    basis = np.zeros((6, 3))
    basis[:3, 0], basis[3:, 1], basis[3:, 2] = plane, u, np.cross(plane, u)
    return basis


def _in_plane_normals(points: np.ndarray, plane: np.ndarray, neighbours: int) -> np.ndarray:
    """(N, 3) unit normals within the plane of normal `plane` of the (N, 3) flat points: across the
    line their `neighbours` nearest points follow (a 2D scan's outline); zero where those points
    do not follow a line (within LINE_SPREAD: the inside of a filled flat shape), which then
    holds no motion."""
    _, j = cKDTree(points).query(points, k=min(neighbours, len(points)))
    values, vectors = refine_stage.local_spread(points[j])
    across = np.cross(plane, vectors[:, :, -1])  # the line's direction is the largest eigenvector
    across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-300)
    return across * (values[:, 1] <= LINE_SPREAD * values[:, 2])[:, None]  # values[:, 0]: across the plane, 0


def _normal_equations(
    moved: np.ndarray,
    target: np.ndarray,
    distance: float,
    scale: Optional[float],
    config: DegeneracyConfig,
    plane: Optional[np.ndarray] = None,
) -> Optional[Tuple[np.ndarray, np.ndarray, float]]:
    """The point-to-plane normal equations of the (N, 3) source `moved` by the result onto the
    (M, 3) target, over its points within `distance` of it: ((6, 6) H,
    (3,) the centre of those moved points, in the target's frame, and the length rotations are
    scaled by); None under 6 such points. H's parameters: rotation (radians) times that length,
    `scale` (None: the RMS distance of those points from their centre, so that a rotation and a
    translation that move them as far weigh the same), then translation (cloud units). `plane`:
    the unit normal of a flat target's plane, whose normals are then taken within it."""
    dist, j = cKDTree(target).query(moved, distance_upper_bound=distance)
    matched = np.isfinite(dist)
    if matched.sum() < 6:
        return None
    centre = moved[matched].mean(axis=0)
    if scale is None:
        scale = max(float(np.sqrt(np.mean(np.sum((moved[matched] - centre) ** 2, axis=1)))), 1e-300)
    c = (moved[matched] - centre) / scale
    n = (refine_stage.normals(target, config.neighbours) if plane is None else _in_plane_normals(target, plane, config.line_neighbours))[j[matched]]
    J = np.hstack([np.cross(c, n), n])  # (K, 6): d(residual) / d(rotation, translation)
    return J.T @ J / len(J), centre, scale


# :func:`held_motion` keeps no motion that turns the source more than this many degrees beyond the
# turn it was given (the projection is linear, and valid for small motions only).
HELD_MAX_EXTRA_TURN = 1.0


def held_motion(
    source: np.ndarray, target: np.ndarray, transformation: np.ndarray, distance: float, config: DegeneracyConfig = DegeneracyConfig()
) -> np.ndarray:
    """The part of the motion `transformation` (4, 4) (from the identity: where a caller's guess
    put the source) that the surfaces hold: its motion along the directions of the normal
    equations whose eigenvalue is below ``held_from`` of the largest is undone, so that the
    guess stands there (degeneracy-aware solution remapping, Zhang, Kaess and Singh, ICRA 2016).
    A corridor's walls hold the motion across it, not along it.

    Args:
        source: (N, 3), as the guess placed it; target: (M, 3); distance: cloud units.
    Returns:
        (4, 4) float64; the identity where under 6 points lie within `distance`, or where the
        motion kept would turn the source more than :data:`HELD_MAX_EXTRA_TURN` degrees beyond
        `transformation`'s own turn (a motion too large for the projection, which is linear);
        `transformation` itself where ``held_from`` is 0.
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(transformation, dtype=np.float64)
    if config.held_from <= 0:
        return T.copy()
    source = refine_stage.downsample(np.asarray(source, dtype=np.float64), config.max_points)
    target = refine_stage.downsample(np.asarray(target, dtype=np.float64), config.max_points)
    equations = _normal_equations(apply_transform(T, source), target, distance, None, config)
    if equations is None:
        return np.eye(4)
    H, centre, scale = equations
    eigenvalues, vectors = np.linalg.eigh(H)
    held = vectors[:, eigenvalues >= config.held_from * max(eigenvalues[-1], 1e-300)]
    start = np.linalg.solve(T[:3, :3], centre - T[:3, 3])  # the source point T moves to the centre
    motion = np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec() * scale, centre - start])  # about that point
    kept = held @ (held.T @ motion)
    if np.linalg.norm(kept[:3]) / scale > np.linalg.norm(motion[:3]) / scale + math.radians(HELD_MAX_EXTRA_TURN):
        # The projection is linear: on a motion far from small (a turn and a long slide along a
        # wall) it can trade the slide for a turn larger than the motion's own, up to a half turn.
        # No part of such a motion can be kept apart: the guess stands.
        return np.eye(4)
    R = Rotation.from_rotvec(kept[:3] / scale).as_matrix()
    return rigid(R, start + kept[3:] - R @ start)


def _kept_fit(moved: Features, base: Features) -> float:
    """The consistency of the source moved away from the result (`moved`), scaled by the share of
    the result's overlap it keeps, over the result's (`base`, whose consistency is positive)."""
    return moved.consistency * min(1.0, moved.overlap / max(base.overlap, 1e-12)) / base.consistency


LATTICE_PROBES = 256  # points whose nearest neighbour is measured by :func:`is_lattice`


def is_lattice(points: np.ndarray, regular_below: float = DegeneracyConfig.regular_below) -> bool:
    """Whether the (N, 3) points are evenly spaced: the nearest-neighbour distances of about
    :data:`LATTICE_PROBES` of them, taken evenly, have a standard deviation over their mean below
    `regular_below` (0 on a grid; about 0.5 for points drawn at random on a surface)."""
    if len(points) < 3:
        return False
    probes = points[:: max(1, len(points) // LATTICE_PROBES)]  # evenly through the cloud: a spread needs no more
    distances = cKDTree(points).query(probes, k=2)[0][:, 1]
    mean = float(distances.mean())
    return mean > 0 and float(distances.std()) < regular_below * mean


def _slide(scorer: Callable[[np.ndarray], Features], transformation: np.ndarray, base: Features, plane: np.ndarray) -> Tuple[float, float, np.ndarray]:
    """For clouds in the plane of unit normal `plane` (3,): the best :func:`_kept_fit` of the
    source shifted by three of the scorer's tight distances along 8 directions within the plane,
    either way (`base`: the result's own measurements); the shift (cloud units) and the (3,)
    direction of that best. A corridor's walls or a filled sheet fit as well shifted along them
    (about 1); an outline with walls across each other loses half."""
    shift = 3.0 * base.tight_distance
    basis = _within(plane)[3:, 1:]  # (3, 2): two directions within the plane
    best = (0.0, shift, basis[:, 0])
    if base.consistency <= 0:
        return best
    for angle in np.radians(np.arange(0.0, 360.0, 22.5)):
        along = basis @ [np.cos(angle), np.sin(angle)]
        fit = _kept_fit(scorer(rigid(np.eye(3), shift * along) @ transformation), base)
        if fit > best[0]:
            best = (fit, shift, np.round(along, 2) + 0.0)
    return best


def _flatness(scorer: Callable[[np.ndarray], Features], transformation: np.ndarray, base: Features, centre: np.ndarray, turn_deg: float) -> float:
    """The best :func:`_kept_fit` of the source turned by `turn_deg` about `centre` (3,), about
    each axis either way (`base`: the result's own measurements)."""
    if base.consistency <= 0:
        return 0.0
    best = 0.0
    for axis in np.eye(3):
        for sign in (1.0, -1.0):
            R = euler_to_matrix(sign * turn_deg * axis)
            best = max(best, _kept_fit(scorer(rigid(R, centre - R @ centre) @ transformation), base))
    return best
