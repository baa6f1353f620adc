"""Translation votes, the search's last resort: for shapes whose estimates slide along a flat or
repeated part at about the right rotation, or are aligned the other way round."""

from __future__ import annotations

from typing import List

import numpy as np

from .. import search as search_stage
from ..pair import PreparedPair
from ..transforms import rigid, rotations_within
from ..verify import Verifier
from .features import matched_icp


class TranslationVotes:
    """At the rotations of the most trusted results (``votes.rotations``, distinct by the feature
    match's ``distinct_deg``), the translations most feature matches vote for (one right match
    suffices there, :meth:`o3dsoft.search.FeatureMatch.translations`); and at the most trusted
    rotation turned by 180 degrees about each principal axis of the target and of the moved
    source (:func:`o3dsoft.search.half_turns`), since a shape nearly symmetric under a half turn is
    often aligned the other way round. Tried in turn until one is confident."""

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        settings = pair.config.search.votes
        distinct_deg = pair.config.search.features.match.distinct_deg
        ranked = sorted(verifier.attempts, key=lambda a: (verifier.admissible(a.fine.transformation), a.trust), reverse=True)
        rotations: List[np.ndarray] = []
        for a in ranked:
            if len(rotations) >= settings.rotations:
                break
            R = a.fine.transformation[:3, :3]
            if verifier.admissible(a.fine.transformation) and not (rotations and rotations_within(np.stack(rotations), R, distinct_deg).any()):
                rotations.append(R)
        counts = [settings.translations] * len(rotations)
        if rotations and settings.flipped:
            R0 = rotations[0]
            turns = np.concatenate([search_stage.half_turns(pair.work[1]), search_stage.half_turns(pair.work[0] @ R0.T)])
            flipped = [R for R in (F @ R0 for F in turns) if verifier.plausible(rigid(R, np.zeros(3)))]
            rotations += flipped
            counts += [settings.flipped] * len(flipped)
        voted = [T for R, count in zip(rotations, counts) for T in pair.feature_match.translations(R, count)]
        icp = matched_icp(pair)
        verifier.clock.lap("search")
        for T in voted:
            if verifier.confident():
                break
            verifier.try_estimate(T, icp, "translation votes")
