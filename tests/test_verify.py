from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from o3dsoft.clock import StageClock
from o3dsoft.confidence import Features, complete_confidence, partial_confidence, scan_confidence
from o3dsoft.config import RegisterConfig, SearchConfig
from o3dsoft.refine import ICPResult
from o3dsoft.transforms import euler_to_matrix, rigid
from o3dsoft.verify import Attempt, Verifier, choice_features


def _attempt(trust, turn_deg=0.0):
    T = rigid(euler_to_matrix([0.0, 0.0, turn_deg]), np.zeros(3))
    return Attempt(trust, Features(0.0, 0.0, 0.0, 0.0), ICPResult(T, 1.0, 0.0), T, T)


def _pair(config=RegisterConfig(), complete=False, scans=False, scored=False):
    """As much of a PreparedPair as the choice reads: `complete`, two complete-looking clouds;
    `scans`, two scans; `scored`: the choice on partial overlaps (``search.partial_choice``) kept,
    else off, so that the other rules are tested on their own."""
    if not scored:
        config = replace(config, search=replace(config.search, partial_choice=None))
    work = (np.zeros((4, 3)), np.zeros((4, 3)))  # the source's centre at the origin
    return SimpleNamespace(config=config, complete=complete, scans=scans, clouds=lambda level: work, norm=SimpleNamespace(scale=1.0))


def _verifier(own, searched, config=RegisterConfig(), complete=False, scored=False, scans=False):
    verifier = Verifier(_pair(config, complete, scans, scored), StageClock())
    verifier.attempts = list(own)
    verifier.begin_search()
    verifier.attempts += list(searched)
    verifier.begin_search()  # a second search keeps the first mark
    return verifier


def test_a_search_estimate_replaces_the_first_only_when_far_more_trusted():
    first, flip = _attempt(0.3), _attempt(0.6, 180.0)
    # odds 1.5 against 0.43: 3.5 times, below the default 30
    assert _verifier([first], [flip]).most_trusted() is first
    sure = _attempt(0.99, 180.0)  # odds 99: 231 times
    assert _verifier([first], [flip, sure]).most_trusted() is sure
    assert _verifier([_attempt(0.0)], [_attempt(0.01)]).most_trusted().trust == 0.01
    most_trusted_wins = RegisterConfig(search=SearchConfig(replace_odds=1.0))
    assert _verifier([first], [flip], most_trusted_wins).most_trusted() is flip


def test_without_a_search_the_most_trusted_wins_and_the_prior_comes_first():
    low, high = _attempt(0.2), _attempt(0.7)
    verifier = Verifier(_pair(), StageClock())
    verifier.attempts = [low, high]
    assert verifier.most_trusted() is high
    bounded = RegisterConfig(max_rotation=30.0)
    # the first estimate lies beyond the prior: the search's, within it, wins however trusted
    assert _verifier([_attempt(0.0, 90.0)], [_attempt(0.05)], bounded).most_trusted().trust == 0.05


def _touching(trust, contact, turn_deg=0.0):
    """An attempt whose pose brings a share `contact` of the points within the tight distance."""
    T = rigid(euler_to_matrix([0.0, 0.0, turn_deg]), np.zeros(3))
    return Attempt(trust, Features(contact, 0.05, 0.9, contact), ICPResult(T, 1.0, 0.0), T, T)


def test_an_estimate_that_brings_under_half_the_points_into_contact_is_not_chosen():
    whole = _touching(0.05, 0.8)  # the clouds lie on each other
    patch = _touching(0.999, 0.2, 90.0)  # a small patch fits well, the rest is off
    assert _verifier([whole], [patch]).most_trusted() is whole
    # the rule holds for the pipeline's own estimates too, before the odds are compared
    assert _verifier([patch], [whole]).most_trusted() is whole
    assert _verifier([patch, whole], []).most_trusted() is whole
    half = _touching(0.999, 0.4, 90.0)  # exactly half as many: still chosen
    assert _verifier([whole], [half]).most_trusted() is half
    anything = RegisterConfig(search=SearchConfig(min_contact=0.0))
    assert _verifier([whole], [patch], anything).most_trusted() is patch


def _fitting(trust, consistency, overlap, spacing_ratio=1.0, turn_deg=0.0, contact=0.8):
    """An attempt whose points near the other cloud are a share `overlap` of the smaller one, a
    share `consistency` of them close (its strict confidence `trust`; `contact`: fitness_tight)."""
    T = rigid(euler_to_matrix([0.0, 0.0, turn_deg]), np.zeros(3))
    return Attempt(trust, Features(contact, 0.07, consistency, overlap, spacing_ratio), ICPResult(T, 1.0, 0.0), T, T)


def test_on_two_independent_samplings_of_a_complete_shape_the_choice_weighs_the_overlap():
    part = _fitting(0.4, consistency=0.86, overlap=0.55, turn_deg=180.0)  # a part fits closely, the rest has no partner
    whole = _fitting(0.05, consistency=0.87, overlap=0.97)  # every point has a partner, none closer than the spacing
    assert complete_confidence(part.scored) < 0.5 <= complete_confidence(whole.scored)
    assert _verifier([part], [whole], complete=True).most_trusted() is whole
    assert _verifier([whole], [part], complete=True).most_trusted() is whole
    # scans, or a partial overlap: the strict confidence ranks, and the first estimate stays
    assert _verifier([part], [whole], complete=False).most_trusted() is part
    # an attempt shows points the clouds share: the strict confidence judges that pair
    shared = _fitting(0.01, consistency=0.6, overlap=0.9, spacing_ratio=0.3, turn_deg=90.0)
    assert _verifier([part], [whole, shared], complete=True).most_trusted() is part
    # the search's estimate replaces the first only at search.independent_odds
    demanding = RegisterConfig(search=SearchConfig(independent_odds=50.0))  # confidence 0.92 against 0.4: odds 11.9 against 0.67, 18 times
    assert _verifier([part], [whole], demanding, complete=True).most_trusted() is part
    # the strict confidence's choice still replaces the first where it brings nearly as many points into contact
    tight = _fitting(0.95, consistency=0.95, overlap=0.8, turn_deg=90.0)  # odds 19 against 11.9 reported, 361 times strictly
    assert _verifier([whole], [tight], complete=True).most_trusted() is tight
    assert _verifier([whole], [tight._replace(scored=tight.scored._replace(fitness_tight=0.6))], complete=True).most_trusted() is whole
    # ... and only at those odds over the choice, even where no first estimate is in close contact
    wider = _fitting(0.02, consistency=0.5, overlap=0.9, turn_deg=90.0, contact=1.0)
    assert _verifier([whole], [wider], complete=True).most_trusted() is whole
    assert _verifier([whole], [wider._replace(trust=0.95)], complete=True).most_trusted().trust == 0.95


def _posed(trust, turn_deg=0.0, shift=0.0, spacing_ratio=1.0):
    """An attempt turned by `turn_deg` about z and shifted by `shift` along x, whose pose shows no
    shared point (`spacing_ratio` 1) and which its strict confidence `trust` flags."""
    T = rigid(euler_to_matrix([0.0, 0.0, turn_deg]), np.array([shift, 0.0, 0.0]))
    return Attempt(trust, Features(0.6, 0.07, 0.82, 0.75, spacing_ratio), ICPResult(T, 1.0, 0.0), T, T)


def test_agreeing_counts_the_attempts_that_reach_a_pose():
    right = _posed(0.1)
    near = [_posed(0.1, 2.0), _posed(0.1, -4.0), _posed(0.1, shift=0.03)]
    apart = [_posed(0.1, 6.0), _posed(0.1, shift=0.06), _posed(0.1, 180.0)]
    verifier = _verifier([right], near + apart)
    assert verifier.agreeing(right) == 4  # itself and the three within 5 degrees and 0.05 x scale
    assert verifier.agreeing(apart[2]) == 1
    assert verifier.agreeing(_posed(0.1, 0.5)) == 4  # an attempt not kept (refined again): those it meets
    assert verifier.agreeing(_posed(0.1, 90.0)) == 1  # none: at least 1
    loose = replace(RegisterConfig(), confidence=replace(RegisterConfig().confidence, agree_deg=10.0, agree_shift=0.1))
    assert _verifier([right], near + apart, loose).agreeing(right) == 6


def test_on_partial_overlaps_the_reported_confidence_weighs_the_attempts_that_agree():
    many = [_posed(0.1, 0.05 * k) for k in range(60)]
    verifier = _verifier(many[:1], many[1:] + [_posed(0.2, 180.0)])
    assert verifier.reported(many[0]).trust == partial_confidence(many[0].scored, 60) >= 0.5
    assert verifier.reported(verifier.attempts[-1]).trust == 0.2  # alone at its pose: the strict one
    # shared points, complete-looking clouds or scans: not this confidence
    shared = [a._replace(scored=a.scored._replace(spacing_ratio=0.3)) for a in many]
    assert _verifier(shared[:1], shared[1:]).reported(shared[0]).trust == 0.1
    assert _verifier(many[:1], many[1:], complete=True).reported(many[0]).trust == max(0.1, complete_confidence(many[0].scored)) < 0.5
    assert _verifier(many[:1], many[1:], scans=True).reported(many[0]).trust == 0.1


def test_min_contact_is_validated():
    import pytest

    from o3dsoft.errors import InputError

    with pytest.raises(InputError, match="min_contact"):
        RegisterConfig(search=SearchConfig(min_contact=1.5)).validate(20)
    with pytest.raises(InputError, match="independent_odds"):
        RegisterConfig(search=SearchConfig(independent_odds=0.5)).validate(20)
    with pytest.raises(InputError, match="independent_contact"):
        RegisterConfig(search=SearchConfig(independent_contact=1.5)).validate(20)
    with pytest.raises(InputError, match="independent_spacing"):
        RegisterConfig(search=SearchConfig(independent_spacing=-1.0)).validate(20)
    with pytest.raises(InputError, match="undetermined_gain"):
        RegisterConfig(search=SearchConfig(undetermined_gain=0.5)).validate(20)


def test_distrust_lowers_a_promoted_estimate_and_its_screening():
    verifier = Verifier(_pair(), StageClock())
    screened = _attempt(0.8)
    promoted = _attempt(0.9)._replace(start=screened.start)  # as Verifier.promote keeps it
    other = _attempt(0.7, 90.0)
    verifier.screened, verifier.attempts = [screened, other], [promoted]
    verifier.distrust(promoted, 0.1)
    assert [a.trust for a in verifier.attempts] == [0.1]
    assert [s.trust for s in verifier.screened] == [0.1, 0.7]  # the screen's record no longer holds it


def test_with_no_estimate_kept_the_screens_best_is_promoted(monkeypatch):
    verifier = Verifier(_pair(), StageClock())
    low, high = _attempt(0.1), _attempt(0.3, 30.0)
    verifier.screened = [low, high]
    monkeypatch.setattr(verifier, "promote", lambda s: verifier.attempts.append(s) or s)
    assert verifier.most_trusted() is high and verifier.attempts == [high]


def test_on_scans_the_result_reports_the_scan_confidence_where_it_is_larger():
    T = np.eye(4)

    def scan_attempt(trust, planar):
        return Attempt(trust, Features(0.5, 0.05, 0.88, 0.5, 1.0, planar), ICPResult(T, 1.0, 0.0), T, T)

    grazing = scan_attempt(0.2, 0.7)  # flagged strictly, most of the overlap on the other surface
    assert scan_confidence(grazing.scored) > 0.5
    scans = Verifier(_pair(scans=True), StageClock())
    assert scans.reported(grazing).trust == scan_confidence(grazing.scored)
    assert scans.reported(scan_attempt(0.99, 0.7)).trust == 0.99  # the larger of the two
    assert scans.reported(scan_attempt(0.2, float("nan"))).trust == 0.2  # not measured: the strict one
    assert scans.reported(scan_attempt(0.0, 0.9)).trust == 0.0  # beyond the prior stays 0
    assert Verifier(_pair(), StageClock()).reported(grazing).trust == 0.2  # not scans: the strict one


def test_on_partial_overlaps_the_choice_weighs_contact_and_spacing():
    patch = _fitting(0.9, consistency=0.95, overlap=0.45, spacing_ratio=1.3, turn_deg=180.0, contact=0.5)  # a part fits closely
    whole = _fitting(0.05, consistency=0.85, overlap=0.7, spacing_ratio=1.0, contact=0.8)  # more points in contact at the spacing
    assert np.allclose(choice_features(patch, [patch, whole]), [0.95, 0.45, 1.3, 0.625])
    assert np.allclose(choice_features(whole, [patch, whole]), [0.85, 0.7, 1.0, 1.0])
    assert _verifier([patch], [whole], scored=True).most_trusted() is whole
    assert _verifier([whole], [patch], scored=True).most_trusted() is whole
    # off (partial_choice None), on scans, and on complete-looking clouds: the most trusted
    assert _verifier([patch], [whole]).most_trusted() is patch
    assert _verifier([patch], [whole], scored=True, scans=True).most_trusted() is patch
    assert _verifier([patch], [whole], RegisterConfig(search=SearchConfig(independent_spacing=2.0)), complete=True, scored=True).most_trusted() is patch
    # the rotation prior still comes first
    bounded = RegisterConfig(max_rotation=90.0)
    assert _verifier([whole._replace(fine=patch.fine)], [patch._replace(fine=whole.fine)], bounded, scored=True).most_trusted().scored == patch.scored
    # the spacing ratio counts up to 3 (beyond, the clouds lie apart)
    apart = _fitting(0.0, consistency=0.0, overlap=0.0, spacing_ratio=40.0)
    assert choice_features(apart, [apart])[2] == 3.0
