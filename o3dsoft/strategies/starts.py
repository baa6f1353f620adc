"""The networks from many starting rotations: the main network from the 24 rotations of a cube
(which cover SO(3); where the feature match is off), the search network from 15 around the pose
as given."""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from .. import coarse as coarse_stage
from .. import search as search_stage
from ..errors import InputError
from ..pair import PreparedPair
from ..preprocess import denormalise_transform, sample_points
from ..verify import Verifier


class NetworkStarts:
    """One batch of network passes on smaller samples (``search.starts.points``); the
    best-ranked are polished by ICP on the network's samples, and the one that fits best there is
    verified (:func:`o3dsoft.search.select`).

    Args:
        model: the main network.
        search_model: the search network, else loaded from ``search.starts.weights`` when needed
            (None there: the main network alone).
        cube: the main network from the 24 cube rotations too. Where the feature match has
            searched rotations all over the sphere, they never decided a pair and took half of
            the starts' time; the search network's starts around the pose as given did, through
            the rotations they give the translation votes (docs/incongruent.md).
    """

    def __init__(self, model: coarse_stage.CoarseModel, search_model: Optional[coarse_stage.CoarseModel] = None, cube: bool = True) -> None:
        self.model = model
        self.search_model = search_model
        self.cube = cube

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        config = pair.config
        settings = config.search.starts
        src_small = sample_points(pair.net_normalised[0], settings.points, seed=config.seed + 2)
        tgt_small = sample_points(pair.net_normalised[1], settings.points, seed=config.seed + 3)
        candidates = np.empty((0, 4, 4))
        if self.cube:
            candidates = search_stage.network_candidates(self.model, src_small, tgt_small, search_stage.cube_rotations())
        if settings.weights is not None:
            if self.search_model is None:
                self.search_model = coarse_stage.cached_model(settings.weights, config.device)
            if self.search_model.config.k > settings.points:
                raise InputError(f"search.starts.points={settings.points} is below the search network's neighbourhood size K={self.search_model.config.k}")
            local = search_stage.network_candidates(self.search_model, src_small, tgt_small, search_stage.local_rotations())
            candidates = np.concatenate([candidates, local])
        if len(candidates) == 0:
            return
        plausible = [T for T in (denormalise_transform(T, pair.norm) for T in candidates) if verifier.plausible(T)]
        candidates = np.stack(plausible or [np.eye(4)])  # none within the prior: the pose as given
        icp = replace(config.icp, normal_within=0.0)  # on the network's random samples: normals from the nearest
        chosen = search_stage.select(*pair.net, candidates, pair.distance, settings.refine, icp if config.refine else None, config.confidence)
        verifier.clock.lap("search")
        verifier.add(chosen.polished, chosen.estimate, "network starts")
