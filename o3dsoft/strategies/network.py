"""The network's pass from the pose the clouds are given in: the pipeline's first estimate."""

from __future__ import annotations

from typing import Optional

import numpy as np

from .. import coarse as coarse_stage
from ..pair import PreparedPair
from ..preprocess import denormalise_transform
from ..verify import Verifier


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
