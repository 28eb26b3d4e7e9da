"""Tests of the sCMOS camera (Huang et al., Nat. Methods 10, 653 (2013)).

Truth comes from routes that share no code with bayespsf.cameras.scmos: a 30-digit mpmath sum
over every photoelectron count that matters, a float logsumexp sum with scipy quadrature (for
the Fisher information), exact moments of the law, and Monte Carlo.
"""

from __future__ import annotations

import itertools

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, special

from bayespsf.cameras import SCMOS, Photon
from bayespsf.cameras._scmos_fisher import fisher_exact

# --------------------------------------------------------------------------------------------
# independent references
# --------------------------------------------------------------------------------------------


def mp_log_p(c, lam, g, o, v):
    """log of sum_n Pois(n; lam) Normal(c; o + g n, v), in ADU, with 30 digits.

    The sum runs over n in [min(lam, y) - W, max(lam, y) + W] with y = (c - o) / g and
    W = 40 sqrt(max(lam, y) + 1) + 40 s + 40: outside it both the Poisson and the Gaussian
    factors are smaller than at the nearer end and fall off faster than exp(-800), far below
    the 30 digits kept.
    """
    with mp.workdps(30):
        c, lam, g, o, v = (mp.mpf(x) for x in (c, lam, g, o, v))
        y = (c - o) / g
        s = mp.sqrt(v) / g
        top = max(lam, y, mp.mpf(0))
        width = 40 * mp.sqrt(top + 1) + 40 * s + 40
        lo = max(0, int(mp.floor(min(lam, y) - width)))
        hi = int(mp.ceil(top + width))
        if lam == 0:
            lo = hi = 0
        log_terms = []
        for n in range(lo, hi + 1):
            log_pois = -lam if n == 0 else n * mp.log(lam) - lam - mp.loggamma(n + 1)
            log_terms.append(log_pois - (c - o - g * n) ** 2 / (2 * v))
        top_term = max(log_terms)
        total = mp.fsum(mp.exp(t - top_term) for t in log_terms)
        return float(top_term + mp.log(total) - mp.log(2 * mp.pi * v) / 2)


def float_log_q(y, lam, s, nmax):
    """log sum_{n <= nmax} Pois(n; lam) phi_s(y - n) by brute-force logsumexp (electrons)."""
    n = np.arange(nmax + 1.0)
    y = np.atleast_1d(np.asarray(y, dtype=float))[:, None]
    terms = special.xlogy(n, lam) - lam - special.gammaln(n + 1) - (y - n) ** 2 / (2 * s * s)
    return special.logsumexp(terms, axis=1) - np.log(s) - 0.5 * np.log(2 * np.pi)


def camera(*, g=2.0, o=100.0, s=1.5, likelihood="exact"):
    """A scalar-map camera with readout sd ``s`` photoelectrons."""
    return SCMOS(g, o, (g * s) ** 2, likelihood=likelihood)


# --------------------------------------------------------------------------------------------
# exact likelihood against mpmath
# --------------------------------------------------------------------------------------------

# (lam, gain, offset, readout sd in e-, y = (counts - offset) / gain)
MP_POINTS = [
    (1e-4, 2.0, 100.0, 1.5, 1.0),  # tiny lam, one electron's worth
    (1e-4, 2.0, 100.0, 0.1, 0.5),  # tiny lam, between lattice points, sharp readout
    (0.0, 1.7, 90.0, 0.8, 3.0),  # no light at all
    (3.7, 0.45, 100.0, 0.3, -50.0),  # far below the offset
    (3.7, 2.3, 100.0, 20.0, -50.0),  # far below, wide readout
    (1e4, 2.0, 100.0, 1.6, 1e4 + 50 * 100 + 50),  # far above (lam + 50 sqrt(lam) + 50)
    (1e4, 2.0, 100.0, 1.6, 1e4 + 37.3),  # lam = 1e4, bulk
    (1e4, 2.0, 100.0, 0.1, 1e4 - 0.5),  # two lattice points tie
    (250.0, 1.1, 400.0, 5.0, 250.0 - 48.0),  # moderate
    (40.0, 3.0, 0.0, 20.0, 40.0 + 50 * np.sqrt(40.0) + 50),  # far above, wide readout
    (0.02, 2.0, 100.0, 0.5, 7.0),  # tiny lam, counts of a rare 7-electron event
]


@pytest.mark.parametrize(("lam", "g", "o", "s", "y"), MP_POINTS)
def test_exact_log_likelihood_matches_mpmath(lam, g, o, s, y):
    cam = SCMOS(g, o, (g * s) ** 2)
    c = o + g * y
    got = float(cam.log_likelihood(c, lam))
    want = mp_log_p(c, lam, g, o, (g * s) ** 2)
    assert abs(got - want) <= 1e-10, (got, want, got - want)


def test_exact_lam_zero_is_the_readout_gaussian():
    g, o, s = 1.3, 50.0, 0.7
    c = np.linspace(o - 20, o + 20, 41)
    want = -0.5 * ((c - o) / (g * s)) ** 2 - np.log(g * s) - 0.5 * np.log(2 * np.pi)
    np.testing.assert_allclose(camera(g=g, o=o, s=s).log_likelihood(c, 0.0), want, atol=1e-12)


# --------------------------------------------------------------------------------------------
# normalisation and moments
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lam", "g", "o", "s"),
    [(0.3, 2.0, 100.0, 0.4), (5.0, 1.5, 100.0, 1.0), (60.0, 0.5, 50.0, 2.5), (2.0, 3.0, 0.0, 0.2)],
)
def test_normalised_with_exact_mean_and_variance(lam, g, o, s):
    """Trapezoid rule over counts (spectrally accurate: the density is analytic and negligible
    at both ends), step well below the readout sd."""
    cam = camera(g=g, o=o, s=s)
    y_lo = -12 * s - 1
    y_hi = lam + 12 * np.sqrt(lam + 1) + 12 + 12 * s
    c = o + g * np.linspace(y_lo, y_hi, int((y_hi - y_lo) / (s * s / 4)) + 1)
    h = c[1] - c[0]
    p = np.exp(cam.log_likelihood(c, lam))
    mass = p.sum() * h
    mean = (c * p).sum() * h
    var = ((c - mean) ** 2 * p).sum() * h
    assert mass == pytest.approx(1.0, rel=1e-8, abs=0)
    assert mean == pytest.approx(o + g * lam, rel=1e-8, abs=0)
    assert var == pytest.approx(g * g * lam + (g * s) ** 2, rel=1e-8, abs=0)


# --------------------------------------------------------------------------------------------
# readout-free pixels: the lattice convention
# --------------------------------------------------------------------------------------------


def test_zero_variance_unit_gain_is_the_photon_camera():
    k = np.arange(0.0, 40.0)
    for lam in (0.0, 0.3, 7.5, 30.0):
        np.testing.assert_allclose(
            SCMOS(1.0, 0.0, 0.0).log_likelihood(k, lam),
            Photon().log_likelihood(k, lam),
            rtol=1e-12,
            atol=1e-12,
        )


def test_zero_variance_lattice_pmf_with_jacobian():
    g, o, lam = 2.7, 100.3, 4.2
    cam = SCMOS(g, o, 0.0)
    n = np.arange(0, 30)
    lattice = cam.log_likelihood(o + g * n, lam)
    want = n * np.log(lam) - lam - special.gammaln(n + 1.0) - np.log(g)
    np.testing.assert_allclose(lattice, want, rtol=1e-13, atol=1e-13)
    # masses (density times the lattice spacing g) sum to 1
    assert np.exp(lattice).sum() * g == pytest.approx(1.0, rel=1e-12)
    # off the lattice, or below the offset: no support
    assert np.all(cam.log_likelihood(o + g * (n + 0.5), lam) == -np.inf)
    assert cam.log_likelihood(o - g, lam) == -np.inf
    # no light: all the mass on n = 0
    assert cam.log_likelihood(o, 0.0) == pytest.approx(-np.log(g))
    assert cam.log_likelihood(o + g, 0.0) == -np.inf
    # huang tier uses the same convention on v == 0 pixels
    np.testing.assert_array_equal(
        SCMOS(g, o, 0.0, likelihood="huang").log_likelihood(o + g * n, lam), lattice
    )


def test_zero_variance_samples_are_on_the_lattice_and_draw_no_normals():
    g, o = 1.9, 99.1
    lam = np.full((4, 5, 5), 3.3)
    cam = SCMOS(g, o, np.zeros((5, 5)))
    counts = cam.sample(lam, 7)
    np.testing.assert_array_equal(counts, o + g * np.random.default_rng(7).poisson(lam))
    rng = np.random.default_rng(8)
    cam.sample(lam, rng)
    reference = np.random.default_rng(8)
    reference.poisson(lam)
    assert rng.bit_generator.state == reference.bit_generator.state  # nothing else drawn
    assert np.all(np.isfinite(cam.log_likelihood(counts, lam)))


def test_mixed_readout_map():
    g = np.array([[1.0, 2.0], [1.5, 2.5]])
    o = np.array([[100.0, 101.0], [99.0, 98.0]])
    v = np.array([[0.0, 4.0], [0.0, 1.0]])
    lam = np.array([[[2.0, 3.0], [4.0, 5.0]]] * 3)
    counts = SCMOS(g, o, v).sample(lam, 11)
    got = SCMOS(g, o, v).log_likelihood(counts, lam)
    for i in range(2):
        for j in range(2):
            want = SCMOS(g[i, j], o[i, j], v[i, j]).log_likelihood(counts[:, i, j], lam[:, i, j])
            np.testing.assert_array_equal(got[:, i, j], want)
    assert np.all(np.isfinite(got))


# --------------------------------------------------------------------------------------------
# Huang et al.'s approximation
# --------------------------------------------------------------------------------------------

# total-variation distance bounds between the "huang" tier and the exact law, measured for
# readout sd 1-3 e- (documented in the module docstring)
HUANG_TV_BOUND = {1.0: 0.08, 10.0: 0.015, 100.0: 1.2e-3, 1000.0: 5e-5}


def test_huang_total_variation_against_exact():
    g, o = 2.0, 100.0
    for s in (1.0, 2.0, 3.0):
        exact, huang = camera(g=g, o=o, s=s), camera(g=g, o=o, s=s, likelihood="huang")
        tvs = []
        for lam, bound in HUANG_TV_BOUND.items():
            y = np.linspace(-12 * s - 2, lam + 12 * np.sqrt(lam + 1) + 12 + 12 * s, 40001)
            c = o + g * y
            p_exact = np.exp(exact.log_likelihood(c, lam))
            p_huang = np.exp(huang.log_likelihood(c, lam))
            tv = 0.5 * np.abs(p_exact - p_huang).sum() * (c[1] - c[0])
            assert tv <= bound, (s, lam, tv)
            tvs.append(tv)
        assert all(b < a for a, b in itertools.pairwise(tvs))  # approaches exact
        # in the bulk (mean -/+ 4 sd) the log densities agree closely at high counts
        lam = 1000.0
        sd = np.sqrt(lam + s * s)
        c = o + g * np.linspace(lam - 4 * sd, lam + 4 * sd, 201)
        diff = huang.log_likelihood(c, lam) - exact.log_likelihood(c, lam)
        assert np.max(np.abs(diff)) < 3e-3


def test_huang_formula_and_support():
    g, o, s, lam = 2.0, 100.0, 1.5, 7.0
    cam = camera(g=g, o=o, s=s, likelihood="huang")
    y = np.array([-s * s, -1.0, 0.0, 3.3, 12.0])
    got = cam.log_likelihood(o + g * y, lam)
    z, mu = y + s * s, lam + s * s
    want = z * np.log(mu) - mu - special.gammaln(z + 1) - np.log(g)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    below = cam.log_likelihood(o + g * np.array([-s * s - 1e-6, -50.0]), lam)
    assert np.all(below == -np.inf)


# --------------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------------


def test_sample_moments_per_pixel():
    rng = np.random.default_rng(2024)
    g = rng.uniform(1.5, 2.5, (3, 3))
    o = rng.uniform(90, 110, (3, 3))
    v = rng.uniform(1, 9, (3, 3))
    lam = rng.uniform(0.1, 50, (3, 3))
    draws = 40000
    counts = SCMOS(g, o, v).sample(np.broadcast_to(lam, (draws, 3, 3)), rng)
    mean, var = g * lam + o, g * g * lam + v
    kappa4 = g**4 * lam  # fourth cumulant: Poisson's scaled, the Gaussian's is 0
    se_mean = np.sqrt(var / draws)
    se_var = np.sqrt((kappa4 + 2 * var**2) / draws)
    assert np.all(np.abs(counts.mean(axis=0) - mean) < 5 * se_mean)
    assert np.all(np.abs(counts.var(axis=0) - var) < 5 * se_var)


# --------------------------------------------------------------------------------------------
# Fisher information
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("lam", "s"), [(0.7, 0.6), (4.0, 0.25), (25.0, 1.5)])
def test_fisher_exact_against_scipy_quadrature(lam, s):
    """integral of (q(y - 1) - q(y))^2 / q(y) dy with a brute-force q and adaptive quadrature."""
    nmax = int(lam + 20 * np.sqrt(lam + 1) + 20)

    def integrand(y):
        log_q0, log_q1 = float_log_q([y, y - 1], lam, s, nmax)
        return np.exp(log_q0) * np.expm1(log_q1 - log_q0) ** 2

    lo, hi = -10 * s - 1, nmax + 1 + 10 * s
    points = np.arange(np.ceil(lo), hi, 0.5)
    total = 0.0
    edges = np.concatenate([[lo], points, [hi]])
    for a, b in itertools.pairwise(edges):
        total += integrate.quad(integrand, a, b, epsabs=0, epsrel=1e-12, limit=200)[0]
    assert fisher_exact(lam, s) == pytest.approx(total, rel=1e-9)


@pytest.mark.parametrize(("lam", "s"), [(0.5, 0.5), (5.0, 1.5), (60.0, 1.0), (3.0, 0.3)])
def test_fisher_exact_against_monte_carlo_score(lam, s):
    g, o = 2.0, 100.0
    cam = camera(g=g, o=o, s=s)
    rng = np.random.default_rng(int(lam * 1000 + s * 10))
    counts = cam.sample(np.full(20000, lam), rng)
    step = 1e-4 * lam
    score = (cam.log_likelihood(counts, lam + step) - cam.log_likelihood(counts, lam - step)) / (
        2 * step
    )
    sq = score**2
    exact = float(cam.fisher_information(lam))
    assert abs(sq.mean() - exact) < 5 * sq.std() / np.sqrt(sq.size), (sq.mean(), exact)
    assert abs(score.mean()) < 5 * score.std() / np.sqrt(score.size)  # score has mean 0


def test_fisher_bounds_limits_and_approx():
    lam = np.array([1e-3, 0.1, 1.0, 3.0, 10.0, 100.0, 1e3, 1e4])
    for s in (0.1, 0.3, 1.0, 1.5, 3.0, 20.0):
        cam = camera(g=1.7, o=10.0, s=s)
        exact = cam.fisher_information(lam)
        approx = cam.fisher_information(lam, method="approx")
        np.testing.assert_allclose(approx, 1 / (lam + s * s), rtol=1e-15)
        # Cramer-Rao for the statistic `counts` below, data processing (n -> counts) above
        assert np.all(exact >= approx * (1 - 1e-9))
        assert np.all(exact <= (1 / lam) * (1 + 1e-9))
        # no light: the chi-square divergence between N(1, s) and N(0, s)
        assert float(cam.fisher_information(0.0)) == pytest.approx(np.expm1(1 / s**2), rel=1e-12)
        if s >= 1:  # continuous at lam -> 0 (reached once lam << exp(-1 / s^2))
            assert float(cam.fisher_information(1e-9)) == pytest.approx(
                np.expm1(1 / s**2), rel=1e-6
            )
    # readout-free: the Poisson information
    cam = SCMOS(2.0, 100.0, 0.0)
    np.testing.assert_allclose(cam.fisher_information(lam), 1 / lam, rtol=1e-15)
    assert cam.fisher_information(0.0) == np.inf
    # high counts, wide readout: the approximation is nearly exact
    cam = camera(s=1.5)
    assert float(cam.fisher_information(1e4)) == pytest.approx(1 / (1e4 + 1.5**2), rel=1e-9)


def test_fisher_quadrature_converged(monkeypatch):
    lam = np.array([0.01, 0.7, 5.0, 40.0, 300.0])
    for s in (0.15, 0.5, 1.2, 4.0):
        base = fisher_exact(lam, s)
        monkeypatch.setattr("bayespsf.cameras._scmos_fisher._FISHER_DROP", 60.0)
        monkeypatch.setattr("bayespsf.cameras._scmos_fisher._FISHER_POISSON_WIDTH", 14.0)
        monkeypatch.setattr("bayespsf.cameras._scmos_fisher._FISHER_READOUT_WIDTH", 14.0)
        fine = fisher_exact(lam, s)
        monkeypatch.undo()
        np.testing.assert_allclose(base, fine, rtol=1e-10)


# --------------------------------------------------------------------------------------------
# per-pixel maps and broadcasting
# --------------------------------------------------------------------------------------------


def test_maps_broadcast_over_walkers_and_roi():
    rng = np.random.default_rng(5)
    roi, walkers = 5, 6
    g = rng.uniform(1.5, 2.5, (roi, roi))
    o = 100.0  # scalar map
    v = rng.uniform(0.5, 6.0, (1, roi))  # one row, broadcast down the columns
    lam = rng.uniform(0.0, 80.0, (walkers, roi, roi))
    counts = SCMOS(g, o, v).sample(lam, rng)
    assert counts.shape == lam.shape
    for likelihood in ("exact", "huang"):
        cam = SCMOS(g, o, v, likelihood=likelihood)
        got = cam.log_likelihood(counts, lam)
        assert got.shape == lam.shape
        # one image of counts against every walker's expected image
        np.testing.assert_array_equal(
            cam.log_likelihood(counts[0], lam),
            cam.log_likelihood(np.broadcast_to(counts[0], lam.shape), lam),
        )
        for i in range(roi):
            for j in range(roi):
                single = SCMOS(g[i, j], o, v[0, j], likelihood=likelihood)
                np.testing.assert_allclose(
                    got[:, i, j], single.log_likelihood(counts[:, i, j], lam[:, i, j]), rtol=1e-14
                )
    cam = SCMOS(g, o, v)
    fisher = cam.fisher_information(lam[:2])
    assert fisher.shape == (2, roi, roi)
    assert fisher[1, 3, 2] == pytest.approx(
        float(SCMOS(g[3, 2], o, v[0, 2]).fisher_information(lam[1, 3, 2])), rel=1e-14
    )
    assert cam.fisher_information(lam, method="approx").shape == lam.shape


def test_to_dict_and_repr():
    g = np.array([[1.0, 2.0], [3.0, 4.0]])
    cam = SCMOS(g, 100.0, np.full((2, 2), 2.0), likelihood="huang")
    d = cam.to_dict()
    assert d == {
        "kind": "scmos",
        "gain_map": [[1.0, 2.0], [3.0, 4.0]],
        "offset_map": 100.0,
        "variance_map": [[2.0, 2.0], [2.0, 2.0]],
        "likelihood": "huang",
    }
    rebuilt = SCMOS(**{k: v for k, v in d.items() if k != "kind"})
    assert rebuilt.to_dict() == d
    assert repr(cam) == (
        "SCMOS(gain_map=<array (2, 2)>, offset_map=100.0, variance_map=<array (2, 2)>, "
        "likelihood='huang')"
    )
    with pytest.raises(ValueError):
        cam.gain_map[0, 0] = 5.0  # maps are read-only


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"gain_map": 0.0}, "gain_map"),
        ({"gain_map": [[1.0, -2.0]]}, "gain_map"),
        ({"gain_map": np.nan}, "gain_map"),
        ({"offset_map": [np.inf, 1.0]}, "offset_map"),
        ({"variance_map": -1.0}, "variance_map"),
        ({"variance_map": 1e-5}, "variance_map"),  # readout sd below 0.01 e-
        ({"variance_map": np.ones((2, 3, 3))}, "variance_map"),
        ({"gain_map": np.ones((3, 3)), "offset_map": np.ones((4, 4))}, "offset_map"),
        ({"gain_map": "two"}, "gain_map"),
        ({"likelihood": "gaussian"}, "likelihood"),
    ],
)
def test_bad_construction_names_the_argument(kwargs, name):
    args = {"gain_map": 2.0, "offset_map": 100.0, "variance_map": 4.0} | kwargs
    with pytest.raises(ValueError, match=name):
        SCMOS(**args)


def test_bad_calls_name_the_argument():
    cam = SCMOS(np.full((4, 4), 2.0), 100.0, 4.0)
    good = np.full((4, 4), 3.0)
    with pytest.raises(ValueError, match="counts"):
        cam.log_likelihood(np.where(np.eye(4) > 0, np.nan, 100.0), good)
    with pytest.raises(ValueError, match="expected"):
        cam.log_likelihood(np.full((4, 4), 100.0), -good)
    with pytest.raises(ValueError, match="expected"):
        cam.sample(-good, 0)
    with pytest.raises(ValueError, match="expected"):
        cam.fisher_information(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="method"):
        cam.fisher_information(good, method="huang")
    for bad in (np.full((5, 5), 3.0), np.full((3, 4, 3), 3.0), 3.0):
        with pytest.raises(ValueError, match="gain_map"):
            cam.log_likelihood(np.full(np.shape(bad), 100.0), bad)
        with pytest.raises(ValueError, match="expected"):
            cam.sample(bad, 0)
        with pytest.raises(ValueError, match="expected"):
            cam.fisher_information(bad)
        with pytest.raises(ValueError, match="expected"):
            cam.fisher_information(bad, method="approx")


# --------------------------------------------------------------------------------------------
# property test
# --------------------------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(
    above=st.floats(-1e4, 1e8),
    lam=st.floats(1e-6, 1e6),
    g=st.floats(0.05, 20.0),
    o=st.floats(-1e3, 1e4),
    s=st.floats(0.01, 100.0),
)
def test_property_finite_and_quiet(above, lam, g, o, s):
    """Counts in [o - 1e4, o + 1e8] ADU, lam in [1e-6, 1e6]: finite exact log p, no warnings
    (the suite turns warnings into errors); the huang tier is -inf only off its support."""
    v = (g * s) ** 2
    c = np.array([o + above, o, o + g * lam])
    exact = SCMOS(g, o, v).log_likelihood(c, lam)
    assert np.all(np.isfinite(exact))
    huang = SCMOS(g, o, v, likelihood="huang").log_likelihood(c, lam)
    support = (c - o) / g + s * s >= 0
    assert np.all(np.isfinite(huang[support]))
    assert np.all(huang[~support] == -np.inf)
    # the exact law is at least as wide as its readout: the density never exceeds the peak
    # of the readout Gaussian
    assert np.all(exact <= -np.log(g * s) - 0.5 * np.log(2 * np.pi) + 1e-9)


@settings(max_examples=40, deadline=None)
@given(lam=st.floats(1e-6, 1e3), s=st.floats(0.01, 50.0))
def test_property_fisher_between_its_bounds(lam, s):
    """1 / (lam + s^2) <= I <= 1 / lam (see test_fisher_bounds_limits_and_approx)."""
    info = float(fisher_exact(lam, s))
    assert np.isfinite(info)
    assert 1 / (lam + s * s) * (1 - 1e-9) <= info <= 1 / lam * (1 + 1e-9)


def test_far_counts_at_tiny_expected_photons_and_lattice_score():
    # Loader's bd0 divided (n - lam) / lam before choosing the branch: an overflow warning at
    # lam = 1e-299 and counts of 1e13 e-; and on readout-free pixels the score by differences
    # stepped onto lam = 0, outside the support of n >= 1 (+inf); it is now n / lam - 1
    cam = SCMOS(124.8, 671.0, (0.06 * 124.8) ** 2)
    assert np.isfinite(cam.log_likelihood(1.24e15, 1.66e-299))
    lattice = SCMOS(2.0, 100.0, 0.0)
    lam = np.array([1e-20, 1e-9, 3.0])
    counts = 100.0 + 2.0 * np.array([3.0, 1.0, 0.0])
    assert np.allclose(lattice.score(counts, lam), [3e20, 1e9 - 1.0, -1.0], rtol=1e-12)
