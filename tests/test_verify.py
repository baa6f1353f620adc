from types import SimpleNamespace

import numpy as np

from o3dsoft.clock import StageClock
from o3dsoft.confidence import Features
from o3dsoft.config import RegisterConfig, SearchConfig
from o3dsoft.refine import ICPResult
from o3dsoft.transforms import euler_to_matrix, rigid
from o3dsoft.verify import Attempt, Verifier


def _attempt(trust, turn_deg=0.0):
    T = rigid(euler_to_matrix([0.0, 0.0, turn_deg]), np.zeros(3))
    return Attempt(trust, Features(0.0, 0.0, 0.0, 0.0), ICPResult(T, 1.0, 0.0), T, T)


def _verifier(own, searched, config=RegisterConfig()):
    verifier = Verifier(SimpleNamespace(config=config), StageClock())
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
    verifier = Verifier(SimpleNamespace(config=RegisterConfig()), StageClock())
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


def test_min_contact_is_validated():
    import pytest

    from o3dsoft.errors import InputError

    with pytest.raises(InputError, match="min_contact"):
        RegisterConfig(search=SearchConfig(min_contact=1.5)).validate(20)


def test_distrust_lowers_a_promoted_estimate_and_its_screening():
    verifier = Verifier(SimpleNamespace(config=RegisterConfig()), StageClock())
    screened = _attempt(0.8)
    promoted = _attempt(0.9)._replace(start=screened.start)  # as Verifier.promote keeps it
    other = _attempt(0.7, 90.0)
    verifier.screened, verifier.attempts = [screened, other], [promoted]
    verifier.distrust(promoted, 0.1)
    assert [a.trust for a in verifier.attempts] == [0.1]
    assert [s.trust for s in verifier.screened] == [0.1, 0.7]  # the screen's record no longer holds it


def test_with_no_estimate_kept_the_screens_best_is_promoted(monkeypatch):
    verifier = Verifier(SimpleNamespace(config=RegisterConfig()), StageClock())
    low, high = _attempt(0.1), _attempt(0.3, 30.0)
    verifier.screened = [low, high]
    monkeypatch.setattr(verifier, "promote", lambda s: verifier.attempts.append(s) or s)
    assert verifier.most_trusted() is high and verifier.attempts == [high]
