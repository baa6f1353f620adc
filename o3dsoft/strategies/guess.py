"""The caller's initial guess (``register(..., init=T)``), the first estimate tried: the source
arrives moved by it, so the guess is the pose as given."""

from __future__ import annotations

import numpy as np

from ..pair import PreparedPair
from ..verify import Verifier


class InitialGuess:
    """ICP from the pose as given on the work clouds, kept among the attempts as the pipeline's
    own estimate, trusted or not (not screened first, as the network's estimate of a scan pair
    is: a guess the caller gives stays in the choice). ICP's tight stages run first, its whole
    schedule only where they are not trusted: the first, widest stage lets a close guess slide
    where the surfaces hold it loosely (a ground with a few objects). Where one is trusted,
    neither the feature match nor the network runs."""

    name = "initial guess"

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        identity = np.eye(4)
        verifier.add(identity, identity, self.name, icp=pair.config.icp.tight())
        if not verifier.confident():
            verifier.add(identity, identity, self.name)
