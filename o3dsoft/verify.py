"""Verification: every estimate, whoever proposed it, is refined by ICP and scored the same way,
and kept in one list from which the result is chosen (:class:`Verifier`)."""

from __future__ import annotations

import math
from typing import Callable, List, NamedTuple, Optional, Tuple

import numpy as np

from . import confidence as confidence_stage
from . import refine as refine_stage
from .clock import StageClock
from .pair import PreparedPair
from .transforms import near_poses, rotation_angle_deg


class Attempt(NamedTuple):
    """One refined and scored estimate.

    trust: its confidence (0-1, higher is better; 0 beyond the rotation prior).
    scored: the measurements the confidence came from.
    fine: ICP's result (transformation (4, 4) T_target_source, fitness, inlier RMSE).
    coarse: (4, 4) the estimate as proposed.
    start: (4, 4) where ICP first started (the estimate, or its polish on smaller clouds; for an
        estimate promoted from the screen clouds, where the screen's ICP started).
    by: what proposed the estimate ("network", "second network", "feature match", ...).
    """

    trust: float
    scored: confidence_stage.Features
    fine: refine_stage.ICPResult
    coarse: np.ndarray
    start: np.ndarray
    by: str = "estimate"


class Verifier:
    """Refines and scores estimates of one pair, and keeps them: ``attempts``, scored on the work
    clouds, among which the result is chosen; ``screened``, the search's estimates (and on scans the
    network's) as the screen clouds scored them first (on large clouds only the most promising
    are promoted to attempts).

    The stop rule of every strategy reads :meth:`confident` and :meth:`settled`.
    """

    def __init__(self, pair: PreparedPair, clock: StageClock) -> None:
        self.pair = pair
        self.config = pair.config
        self.clock = clock
        self.attempts: List[Attempt] = []
        self.screened: List[Attempt] = []
        self.search_from: Optional[int] = None  # attempts before this index are the pipeline's own

    # -- the prior and the stop rule ------------------------------------------------------------
    def admissible(self, T: np.ndarray, margin: float = 0.0) -> bool:
        """T (4, 4) rotates the source within ``max_rotation`` (+ `margin`) degrees, or no prior."""
        bound = self.config.max_rotation
        return bound is None or rotation_angle_deg(T[:3, :3]) <= bound + margin

    def plausible(self, T: np.ndarray) -> bool:
        """An estimate worth refining under the prior: within it by ``prior_margin_deg``, since
        ICP can still move it into the bound."""
        return self.admissible(T, self.config.search.prior_margin_deg)

    def best_trust(self) -> float:
        return max((a.trust for a in self.attempts), default=0.0)

    def confident(self) -> bool:
        """Some attempt so far is trusted (not flagged likely failed)."""
        return self.best_trust() >= self.config.confidence.likely_failed_below

    def settled(self) -> bool:
        """Some attempt so far is trusted enough to end the feature match (its ``stop``)."""
        return self.best_trust() >= max(self.config.search.features.stop, self.config.confidence.likely_failed_below)

    def begin_search(self) -> None:
        """Mark the attempts so far as the pipeline's own, those from here on as the search's."""
        if self.search_from is None:
            self.search_from = len(self.attempts)

    def most_trusted(self) -> Attempt:
        """The attempt to answer with: among those :meth:`in_contact`, the most trusted, those
        within the rotation prior first (when no estimate was kept, the one the screen trusted
        most is promoted first: refined and scored on the work clouds, and kept). One the search
        proposed replaces the most trusted of the pipeline's own only when its odds of being
        right are ``search.replace_odds`` times higher: on sparse, independently sampled clouds a
        right pose and a turn onto a near-symmetric copy of the shape score alike, and the search
        would trade the first estimate for one no better.

        Where the clouds are two independent samplings of a complete shape (:meth:`independent`),
        the attempts are ranked by the confidence the result reports (:meth:`reported`) instead,
        with ``search.independent_odds``: the strict confidence flags most right poses there, and
        trusts some that fit a part of the shape closely and leave the rest without a partner.
        Failing that, the search's estimate the strict confidence trusts most among those that
        bring nearly as many points into close contact as any (``search.independent_contact``)
        still replaces that choice where its strict odds are ``search.replace_odds`` times
        higher: noisy crops of one point set can pass for independent samplings, and the strict
        confidence knows their right pose.

        Where the clouds neither both look complete nor are scans (:meth:`scores_choice`), the
        attempt in contact with the highest ``search.partial_choice`` score is chosen instead:
        on partial overlaps the strict confidence trusts poses that fit a small part closely."""

        def strict(a: Attempt) -> float:
            return a.trust

        def reported_trust(a: Attempt) -> float:
            return self.reported(a).trust

        if not self.attempts:  # every estimate was screened and none promoted: the screen's best
            assert self.screened, "no estimate was proposed"
            self.promote(max(self.screened, key=lambda a: self._rank(a, strict)))
        search = self.config.search
        if self.scores_choice():
            weights = np.asarray(search.partial_choice)

            def score(a: Attempt) -> float:
                return float(weights @ choice_features(a, self.attempts))

            return max(self.in_contact(self.attempts, search.min_contact), key=lambda a: self._rank(a, score))
        if not self.independent():
            return self._choose(strict, search.replace_odds, search.min_contact)[0]
        chosen, replaced = self._choose(reported_trust, search.independent_odds, search.min_contact)
        if replaced:
            return chosen
        close = max(self.in_contact(self.attempts, search.independent_contact), key=lambda a: self._rank(a, strict))
        own = self.search_from is not None and any(a is close for a in self.attempts[: self.search_from])
        return close if not own and self._replaces(close, chosen, strict, search.replace_odds) else chosen

    def _choose(self, trust: Callable[[Attempt], float], odds: float, min_contact: float) -> Tuple[Attempt, bool]:
        """The most trusted by `trust` of the attempts :meth:`in_contact` at `min_contact`, a
        search's estimate replacing the most trusted of the pipeline's own only at `odds`; and
        whether a search's estimate replaced the pipeline's own."""

        def rank(a: Attempt) -> Tuple[bool, float]:
            return self._rank(a, trust)

        candidates = self.in_contact(self.attempts, min_contact)
        own = self.in_contact(self.attempts[: self.search_from], min_contact) if self.search_from is not None else candidates
        best = max(candidates, key=rank)
        if any(a is best for a in own):
            return best, False
        if not own:
            return best, True
        first = max(own, key=rank)
        return (best, True) if self._replaces(best, first, trust, odds) else (first, False)

    def _rank(self, a: Attempt, trust: Callable[[Attempt], float]) -> Tuple[bool, float]:
        """The key the choice maximises: within the rotation prior first, then `trust`."""
        return (self.admissible(a.fine.transformation), trust(a))

    def _replaces(self, new: Attempt, old: Attempt, trust: Callable[[Attempt], float], odds: float) -> bool:
        """`new` is chosen over `old`: it lies within the rotation prior where `old` does not, or
        both on the same side and its odds by `trust` are `odds` times higher."""
        new_within, old_within = self.admissible(new.fine.transformation), self.admissible(old.fine.transformation)
        if new_within != old_within:
            return new_within
        return _log_odds(trust(new)) - _log_odds(trust(old)) >= math.log(odds)

    def scores_choice(self) -> bool:
        """The choice weighs each estimate's measurements (``search.partial_choice``, by
        :func:`choice_features`) rather than taking the most trusted: set, and the pair is one it
        applies to (:func:`choice_applies`)."""
        return self.config.search.partial_choice is not None and choice_applies(self.pair)

    def shares_no_point(self, attempt: Attempt) -> bool:
        """`attempt`'s pose shows no point the clouds share: its spacing ratio is at least
        ``search.independent_spacing`` (right poses of two independent samplings seldom fall
        under 0.85, those of noisy clouds that share their points reach 0.9)."""
        return attempt.scored.spacing_ratio >= self.config.search.independent_spacing

    def independent(self) -> bool:
        """Both clouds look complete (:attr:`PreparedPair.complete`) and no attempt shows a point
        they share (:meth:`shares_no_point`): two independent samplings of one shape, as far as
        the attempts tell."""
        return self.pair.complete and all(self.shares_no_point(a) for a in self.attempts)

    def reported(self, attempt: Attempt) -> Attempt:
        """`attempt` with the confidence a result reports: the larger of the strict one and, on a
        pair whose clouds both look complete (:attr:`PreparedPair.complete`),
        :func:`~o3dsoft.confidence.complete_confidence`, on scans
        :func:`~o3dsoft.confidence.scan_confidence`; a 0 (beyond the rotation prior, or the
        clouds barely touch) stays 0. The strict one flags about nine in ten right alignments of
        two independent samplings of a shape, whose points are never closer than the samplings'
        spacing, and some right alignments of scans whose overlap's edges curl (docs/scans.md)."""
        if attempt.trust == 0.0:
            return attempt
        if self.pair.complete:
            second = confidence_stage.complete_confidence(attempt.scored, self.config.confidence)
        elif self.pair.scans:
            second = confidence_stage.scan_confidence(attempt.scored, self.config.confidence)
        else:
            second = confidence_stage.partial_confidence(attempt.scored, self.agreeing(attempt), self.config.confidence)
        return attempt._replace(trust=max(attempt.trust, second))

    def agreeing(self, attempt: Attempt) -> int:
        """How many attempts reach `attempt`'s pose (``confidence.agree_deg``, ``agree_shift``),
        itself included where it is kept (at least 1)."""
        if not self.attempts:
            return 1
        return max(int(self._near(np.stack([a.fine.transformation for a in self.attempts]), attempt.fine.transformation).sum()), 1)

    def same_pose(self, T: np.ndarray, T0: np.ndarray) -> bool:
        """The (4, 4) poses agree, as :meth:`agreeing` counts."""
        return bool(self._near(T[None], T0)[0])

    def _near(self, T: np.ndarray, T0: np.ndarray) -> np.ndarray:
        """(K,) which of the (K, 4, 4) poses `T` agree with the (4, 4) `T0`: within
        ``confidence.agree_deg`` of turn and ``agree_shift`` of the scale apart at the source's centre."""
        c = self.config.confidence
        centre = self.pair.clouds("work")[0].mean(axis=0)
        return near_poses(
            T[:, :3, :3], T[:, :3, :3] @ centre + T[:, :3, 3], T0[:3, :3], T0[:3, :3] @ centre + T0[:3, 3], self.pair.norm.scale, c.agree_deg, c.agree_shift
        )

    def in_contact(self, attempts: List[Attempt], min_contact: float) -> List[Attempt]:
        """Those of `attempts` that bring at least `min_contact` (``search.min_contact`` for the
        choice) times as many points within the tight distance (``Features.fitness_tight``) as the
        attempt of the pair that brings most: the others are not chosen. The confidence judges
        how well the part in contact fits, so that partial overlaps are not penalised; a pose
        that slides one shape off the other until a small patch fits scores as high as the right
        one, and among the estimates of one pair the one that explains more of the clouds at that
        quality is the likelier."""
        most = max(a.scored.fitness_tight for a in self.attempts)
        return [a for a in attempts if a.scored.fitness_tight >= min_contact * most]

    # -- refining and scoring ---------------------------------------------------------------------
    def refine(
        self,
        start: np.ndarray,
        coarse: np.ndarray,
        level: str = "work",
        icp: Optional[refine_stage.ICPConfig] = None,
        refine: Optional[bool] = None,
        by: str = "estimate",
    ) -> Attempt:
        """ICP from `start` (4, 4) on the clouds at `level` (with `icp`, default the config's),
        or only scored there when `refine` is False; then the confidence. Not kept. `by`: what
        proposed it."""
        icp = icp or self.config.icp
        refine = self.config.refine if refine is None else refine
        src, tgt = self.pair.clouds(level)
        if refine:
            fine = refine_stage.icp(src, tgt, start, self.pair.distance, icp, self.pair.target_normals(level), self.pair.target_tree(level))
        else:
            fine = refine_stage.evaluate(src, tgt, start, self.pair.distance, self.config.icp.max_points)
        self.clock.lap("refine")
        scored = self.pair.scorer(level)(fine.transformation)
        trust = confidence_stage.confidence(scored, self.config.confidence) if self.admissible(fine.transformation) else 0.0
        self.clock.lap("score")
        return Attempt(trust, scored, fine, coarse, start, by)

    def add(self, start: np.ndarray, coarse: np.ndarray, by: str, icp: Optional[refine_stage.ICPConfig] = None) -> Attempt:
        """Refine and score an estimate (proposed by `by`) on the work clouds, and keep it among
        the attempts."""
        attempt = self.refine(start, coarse, icp=icp, by=by)
        self.attempts.append(attempt)
        return attempt

    def distrust(self, attempt: Attempt, trust: float) -> None:
        """Lower a kept attempt's trust to what the full clouds gave it (no-op for one not kept),
        and that of its screening, if it was promoted from one (the screen's record)."""
        for i, a in enumerate(self.attempts):
            if a is attempt:
                self.attempts[i] = a._replace(trust=min(a.trust, trust))
        for i, s in enumerate(self.screened):
            if s.start is attempt.start:
                self.screened[i] = s._replace(trust=min(s.trust, trust))

    def promote(self, screened: Attempt) -> Attempt:
        """An estimate converged on the screen clouds, refined (tight ICP stages, from where the
        screen left it) and scored on the work clouds, and kept among the attempts."""
        attempt = self.refine(screened.fine.transformation, screened.coarse, icp=self.config.icp.tight(), by=screened.by)._replace(start=screened.start)
        self.attempts.append(attempt)
        return attempt

    def screen_first(self, start: np.ndarray, by: str) -> None:
        """The pipeline's own estimate of a scan pair, screened first: refined and scored on the
        screen clouds, and kept among the attempts (as the pipeline's own) only when the screen
        trusts it. Otherwise the search follows, this screening counts in its record and budget
        like any of its own, and an estimate the search promotes replaces it freely (it is not the
        pipeline's own). A wrong estimate costs ICP on the work clouds most from far away
        (docs/scans.md)."""
        s = self._screen(start, self.config.icp, by)
        if s.trust >= self.config.confidence.likely_failed_below:
            self.promote(s)

    def try_estimate(self, start: np.ndarray, icp: refine_stage.ICPConfig, by: str) -> None:
        """One of the search's estimates: on small clouds refined and kept at once; on large ones
        screened first, and kept only when the screen trusts it more than every estimate before
        it (and at least ``screen.min_trust``), or confidently."""
        if not self.pair.screening:
            self.add(start, start, by, icp)
            return
        budget = self.config.search.screen.budget
        if budget and len(self.screened) >= budget:
            return
        record = max((a.trust for a in self.screened), default=0.0)
        s = self._screen(start, icp, by)
        if (s.trust > record and s.trust >= self.config.search.screen.min_trust) or s.trust >= self.config.confidence.likely_failed_below:
            self.promote(s)

    def _screen(self, start: np.ndarray, icp: refine_stage.ICPConfig, by: str) -> Attempt:
        """An estimate refined on the screen clouds (by the screen's quicker ICP,
        ``screen.max_iterations``), scored there, and kept among the screened."""
        quick = self.config.search.screen.max_iterations
        s = self.refine(start, start, "screen", icp.quick(quick) if quick else icp, by=by)
        self.screened.append(s)
        return s


def choice_applies(pair: PreparedPair) -> bool:
    """The pairs ``search.partial_choice`` weighs: clouds that neither both look complete nor are
    scans (a partial overlap of small clouds)."""
    return not pair.complete and not pair.scans


def choice_features(attempt: Attempt, attempts: List[Attempt]) -> np.ndarray:
    """(4,) what the choice on partial overlaps weighs (``search.partial_choice``): the
    attempt's consistency, overlap, spacing ratio (capped at 3: beyond, the clouds lie apart) and
    fitness_tight over the most of `attempts` (the pair's)."""
    s = attempt.scored
    most = max(a.scored.fitness_tight for a in attempts)
    return np.array([s.consistency, s.overlap, min(s.spacing_ratio, 3.0), s.fitness_tight / max(most, 1e-12)])


def _log_odds(p: float) -> float:
    """log(p / (1 - p)), finite for p in [0, 1]."""
    p = min(max(p, 1e-300), 1.0 - 1e-16)
    return math.log(p) - math.log1p(-p)
