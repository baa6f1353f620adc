import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from o3dsoft import confidence
from o3dsoft.transforms import euler_to_matrix, rigid


def torus(rng: np.random.Generator, n: int) -> np.ndarray:
    """n points drawn uniformly (in parameter space) on a torus of radii 1 and 0.4: (n, 3)."""
    u, v = rng.uniform(0, 2 * np.pi, size=(2, n))
    return np.stack([(1 + 0.4 * np.cos(v)) * np.cos(u), (1 + 0.4 * np.cos(v)) * np.sin(u), 0.4 * np.sin(v)], axis=1)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.sampled_from([300, 600, 1500]))
def test_spacing_ratio_reads_independent_samples_of_one_surface_as_aligned(seed, n):
    rng = np.random.default_rng(seed)
    a, b = torus(rng, n), torus(rng, n)
    d = 0.1 * 1.4
    right = confidence.features(a, b, np.eye(4), d)
    assert 0.6 < right.spacing_ratio < 1.4  # about one spacing apart, whatever the density
    assert confidence.features(a, a, np.eye(4), d).spacing_ratio == 0.0  # the same points
    turned = rigid(euler_to_matrix(np.array([0.0, 25.0, 0.0])), np.zeros(3))
    wrong = confidence.features(a, b, turned, d)
    assert wrong.spacing_ratio > 1.5 * right.spacing_ratio


def test_no_partner_within_reach_reads_as_infinitely_far():
    rng = np.random.default_rng(0)
    a = torus(rng, 400)
    far = confidence.features(a, a + 100.0, np.eye(4), 0.1)
    assert far.spacing_ratio == np.inf and far.consistency == 0.0
    assert confidence.confidence(far) == 0.0
    assert confidence.feature_vector(far)[1] == confidence.RATIO_CAP


def test_the_confidence_is_a_logistic_function_of_the_features():
    f = confidence.Features(fitness_tight=1.0, tight_distance=0.1, consistency=0.95, overlap=1.0, spacing_ratio=1.0)
    z = confidence.COEFFICIENTS[0] + np.dot(confidence.COEFFICIENTS[1:], confidence.feature_vector(f))
    assert confidence.confidence(f) == pytest.approx(1 / (1 + np.exp(-z)))
    assert len(confidence.COEFFICIENTS) == len(confidence.FEATURE_NAMES) + 1
