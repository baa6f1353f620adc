"""Global search, for pairs with no initial guess: a feature match, and the coarse stage started
from many rotations.

The pipeline first tries FPFH features matched by RANSAC (:class:`FeatureMatch`), which does
not depend on how the network was trained. Then, while no result is confident: the network is
trained on rotations of up to 45 degrees per axis, and far beyond that its estimate is
unreliable (the paper's experiment 10), so the search pre-rotates the source by each of
the 24 rotations of a cube, which cover SO(3) (every rotation lies within 62.8 degrees of one of
them), runs the network on all of them as one batch, ranks the estimates by the share of sampled
source points that land near the target, polishes the best few by ICP on the samples and keeps
the one that fits best, for the pipeline to refine at full resolution.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple, Optional

import numpy as np
import torch

from . import baselines
from . import confidence as confidence_stage
from . import refine as refine_stage
from .coarse import CoarseModel
from .transforms import rigid


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
    axes = [np.array(a, dtype=np.float64) for a in itertools.product((-1.0, 0.0, 1.0), repeat=3)
            if np.count_nonzero(a) in (1, 3)]
    rotations = [np.eye(3)]
    for axis in axes:
        k = axis / np.linalg.norm(axis)
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        a = np.radians(angle_deg)
        rotations.append(np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K)  # Rodrigues
    return np.stack(rotations)


def network_candidates(model: CoarseModel, source: np.ndarray, target: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """The network's estimate from each starting rotation, as one batch.

    Args:
        model: a loaded model.
        source: (N, 3) normalised source points.
        target: (M, 3) normalised target points.
        rotations: (H, 3, 3) starting rotations applied to the source about its centroid c.
    Returns:
        (H, 4, 4) float64 T_target_source in the normalised frame, one per start.
    """
    source = np.asarray(source, dtype=np.float64)
    centre = source.mean(axis=0)
    starts = np.einsum("hij,nj->hni", rotations, source - centre)  # the network expects a centred source
    src = torch.as_tensor(starts, dtype=torch.float32)
    run = model.aligner(torch.as_tensor(np.ascontiguousarray(target), dtype=torch.float32).unsqueeze(0))
    R, t, _ = run(src, model.neighbours(src[:1]))  # rotations keep the neighbourhoods
    R, t = R.double().cpu().numpy(), t.double().cpu().numpy()
    # p -> R (Rh (p - c)) + t
    full = R @ rotations
    return np.stack([rigid(full[h], t[h] - full[h] @ centre) for h in range(len(rotations))])


class Choice(NamedTuple):
    """The search's pick: `estimate` (4, 4), the candidate as the network gave it, and
    `polished` (4, 4), the same after ICP on the samples."""

    estimate: np.ndarray
    polished: np.ndarray


def select(source: np.ndarray, target: np.ndarray, candidates: np.ndarray, distance: float, keep: int,
           icp: Optional[refine_stage.ICPConfig] = refine_stage.ICPConfig()) -> Choice:
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
    """
    fitness = [refine_stage.evaluate(source, target, T, 0.5 * distance).fitness for T in candidates]
    kept = sorted(range(len(candidates)), key=lambda h: -fitness[h])[:keep]
    if icp is None:
        return Choice(candidates[kept[0]], candidates[kept[0]])
    polished = [refine_stage.icp(source, target, candidates[h], distance, icp).transformation for h in kept]
    trust = [confidence_stage.confidence(confidence_stage.features(source, target, T, distance)) for T in polished]
    best = int(np.argmax(trust))
    return Choice(candidates[kept[best]], polished[best])


class FeatureMatch:
    """FPFH features of both clouds, computed once with the settings of
    :class:`o3dsoft.baselines.GlobalConfig` (clouds voxel-downsampled to 0.05 x `scale` first);
    :meth:`estimate` matches them by RANSAC, as many times as asked.

    Args:
        source: (N, 3); target: (M, 3), in their original frames.
        scale: the pair's scale (cloud units).
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, scale: float) -> None:
        self.source = baselines.fpfh_features(source, scale)
        self.target = baselines.fpfh_features(target, scale)
        self.scale = scale

    def estimate(self, seed: int) -> np.ndarray:
        """(4, 4) T_target_source from RANSAC with this seed."""
        return baselines.ransac(self.source, self.target, self.scale, seed)
