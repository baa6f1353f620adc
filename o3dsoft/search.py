"""Global search: the coarse stage started from many rotations, for pairs with no initial guess.

The network is trained on rotations of up to 45 degrees per axis, and far beyond that its
estimate is unreliable (the paper's experiment 10). The search pre-rotates the source by each of
the 24 rotations of a cube, which cover SO(3) (every rotation lies within 62.8 degrees of one of
them), runs the network on all of them as one batch, ranks the estimates by the share of sampled
source points that land near the target, and leaves the best few to ICP and the confidence.
"""

from __future__ import annotations

import itertools
from typing import List

import numpy as np
import torch

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
    tgt = torch.as_tensor(np.ascontiguousarray(target), dtype=torch.float32).unsqueeze(0).expand(len(rotations), -1, -1)
    R, t, _ = model.run(src, tgt)
    R, t = R.double().cpu().numpy(), t.double().cpu().numpy()
    # p -> R (Rh (p - c)) + t
    full = R @ rotations
    return np.stack([rigid(full[h], t[h] - full[h] @ centre) for h in range(len(rotations))])


def rank(source: np.ndarray, target: np.ndarray, candidates: np.ndarray, distance: float) -> List[int]:
    """Candidate indices, best first, by the share of source points within `distance` of the target.

    Args:
        source: (N, 3), target: (M, 3): small samples of the clouds (scoring runs once per candidate).
        candidates: (H, 4, 4) T_target_source in the clouds' frame.
        distance: the inlier distance (cloud units).
    """
    fitness = [refine_stage.evaluate(source, target, T, distance).fitness for T in candidates]
    return sorted(range(len(candidates)), key=lambda h: -fitness[h])
