"""KISS-Matcher's estimate, where the optional package is installed (``o3dsoft[peers]``): a
global registration made for scans (robust to low overlap), proposed on clouds registered on a
voxel grid before the FPFH feature match."""

from __future__ import annotations

from .. import baselines
from ..pair import PreparedPair
from ..preprocess import scene_size
from ..verify import Verifier


def kiss_available() -> bool:
    """The optional package ``kiss-matcher`` can be imported."""
    return baselines.installed("kiss_matcher")


class KissMatcherProposal:
    """One estimate, from KISS-Matcher on the full clouds at ``search.kiss_voxel`` of the larger
    scene's size (its radii ``search.kiss_normal_radius`` and ``kiss_feature_radius``), verified
    like the feature match's (refined on the screen, then the work clouds); none where a cloud has
    too few points for it (:data:`o3dsoft.baselines.KISS_MIN_POINTS` on its grid)."""

    def propose(self, pair: PreparedPair, verifier: Verifier) -> None:
        source, target = pair.full
        search = pair.config.search
        voxel = search.kiss_voxel * max(scene_size(source), scene_size(target))
        T = baselines.kiss_matcher(source, target, voxel, search.kiss_normal_radius, search.kiss_feature_radius)
        verifier.clock.lap("search")
        if T is not None and verifier.plausible(T):
            verifier.try_estimate(T, pair.config.icp, "KISS-Matcher")
