"""The ideal photon-counting camera against scipy.stats' Poisson law."""

import numpy as np
import pytest
from scipy import stats

from bayespsf.cameras import Photon


def test_log_likelihood_is_the_poisson_pmf():
    k = np.arange(0, 60)
    for lam in (1e-6, 0.3, 4.0, 45.0):
        assert np.allclose(
            Photon().log_likelihood(k, lam), stats.poisson.logpmf(k, lam), atol=1e-12
        )


def test_zero_expected_photons():
    assert np.array_equal(Photon().log_likelihood([0, 1], 0.0), [0.0, -np.inf])


def test_sample_and_fisher():
    lam = np.full(100_000, 3.5)
    draws = Photon().sample(lam, rng=5)
    assert np.array_equal(draws, Photon().sample(lam, rng=5))
    assert abs(draws.mean() - 3.5) < 5 * np.sqrt(3.5 / draws.size)  # 5 standard errors
    assert np.allclose(Photon().fisher_information([0.5, 2.0]), [2.0, 0.5])


def test_bad_counts_are_named():
    with pytest.raises(ValueError, match="counts"):
        Photon().log_likelihood([-1.0], 1.0)
    with pytest.raises(ValueError, match="counts"):
        Photon().log_likelihood([1.5], 1.0)
    with pytest.raises(ValueError, match="expected"):
        Photon().log_likelihood([1.0], -2.0)
