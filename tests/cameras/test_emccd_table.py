"""The `table` tier: its error against the exact tier over the realistic EMCCD domain, and
exactness wherever it falls back to quadrature."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayespsf.cameras import EMCCD
from bayespsf.cameras import _emccd_table as table

# Realistic EMCCD cameras: EM gain 100-1000, readout 10-100 e- (readout/gain 0.01 to 1).
REALISTIC = [
    dict(gain=1000.0, readout_sd=10.0, offset=100.0, e_per_adu=20.0),
    dict(gain=300.0, readout_sd=30.0, offset=500.0, e_per_adu=12.0),
    dict(gain=100.0, readout_sd=100.0, offset=100.0, e_per_adu=2.0),
]


@pytest.mark.parametrize("params", REALISTIC, ids=lambda p: f"G{p['gain']:g}-s{p['readout_sd']:g}")
def test_table_within_1e4_of_exact_on_counts_from_the_law(params):
    # the documented target of the tier: |log p - exact| <= 1e-4 for lam in [1e-2, 1e4] and
    # counts drawn from the law itself (measured worst ~3e-5: benchmarks/README.md)
    rng = np.random.default_rng(11)
    lam = 10 ** rng.uniform(-2, 4, 20_000)
    exact = EMCCD(**params, likelihood="exact")
    counts = exact.sample(lam, rng)
    fast = EMCCD(**params, likelihood="table")
    err = np.abs(fast.log_likelihood(counts, lam) - exact.log_likelihood(counts, lam))
    assert err.max() <= 1e-4


def test_outside_the_grid_it_is_the_exact_quadrature():
    params = REALISTIC[1]
    exact = EMCCD(**params, likelihood="exact")
    fast = EMCCD(**params, likelihood="table")
    g = params["gain"] / params["e_per_adu"]
    off = params["offset"]
    lam = np.array([1e-5, 1e6, 5.0, 5.0, 5.0])
    counts = np.array([off + 3.0, off + 1e6 * g, off - 60.0, off + 200.0 * g, off + 5.0 * g])
    a, b = fast.log_likelihood(counts, lam), exact.log_likelihood(counts, lam)
    assert np.allclose(a[:4], b[:4], rtol=0, atol=1e-12)  # the four off-grid points
    assert abs(a[4] - b[4]) < 1e-4  # on the grid


def test_zero_signal_no_readout_and_large_readout():
    cam = EMCCD(gain=300.0, readout_sd=30.0, likelihood="table")
    assert np.allclose(
        cam.log_likelihood([-20.0, 0.0, 40.0], 0.0),
        EMCCD(gain=300.0, readout_sd=30.0).log_likelihood([-20.0, 0.0, 40.0], 0.0),
    )
    c = np.array([0.0, 150.0, 900.0])
    no_readout = EMCCD(gain=300.0, likelihood="table").log_likelihood(c, 2.0)
    assert np.array_equal(no_readout, EMCCD(gain=300.0).log_likelihood(c, 2.0))
    # readout/gain above R_MAX: the table is not built, the exact law is used
    big = dict(gain=1.0, readout_sd=table.R_MAX * 2)
    assert np.array_equal(
        EMCCD(**big, likelihood="table").log_likelihood(c, 2.0), EMCCD(**big).log_likelihood(c, 2.0)
    )


@settings(max_examples=100, deadline=None)
@given(counts=st.floats(-1e4, 1e8), lam=st.floats(1e-6, 1e6))
def test_table_finite_everywhere(counts, lam):
    value = EMCCD(**REALISTIC[1], likelihood="table").log_likelihood(counts, lam)
    assert np.isfinite(value)


def test_below_the_grid_the_closed_form_equals_the_quadrature(monkeypatch):
    # lam < 1e-6 (pixels far from a spot without background) went to the exact quadrature, one
    # pixel at a time in memory (0.5 GB for a stack) and hundreds of times slower; the
    # second-order expansion is within 1e-7 in log p of it up to t = 1000 gain units
    from bayespsf.cameras import _emccd_law as law
    from bayespsf.cameras import _emccd_table as table

    for r in (0.005, 0.25, 2.0):
        t = np.array([-5 * r, -r, 0.0, r, 3 * r, 1.0, 5.0, 20.0, 200.0, 1000.0])
        for lam in (1e-9, 1e-7, 9.9e-7):
            lams = np.full_like(t, lam)
            exact = law.log_exact(t, lams, r)
            np.testing.assert_allclose(law.log_small_lam(t, lams, r), exact, rtol=0, atol=1e-7)
    table.table_for(0.25)  # built before the quadrature is forbidden

    def forbidden(*args):
        raise AssertionError("the exact quadrature was called below the grid")

    monkeypatch.setattr(law, "log_exact", forbidden)
    lams = np.array([1e-12, 1e-8, 5e-7])
    assert np.all(np.isfinite(table.log_table(np.array([0.3, 2.0, -0.1]), lams, 0.25)))


def test_below_the_grid_far_counts_use_the_quadrature():
    # the second-order expansion in lam misses the n >= 3 terms, ~(lam t)^2 / 12 relative: at
    # lam = 9e-7 it is off by 47 in log p at t = 1e9, so beyond lam (|t| + r) = 1e-3 the table
    # tier takes the exact law
    t = np.array([1e3, 1e5, 1e6, 1e9])
    lam = np.full_like(t, 9e-7)
    exact = EMCCD(gain=1.0, readout_sd=0.25).log_likelihood(t, lam)
    fast = EMCCD(gain=1.0, readout_sd=0.25, likelihood="table").log_likelihood(t, lam)
    np.testing.assert_allclose(fast, exact, rtol=1e-12, atol=1e-7)


@pytest.mark.parametrize("params", REALISTIC, ids=lambda p: f"G{p['gain']:g}-s{p['readout_sd']:g}")
def test_score_is_the_derivative_of_the_interpolant(params):
    # the tier's score is the patches' exact derivative (one pass with log p): it matches
    # central differences of the tier's own log-likelihood (step 1e-5 lam: truncation and
    # rounding ~1e-9 of the score's scale 1/sqrt(lam)), the near and bulk grids both covered
    cam = EMCCD(**params, likelihood="table")
    rng = np.random.default_rng(5)
    lam = 10 ** rng.uniform(-5, 4.5, 20_000)
    counts = cam.sample(lam, rng)
    h = 1e-5 * lam
    differences = (cam.log_likelihood(counts, lam + h) - cam.log_likelihood(counts, lam - h)) / (
        2 * h
    )
    score = cam.score(counts, lam)
    assert np.all(np.abs(score - differences) * np.sqrt(lam) < 1e-6)
    log_p, both = cam.log_likelihood_and_score_unchecked(counts, lam)
    assert np.array_equal(log_p, cam.log_likelihood(counts, lam))
    assert np.array_equal(both, score)


def test_score_off_the_grids_is_differences_of_the_tier():
    # where the table does not interpolate (lam == 0, below LAM_MIN, off the grid) the score is
    # the base class's differences of the tier's log-likelihood, as before
    from bayespsf.cameras import Camera

    params = REALISTIC[1]
    cam = EMCCD(**params, likelihood="table")
    g = params["gain"] / params["e_per_adu"]
    off = params["offset"]
    lam = np.array([0.0, 1e-7, 5.0, 2e5])
    counts = np.array([off + 3.0, off + 10.0, off + 200.0 * g, off + 2e5 * g])
    assert np.array_equal(cam.score(counts, lam), Camera.score_unchecked(cam, counts, lam))


@pytest.mark.parametrize("params", REALISTIC, ids=lambda p: f"G{p['gain']:g}-s{p['readout_sd']:g}")
def test_curvature_is_the_second_derivative_of_the_interpolant(params):
    # the curvature of the one pass (the observed information's, used where lam >= 1) against
    # central differences of the interpolant's own score, step 1e-6 lam: within a cell both
    # are the patch's second derivative (truncation ~1e-12 relative; rounding: the score's
    # terms, up to 1 / (lam XI_STEP) = 20 / lam, times 1e-16 over the step, ~2e-9 / lam**2);
    # a step straddling a cell boundary sees the jump of a C1 patch's second derivative, so
    # one pixel in ~1e4 may differ there. Near and bulk grids both covered.
    cam = EMCCD(**params, likelihood="table")
    rng = np.random.default_rng(6)
    lam = 10 ** rng.uniform(0, 4.5, 20_000)
    t = cam.gain_units(cam.sample(lam, rng))
    r = cam.readout_in_gain_units
    _, score, curvature = table.log_and_score_table(t, lam, r, curvature=True)
    np.testing.assert_array_equal(np.isnan(curvature), np.isnan(score))
    h = 1e-6 * lam
    up = table.log_and_score_table(t, lam + h, r)[1]
    down = table.log_and_score_table(t, lam - h, r)[1]
    differences = (up - down) / (2 * h)
    scale = np.abs(differences) + np.abs(score) / lam
    off = np.abs(curvature - differences) > 1e-6 * scale
    assert np.isfinite(curvature).mean() > 0.99
    assert off.sum() <= 2, np.c_[t[off], lam[off], curvature[off], differences[off]][:5]


def test_the_observed_information_takes_the_curvature_where_lam_is_at_least_one():
    # EMCCD.score_and_curvature_unchecked: the interpolant's where lam >= 1 (within 1e-6 of the base
    # class's central differences of the score there, whose step 1e-4 lam gives ~1e-8), the
    # base class's secant below (b = 0: the law's tangent curvature at lam -> 0 is unbounded)
    from bayespsf.cameras import Camera

    params = REALISTIC[1]
    cam = EMCCD(**params, likelihood="table")
    rng = np.random.default_rng(7)
    lam = np.concatenate([10 ** rng.uniform(0, 4, 2000), 10 ** rng.uniform(-8, -0.01, 200)])
    counts = cam.sample(lam, rng)
    score, curvature = cam.score_and_curvature_unchecked(counts, lam)
    base_score, base_curvature = Camera.score_and_curvature_unchecked(cam, counts, lam)
    low = lam < 1
    np.testing.assert_array_equal(curvature[low], base_curvature[low])
    np.testing.assert_allclose(score, base_score, rtol=1e-12, atol=1e-12)
    scale = np.abs(base_curvature) + np.abs(score) / lam
    assert np.all(np.abs(curvature - base_curvature)[~low] < 1e-6 * scale[~low])
