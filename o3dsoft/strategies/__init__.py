"""Ways of proposing estimates of T_target_source: each hands its estimates to the
:class:`o3dsoft.verify.Verifier`, which refines, scores and keeps them, and stops as soon as the
verifier's stop rule says so. :func:`o3dsoft.register` runs them in this order (on a partial
overlap the feature match goes first, and the network only when it found nothing confident):

- :class:`InitialGuess` (:mod:`.guess`): the caller's initial guess, where one is given (then the
  feature match and the network run only when it is not trusted);
- :class:`NetworkPass` (:mod:`.network`): the network from the pose the clouds are given in;
- :class:`TurnedPasses` (:mod:`.network`): the second network from the other rotations of a cube;
- :class:`KissMatcherProposal` (:mod:`.kiss`): KISS-Matcher's estimate, on scans, where installed;
- :class:`FeatureMatchProposals` (:mod:`.features`): FPFH + RANSAC's distinct estimates;
- :class:`NetworkStarts` (:mod:`.starts`): the networks from many starting rotations;
- :class:`TranslationVotes` (:mod:`.votes`): translations the feature matches vote for at the best
  rotations and at their half turns;
- :class:`Restart` (:mod:`.restart`): every distinct start again, with ICP's tight stages.
"""

from __future__ import annotations

from typing import Protocol

from ..pair import PreparedPair
from ..verify import Verifier
from .features import FeatureMatchProposals
from .guess import InitialGuess
from .kiss import KissMatcherProposal, kiss_available
from .network import NetworkPass, TurnedPasses
from .restart import Restart
from .starts import NetworkStarts
from .votes import TranslationVotes


class Strategy(Protocol):
    """A way of proposing estimates of one pair."""

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        """Hand estimates to `verifier` (:meth:`~o3dsoft.verify.Verifier.add` or
        :meth:`~o3dsoft.verify.Verifier.try_estimate`) until done or its stop rule holds."""


__all__ = [
    "Strategy",
    "InitialGuess",
    "NetworkPass",
    "TurnedPasses",
    "KissMatcherProposal",
    "kiss_available",
    "FeatureMatchProposals",
    "NetworkStarts",
    "TranslationVotes",
    "Restart",
]
