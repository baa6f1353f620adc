"""The network's passes from the pose the clouds are given in (the pipeline's first estimate),
and from the other rotations of a cube (the second network's, for clouds turned further than it
was trained on)."""

from __future__ import annotations

from typing import List, Optional

import numpy as np

from .. import coarse as coarse_stage
from .. import refine as refine_stage
from .. import search as search_stage
from ..pair import PreparedPair
from ..preprocess import denormalise_transform
from ..verify import Attempt, Verifier


class NetworkPass:
    """The soft-alignment network on the normalised samples (``coarse_iterations`` passes, each
    from the estimate so far), mapped back to the clouds' frames and verified (on scans, screened
    first: :meth:`~o3dsoft.verify.Verifier.screen_first`).

    After :meth:`propose`: ``estimate`` (the network's output in the normalised frame, with its
    per-point weights) and ``transformation`` ((4, 4) T_target_source in the clouds' frames).
    """

    def __init__(self, model: coarse_stage.CoarseModel, iterations: int = 1, stage: str = "coarse", name: str = "network") -> None:
        self.model = model
        self.iterations = iterations
        self.stage = stage  # the name its time is reported under
        self.name = name  # the name its estimate is reported under
        self.estimate: Optional[coarse_stage.CoarseEstimate] = None
        self.transformation: Optional[np.ndarray] = None

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        self.estimate = coarse_stage.estimate(self.model, *pair.net_normalised, self.iterations)
        verifier.clock.lap(self.stage)
        self.transformation = denormalise_transform(self.estimate.transform, pair.norm)
        if pair.scans and pair.screening:
            verifier.screen_first(self.transformation, self.name)
        else:
            verifier.add(self.transformation, self.transformation, self.name)


class TurnedPasses:
    """The network from the 23 rotations of a cube other than the identity (which, with it, cover
    every rotation to within 63 degrees), for clouds turned further than the network was trained
    on: one pass from each within the rotation prior, as one batch; the `keep` whose pose brings
    the most source points within half the correspondence distance of the target (on the
    network's samples) get the remaining passes, and each still within the prior is verified.
    Its time counts as the second network's, its estimates as "second network, turned".

    After :meth:`propose`: ``attempts``, the attempts it verified (in ranking order).
    """

    def __init__(self, model: coarse_stage.CoarseModel, iterations: int, keep: int) -> None:
        self.model = model
        self.iterations = iterations
        self.keep = keep
        self.attempts: List[Attempt] = []

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        source, target = pair.net_normalised
        first = search_stage.network_candidates(self.model, source, target, search_stage.cube_rotations()[1:])  # (23, 4, 4)
        poses = [denormalise_transform(T, pair.norm) for T in first]
        plausible = [h for h, pose in enumerate(poses) if verifier.plausible(pose)]
        fits = {h: refine_stage.evaluate(*pair.net, poses[h], 0.5 * pair.distance).fitness for h in plausible}
        kept = sorted(plausible, key=lambda h: -fits[h])[: self.keep]
        estimates = first[kept]
        if kept and self.iterations > 1:
            estimates = search_stage.network_candidates(self.model, source, target, estimates[:, :3, :3], self.iterations - 1)
        verifier.clock.lap("second_network")
        for T in estimates:
            pose = denormalise_transform(T, pair.norm)
            if verifier.plausible(pose):
                self.attempts.append(verifier.add(pose, pose, "second network, turned"))
