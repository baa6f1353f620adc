"""The global search's building blocks, for pairs with no usable initial guess.

- :class:`FeatureMatch`: FPFH features matched by a RANSAC that keeps many distinct hypotheses,
  best-supported first, and votes for translations at a given rotation.
- :func:`network_candidates`: the network from many starting rotations as one batch
  (:func:`cube_rotations` cover SO(3), :func:`local_rotations` the pose as given), ranked and
  polished by :func:`select`.
- :func:`half_turns`: the turns that align a nearly symmetric shape the other way round.

The strategies in :mod:`o3dsoft.strategies` use them to propose estimates to the pipeline.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from . import baselines
from . import confidence as confidence_stage
from . import refine as refine_stage
from .coarse import CoarseModel
from .preprocess import principal_axes
from .procrustes import weighted_procrustes
from .transforms import axis_angle_to_matrix, first_of_each_pose, near_poses, rigid


def cube_rotations() -> np.ndarray:
    """The 24 rotations of a cube (the octahedral group), identity first: (24, 3, 3) float64."""
    rotations = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                rotations.append(R)
    return np.stack(rotations)


def local_rotations(angle_deg: float = 45.0) -> np.ndarray:
    """The identity and the 14 rotations by `angle_deg` about the axes through a cube's 6 faces
    and 8 corners: starts around the pose the clouds are given in, (15, 3, 3) float64."""
    axes = [np.array(a, dtype=np.float64) for a in itertools.product((-1.0, 0.0, 1.0), repeat=3) if np.count_nonzero(a) in (1, 3)]
    turns = [axis_angle_to_matrix(np.radians(angle_deg) * axis / np.linalg.norm(axis)) for axis in axes]
    return np.stack([np.eye(3), *turns])


def half_turns(points: np.ndarray) -> np.ndarray:
    """The turns by 180 degrees about the principal axes of an (N, 3) cloud, largest variance
    first: (3, 3, 3) float64. A shape nearly symmetric under one of them (a guitar's face and back,
    a table's ends) is often aligned the other way round, more so when a crop breaks the symmetry
    only in part."""
    return np.stack([2.0 * np.outer(a, a) - np.eye(3) for a in principal_axes(points).T])


def network_candidates(model: CoarseModel, source: np.ndarray, target: np.ndarray, rotations: np.ndarray, passes: int = 1) -> np.ndarray:
    """The network's estimate from each starting rotation, as one batch.

    Args:
        model: a loaded model.
        source: (N, 3) normalised source points.
        target: (M, 3) normalised target points.
        rotations: (H, 3, 3) starting rotations applied to the source about its centroid c.
        passes: the network's passes (at least 1), each from the rotation the one before gave
            (the target's descriptors are computed once).
    Returns:
        (H, 4, 4) float64 T_target_source in the normalised frame, one per start.
    """
    source = np.asarray(source, dtype=np.float64)
    centre = source.mean(axis=0)
    run = model.aligner(torch.as_tensor(np.ascontiguousarray(target), dtype=torch.float32).unsqueeze(0))
    for _ in range(passes):
        starts = np.einsum("hij,nj->hni", rotations, source - centre)  # the network expects a centred source
        src = torch.as_tensor(starts, dtype=torch.float32)
        R, t, _ = run(src, model.neighbours(src[:1]))  # rotations keep the neighbourhoods
        R, t = R.double().cpu().numpy(), t.double().cpu().numpy()
        rotations = R @ rotations  # p -> R (Rh (p - c)) + t
    return np.stack([rigid(rotations[h], t[h] - rotations[h] @ centre) for h in range(len(rotations))])


class Choice(NamedTuple):
    """The search's pick: `estimate` (4, 4), the candidate as the network gave it, and
    `polished` (4, 4), the same after ICP on the samples."""

    estimate: np.ndarray
    polished: np.ndarray


def select(
    source: np.ndarray,
    target: np.ndarray,
    candidates: np.ndarray,
    distance: float,
    keep: int,
    icp: Optional[refine_stage.ICPConfig] = refine_stage.ICPConfig(),
    confidence: confidence_stage.ConfidenceConfig = confidence_stage.ConfidenceConfig(),
) -> Choice:
    """The candidate that fits best, after a quick ICP on small samples of the clouds.

    The candidates are ranked by the share of source points within distance / 2 of the target;
    the `keep` best are refined by ICP on the samples and compared by their confidence. With `icp` None nothing is
    refined: the top-ranked candidate is picked.

    Args:
        source: (N, 3), target: (M, 3): samples of the clouds (ICP runs once per kept candidate).
        candidates: (H, 4, 4) T_target_source in the clouds' frame.
        distance: the ICP correspondence distance (cloud units).
        keep: how many of the ranked candidates to refine.
        icp: ICP settings (its distance schedule and convergence criteria), or None.
        confidence: how the polished candidates are scored.
    """
    fitness = [refine_stage.evaluate(source, target, T, 0.5 * distance).fitness for T in candidates]
    kept = sorted(range(len(candidates)), key=lambda h: -fitness[h])[:keep]
    if icp is None:
        return Choice(candidates[kept[0]], candidates[kept[0]])
    # One target for every candidate: its normals and KD-tree once.
    plane = icp.method == "plane"
    normals = refine_stage.normals(target, icp.normal_neighbours, icp.normal_within) if plane else None
    tree = refine_stage.kd_tree(target) if plane else None
    polished = [refine_stage.icp(source, target, candidates[h], distance, icp, normals, tree).transformation for h in kept]
    scorer = confidence_stage.Scorer(source, target, distance, config=confidence)
    trust = [confidence_stage.confidence(scorer(T), confidence) for T in polished]
    best = int(np.argmax(trust))
    return Choice(candidates[kept[best]], polished[best])


# Clouds of up to this many points (after the features' voxel grid) are matched through a table of
# all feature distances, and keep one of squared distances for the edge checks (32 MB each at
# most); larger ones through KD-trees. Both give the same matches.
TABLE_POINTS = 2048


@dataclass(frozen=True)
class FeatureMatchConfig:
    """Settings of :class:`FeatureMatch`.

    Attributes:
        features: voxel, FPFH radii, RANSAC distance and edge-length ratio. Open3D's tutorial
            values but for normals oriented towards the centroid (features independent of the
            frame each cloud is given in) estimated over 3 voxels (steadier under noise).
        hypotheses: triplets of matches drawn, all scored at once.
        scored_matches: matches a hypothesis is scored on (a random subset when there are more).
        distinct_deg, distinct_shift: candidates closer than this in rotation (degrees) and in
            where they put the matches' centre (x scale) are one candidate.
    """

    features: baselines.GlobalConfig = baselines.GlobalConfig(normal_radius=3.0, orient_normals=True)
    hypotheses: int = 100_000
    scored_matches: int = 1_000
    distinct_deg: float = 10.0
    distinct_shift: float = 0.1


class FeatureMatch:
    """FPFH features of both clouds, computed once (clouds voxel-downsampled to
    ``features.voxel`` x `scale` first), and matched by a RANSAC that keeps many distinct
    hypotheses (:meth:`candidates`).

    Open3D's RANSAC returns the one hypothesis with the most inlier matches, and with partial
    overlap that is often a wrong one. Here every hypothesis is drawn and scored as one array
    operation, and the best-supported distinct ones are returned in order, for the pipeline to
    refine and score in turn. The draws come from a seeded generator, so the same seed gives the
    same candidates (Open3D's multi-threaded RANSAC may not). Measurements: docs/pipeline.md.

    Args:
        source: (N, 3); target: (M, 3), in their original frames.
        scale: the pair's scale (cloud units).
        config: feature and RANSAC settings.
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, scale: float, config: FeatureMatchConfig = FeatureMatchConfig()) -> None:
        self.source = baselines.fpfh_features(source, scale, config.features)
        self.target = baselines.fpfh_features(target, scale, config.features)
        self.scale = scale
        self.config = config
        self._drawn: Dict[Tuple[int, int], Optional[Tuple[np.ndarray, ...]]] = {}

    @property
    def inlier_distance(self) -> float:
        """RANSAC's inlier distance in cloud units: a candidate carries its matches to within it."""
        features = self.config.features
        return features.ransac_distance * features.voxel * self.scale

    def points(self) -> Tuple[np.ndarray, np.ndarray]:
        """The downsampled clouds the features describe: (N', 3) source, (M', 3) target."""
        return np.asarray(self.source.cloud.points), np.asarray(self.target.cloud.points)

    def match_indices(self) -> Tuple[np.ndarray, np.ndarray]:
        """Point pairs whose features are nearest neighbours, in either direction: (C,) indices
        into the downsampled source and (C,) into the downsampled target (see :meth:`points`)."""
        fs, ft = np.asarray(self.source.fpfh.data).T, np.asarray(self.target.fpfh.data).T
        if max(len(fs), len(ft)) <= TABLE_POINTS:  # one table of all feature distances serves both ways
            d = cdist(fs, ft, "sqeuclidean")
            to_target, to_source = d.argmin(axis=1), d.argmin(axis=0)
        else:
            _, to_target = cKDTree(ft).query(fs)
            _, to_source = cKDTree(fs).query(ft)
        return np.concatenate([np.arange(len(fs)), to_source]), np.concatenate([to_target, np.arange(len(ft))])

    def candidates(self, seed: int, count: int) -> np.ndarray:
        """Up to `count` distinct estimates, the best-supported first: (H, 4, 4) T_target_source.

        Draws ``hypotheses`` triplets of matches (:class:`FeatureMatchConfig`), keeps those whose three edge lengths agree in
        both clouds (within the edge-length ratio), fits each by least squares, and ranks them by
        how many matches they carry to within the RANSAC distance. The `count` best that differ
        (by ``distinct_deg`` in rotation or ``distinct_shift`` x scale in where they put the matches'
        centre) are refitted on all the matches they carry; refits that meet are kept once.
        Empty when there are fewer than 3 matches or no triplet passes the check. With the same
        seed, the candidates for a larger count begin with those for a smaller one, and the
        triplets are drawn only once.

        Raises:
            ValueError: count below 1.
        """
        if count < 1:
            raise ValueError(f"count must be at least 1, got {count}")
        drawn = self._draw(seed, self.config.hypotheses)
        if drawn is None:
            return np.empty((0, 4, 4))
        a, b, R, t, support = drawn
        distance = self.inlier_distance
        centre = a.mean(axis=0)
        moved = R @ centre + t  # where each hypothesis puts the matches' centre
        kept: List[int] = []
        free = np.ones(len(R), dtype=bool)  # not near a kept hypothesis
        for h in np.argsort(-support, kind="stable"):
            if free[h]:
                kept.append(int(h))
                if len(kept) == count:
                    break
                free &= ~near_poses(R, moved, R[h], moved[h], self.scale, *self._distinct)
        refits = self._refit(R[kept], t[kept], a, b, distance)
        return refits[first_of_each_pose(refits, centre, self.scale, *self._distinct)]  # refits can meet: each pose once

    @property
    def _distinct(self) -> Tuple[float, float]:
        return self.config.distinct_deg, self.config.distinct_shift

    def translations(self, rotation: np.ndarray, count: int) -> np.ndarray:
        """Estimates that keep `rotation` and take the translations most matches vote for: (H, 4, 4).

        Under the right rotation R every right match (a, b) gives the same t = b - R a, so one
        right match is enough where RANSAC needs three at once. Each match votes for its t; the
        translation with the most votes within the RANSAC distance wins, its neighbourhood (two
        distances) is taken out, and so on, up to `count` estimates, each at the mean of its
        voters. For pairs whose feature estimates all slide along a flat or repeated shape at
        about the right rotation. Empty when there are no matches.

        Args:
            rotation: (3, 3) rotation of the source.
            count: at most this many estimates (at least 1).
        """
        if count < 1:
            raise ValueError(f"count must be at least 1, got {count}")
        (ps, pt), (ms, mt) = self.points(), self.match_indices()
        if len(ms) == 0:
            return np.empty((0, 4, 4))
        votes = pt[mt] - ps[ms] @ np.asarray(rotation).T
        tree = cKDTree(votes)
        radius = self.inlier_distance
        support = tree.query_ball_point(votes, radius, return_length=True)
        free = np.ones(len(votes), dtype=bool)
        estimates: List[np.ndarray] = []
        for i in np.argsort(-support, kind="stable"):
            if free[i]:
                estimates.append(rigid(rotation, votes[tree.query_ball_point(votes[i], radius)].mean(axis=0)))
                if len(estimates) == count:
                    break
                free[tree.query_ball_point(votes[i], 2.0 * radius)] = False
        return np.stack(estimates)

    def _draw(self, seed: int, hypotheses: int) -> Optional[Tuple[np.ndarray, ...]]:
        """The matches a (C, 3), b (C, 3), the hypotheses R (H', 3, 3), t (H', 3) of the
        triplets that pass the edge-length check, and their support (H',); None when there are
        none. Kept per seed, so that asking again for more candidates does not draw again."""
        key = (seed, hypotheses)
        if key not in self._drawn:
            self._drawn[key] = None
            (ps, pt), (ms, mt) = self.points(), self.match_indices()
            a, b = ps[ms], pt[mt]
            if len(a) < 3:
                return None
            rng = np.random.default_rng(seed)
            pick = rng.integers(0, len(a), size=(hypotheses, 3))
            # Squared edge lengths against the squared ratio, one edge at a time on the triplets
            # still in: few pass the first (under 1 in 100 pass all three on ModelNet40 crops).
            # Matches share points, so small clouds look them up in a table of all of them.
            tables = [cdist(p, p, "sqeuclidean") if len(p) <= TABLE_POINTS else None for p in (ps, pt)]
            for i, j in ((0, 1), (1, 2), (0, 2)):
                dp = _squared_distances(ps, ms[pick[:, i]], ms[pick[:, j]], tables[0])
                dq = _squared_distances(pt, mt[pick[:, i]], mt[pick[:, j]], tables[1])
                pick = pick[(np.minimum(dp, dq) >= self.config.features.edge_length**2 * np.maximum(dp, dq)) & (dp > 0)]
            if len(pick) == 0:
                return None
            R, t = weighted_procrustes(torch.from_numpy(a[pick]), torch.from_numpy(b[pick]))  # (H', 3, 3) triplets
            R, t = R.numpy(), t.numpy()
            scored = rng.choice(len(a), size=self.config.scored_matches, replace=False) if len(a) > self.config.scored_matches else np.arange(len(a))
            self._drawn[key] = (a, b, R, t, _support(R, t, a[scored], b[scored], self.inlier_distance))
        return self._drawn[key]

    @staticmethod
    def _refit(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray, distance: float) -> np.ndarray:
        """The least-squares fit of all the matches each hypothesis (R (K, 3, 3), t (K, 3))
        carries (its three points only fix it roughly), as Open3D's RANSAC ends: (K, 4, 4). One
        batched fit with each hypothesis's inliers weighted 1 and the rest 0; a hypothesis that
        carries fewer than 3 matches is kept as it is."""
        inliers = np.sum((np.einsum("kij,nj->kni", R, a) + t[:, None] - b) ** 2, axis=2) < distance**2  # (K, C)
        source, target = (torch.from_numpy(x).expand(len(R), -1, -1) for x in (a, b))
        R_fit, t_fit = weighted_procrustes(source, target, torch.from_numpy(inliers.astype(a.dtype)))
        enough = inliers.sum(axis=1) >= 3
        return np.stack([rigid(R_fit[k].numpy(), t_fit[k].numpy()) if enough[k] else rigid(R[k], t[k]) for k in range(len(R))])


def _squared_distances(points: np.ndarray, i: np.ndarray, j: np.ndarray, table: Optional[np.ndarray] = None) -> np.ndarray:
    """|points[i] - points[j]|^2 for index arrays i, j (P,): from `table`, the (N, N) squared
    distances of all the points, when given (one lookup per pair instead of two gathers of
    coordinates: the edge checks of 100,000 triplets took half the time). (P,) float64."""
    if table is not None:
        return table[i, j]
    return np.sum((points[i] - points[j]) ** 2, axis=1)


def _support(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray, distance: float) -> np.ndarray:
    """For each hypothesis (R (H, 3, 3), t (H, 3)), how many matches (a (C, 3) -> b (C, 3)) it
    carries to within `distance`: (H,) counts.

    ||R a + t - b||^2 = |a|^2 + |b|^2 + |t|^2 + 2 a.(R^T t) - 2 b^T R a - 2 t.b is one matrix
    product of a per-hypothesis and a per-match vector, many times faster than moving every match.
    """
    x = np.concatenate([R.reshape(-1, 9), t, np.einsum("hji,hj->hi", R, t), np.sum(t**2, axis=1, keepdims=True), np.ones((len(R), 1))], axis=1)  # (H, 17)
    y = np.concatenate(
        [
            -2.0 * np.einsum("nj,ni->nji", b, a).reshape(-1, 9),
            -2.0 * b,
            2.0 * a,
            np.ones((len(a), 1)),
            np.sum(a**2, axis=1, keepdims=True) + np.sum(b**2, axis=1, keepdims=True),
        ],
        axis=1,
    )  # (C, 17)
    counts = np.empty(len(R), dtype=np.int64)
    for s in range(0, len(R), 4096):  # bounded memory: 4096 x C distances at a time
        counts[s : s + 4096] = np.count_nonzero(x[s : s + 4096] @ y.T < distance**2, axis=1)
    return counts
