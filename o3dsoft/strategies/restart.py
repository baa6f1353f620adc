"""The optional restart: every distinct start so far again, with only ICP's tight stages. On
partial overlap the loose stage pulls a start a few degrees off towards the parts with no
partner, and a wrong pose can end up fitting better than the drifted right one."""

from __future__ import annotations

from typing import List

import numpy as np

from ..pair import PreparedPair
from ..transforms import first_of_each_pose
from ..verify import Attempt, Verifier


def distinct_starts(attempts: List[Attempt], centre: np.ndarray, scale: float, degrees: float, shift: float) -> List[Attempt]:
    """`attempts` in order, less those whose start (4, 4) lies within `degrees` in rotation of an
    earlier one's and puts the source's `centre` (3,) within `shift` x `scale` of where that one
    does."""
    if not attempts:
        return []
    first = first_of_each_pose(np.stack([a.start for a in attempts]), centre, scale, degrees, shift)
    return [attempts[k] for k in first]


class Restart:
    """Each distinct start, most trusted first, refined by the tight stages on the screen clouds
    (all of a small cloud); only the ``restart.refined`` most trusted there are then refined and
    scored on the work clouds, which bounds the cost on scans."""

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        settings = pair.config.search.restart
        ranked = sorted(verifier.attempts + verifier.screened, key=lambda a: a.trust, reverse=True)
        starts = distinct_starts(ranked, pair.work[0].mean(axis=0), pair.norm.scale, settings.distinct_deg, settings.distinct_shift)
        restarted = [verifier.refine(a.start, a.coarse, "screen", pair.config.icp.tight(), by=a.by) for a in starts if verifier.plausible(a.start)]
        verifier.screened.extend(restarted)
        for s in sorted(restarted, key=lambda s: s.trust, reverse=True)[: settings.refined]:
            if verifier.settled():
                break
            verifier.promote(s)
