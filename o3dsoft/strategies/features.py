"""The feature match's estimates: FPFH features matched by a RANSAC that keeps its
best-supported distinct hypotheses (:class:`o3dsoft.search.FeatureMatch`), classical estimates
that do not depend on how the network was trained (partial scans, large rotations)."""

from __future__ import annotations

from typing import Optional

from ..pair import PreparedPair
from ..refine import ICPConfig
from ..verify import Verifier


def matched_icp(pair: PreparedPair) -> ICPConfig:
    """ICP for estimates that carry their matches to within RANSAC's inlier distance: starting
    there rather than at the loosest stage, which pulls some right estimates of partial clouds
    towards the parts with no partner."""
    return pair.config.icp.starting_at(pair.feature_match.inlier_distance / pair.distance)


class FeatureMatchProposals:
    """The feature match's candidates, best-supported first, each tried in turn until one
    reaches the feature stop (``search.features.stop``). In two rounds: most pairs have a
    confident estimate among the first ``first_round``, and the rest cost only the pairs that
    need them. With `limit`, only the first `limit` candidates (at most ``candidates``), in one round."""

    def __init__(self, limit: Optional[int] = None) -> None:
        self.limit = limit

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        settings = pair.config.search.features
        icp = matched_icp(pair)
        before, tried = len(verifier.attempts), 0
        rounds = (
            (min(self.limit, settings.candidates),) if self.limit is not None else sorted({min(settings.first_round, settings.candidates), settings.candidates})
        )
        for count in rounds:
            if tried and verifier.settled():
                break
            found = pair.feature_match.candidates(pair.config.seed, count)[tried:]  # each round extends the last
            tried += len(found)
            verifier.clock.lap("search")
            for T in filter(verifier.plausible, found):
                if len(verifier.attempts) > before and verifier.settled():
                    break
                verifier.try_estimate(T, icp, "feature match")
