"""The ADU per photon's standard error from many molecules (bayespsf.calibration.gain)."""

import numpy as np
import pandas as pd
import pytest

from bayespsf.calibration.gain import _combine


def table(m, se):
    n = len(m)
    return pd.DataFrame(
        {
            "molecule": range(n),
            "x": np.zeros(n),
            "y": np.zeros(n),
            "frames": np.full(n, 100),
            "adu_per_photon": m,
            "se": se,
            "fluctuation": np.zeros(n),
            "peak_photons": np.full(n, 100.0),
        }
    )


def test_se_is_never_below_the_molecules_own():
    # molecules that agree far better than their SEs say: the SE is the one their SEs give
    se = np.full(12, 0.5)
    got = _combine(table(16.0 + 0.01 * np.arange(12), se), 2.0)
    assert got.se == pytest.approx(0.5 / np.sqrt(12))


def test_se_follows_the_scatter_where_it_is_larger():
    rng = np.random.default_rng(0)
    m = 16.0 + 1.0 * rng.standard_normal(15)  # scatter 1, stated SEs 0.5: Birge's ratio ~2
    got = _combine(table(m, np.full(15, 0.5)), 2.0)
    assert got.se == pytest.approx(np.std(m, ddof=1) / np.sqrt(15), rel=1e-6)
