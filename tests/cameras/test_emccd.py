"""The EMCCD law: normalisation and moments, independent high-precision truth at every known
trap, property-based stability, tier errors, sampling, Fisher information, bad input."""

import itertools
import json
from pathlib import Path

import emccd_reference as ref
import mpmath as mp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import stats

from bayespsf.cameras import EMCCD
from bayespsf.cameras import _emccd_law as law

GL_X, GL_W = np.polynomial.legendre.leggauss(24)


def panel_nodes(edges):
    """Nodes and weights of a composite 24-point Gauss-Legendre rule over consecutive panels."""
    edges = np.asarray(edges, dtype=float)
    half = 0.5 * np.diff(edges)[:, None]
    mid = 0.5 * (edges[1:] + edges[:-1])[:, None]
    return (mid + half * GL_X).ravel(), (half * GL_W).ravel()


def panel_quadrature(f, edges):
    x, w = panel_nodes(edges)
    return float(np.sum(f(x) * w))


def count_panels(cam, lam):
    """Panels in ADU that resolve both the readout peak at the offset and the amplified part."""
    g, s, k = cam.gain, cam.readout_sd, cam.e_per_adu
    sd = np.sqrt(2 * lam * g * g + s * s)
    top = lam * g + 16 * sd + 60 * g
    bulk = np.linspace(max(0.0, lam * g - 16 * sd), top, 100)
    near = np.linspace(-16 * s, 16 * s, 65) if s > 0 else np.array([0.0])
    small = np.linspace(0.0, min(top, 60 * g), 100)  # the exponential part when lam is small
    return cam.offset + np.unique(np.concatenate([bulk, near, small])) / k


CAMERAS = [
    dict(gain=1.0, readout_sd=0.0),
    dict(gain=1.0, readout_sd=1.0),
    dict(gain=10.0, readout_sd=100.0, offset=100.0, e_per_adu=3.0),
    dict(gain=300.0, readout_sd=30.0, offset=500.0, e_per_adu=12.0),
    dict(gain=1000.0, readout_sd=0.0, offset=0.0, e_per_adu=20.0),
    dict(gain=1000.0, readout_sd=100.0, offset=200.0, e_per_adu=0.5),
]


@pytest.mark.parametrize("params", CAMERAS, ids=lambda p: f"G{p['gain']:g}-s{p['readout_sd']:g}")
@pytest.mark.parametrize("lam", [1e-3, 0.1, 1.0, 10.0, 1e3, 1e4])
def test_exact_law_normalised_with_exact_mean_and_variance(params, lam):
    # Mean lam G and variance 2 lam G^2 + readout^2 (electrons) are exact for the
    # Poisson-Gamma-Normal law; 1e-8 relative is far above the quadrature error (~1e-13) and
    # far below any modelling error a wrong term would cause.
    cam = EMCCD(**params)
    c, w = panel_nodes(count_panels(cam, lam))
    pw = np.exp(cam.log_likelihood(c, lam)) * w
    atom = np.exp(-lam) if cam.readout_sd == 0 else 0.0  # the mass at the offset
    mass = pw.sum() + atom
    mean = (c * pw).sum() + atom * cam.offset
    second = ((c - mean) ** 2 * pw).sum() + atom * (cam.offset - mean) ** 2
    k = cam.e_per_adu
    assert mass == pytest.approx(1.0, rel=1e-8)
    assert mean - cam.offset == pytest.approx(lam * cam.gain / k, rel=1e-8)
    var = (2 * lam * cam.gain**2 + cam.readout_sd**2) / k**2
    assert second == pytest.approx(var, rel=1e-8)


# Each known trap of DESIGN.md, in gain units (t = electrons/G, r = readout/G), against the
# independent mpmath routes of emccd_reference (Poisson-parabolic-cylinder series or
# tanh-sinh quadrature, 25 digits; the quadrature's values are stored in tests/data, made by
# `python tests/cameras/emccd_reference.py`). Tolerance 1e-9 absolute in log p (1e-9 relative in p),
# except where |log p| is so large that double precision of its terms limits us (eps*|log p|).
TRAPS = [
    ("lam 1e4: exp(-lam) underflows, I1 overflows", 1.0e4 + 50.0, 1.0e4, 0.05, "quad"),
    ("lam 1e5 in the upper tail", 1.03e5, 1.0e5, 0.3, "quad"),
    ("counts far below the offset", -50.0, 10.0, 0.5, "series"),
    ("far below with readout comparable to G", -100.0, 1.0, 1.0, "series"),
    ("counts of 1e6 electrons/G at lam 1", 1.0e6, 1.0, 0.1, "quad"),
    ("lam 1e-3", 0.001, 1e-3, 1.0, "series"),
    ("lam 1e-3 in the amplified tail", 3.0, 1e-3, 1.0, "series"),
    ("lam 1e-6, tiny readout", 0.5, 1e-6, 1e-3, "series"),
    ("readout comparable to G = 1", 2.0, 3.0, 1.0, "series"),
    ("narrow readout peak inside the amplified bulk", 7.3, 3.0, 1e-4, "quad"),
    ("narrow peak at zero", 0.0, 2.0, 1e-3, "series"),
    ("large readout, small signal", 5.0, 0.1, 3.0, "series"),
]


QUADRATURE = json.loads((Path(__file__).parents[1] / ref.REFERENCE_FILE).read_text())


@pytest.mark.slow
@pytest.mark.parametrize("name,t,lam,r,route", TRAPS, ids=[t[0] for t in TRAPS])
def test_exact_tier_against_mpmath_at_known_traps(name, t, lam, r, route):
    ours = law.log_exact(np.array([t]), np.array([lam]), r)[0]
    if route == "series":
        truth = float(mp.log(ref.readout_series(t, lam, r)))
    else:  # the quadrature's stored values (26 s to recompute: tests/cameras/emccd_reference.py)
        stored = QUADRATURE["traps"][name]
        assert (stored["t"], stored["lam"], stored["r"]) == (t, lam, r)
        truth = float(stored["log_p"])
    assert np.isfinite(ours)
    assert ours == pytest.approx(truth, abs=1e-9 + 1e-15 * abs(truth) * (1 + abs(t) / r))


@pytest.mark.parametrize(
    "t,lam", [(0.3, 1e-3), (2.0, 0.5), (40.0, 30.0), (1e4 + 30.0, 1e4), (2000.0, 2.0)]
)
def test_high_gain_closed_form_against_poisson_gamma_series(t, lam):
    ours = law.log_high_gain(np.array([t]), np.array([lam]))[0]
    truth = float(mp.log(ref.high_gain_series(t, lam)))
    assert ours == pytest.approx(truth, abs=1e-10 * max(1.0, abs(truth)))


def test_atom_without_readout_is_a_probability_mass_at_the_offset():
    cam = EMCCD(gain=100.0, offset=50.0)
    lam = np.array([0.0, 0.2, 3.0])
    assert np.allclose(cam.log_likelihood(50.0, lam), -lam)
    assert np.all(cam.log_likelihood(49.0, lam) == -np.inf)  # below the offset: no support


def test_zero_expected_photons():
    # lam = 0: no photoelectrons, counts are pure readout (or the atom when readout is 0)
    cam = EMCCD(gain=100.0, readout_sd=10.0, offset=100.0)
    c = np.array([80.0, 100.0, 130.0])
    assert np.allclose(cam.log_likelihood(c, 0.0), stats.norm.logpdf(c, 100.0, 10.0))
    noiseless = EMCCD(gain=100.0)
    assert np.array_equal(noiseless.log_likelihood([0.0, 5.0], 0.0), [0.0, -np.inf])


@settings(max_examples=150, deadline=None)
@example(counts=-5e-324, lam=1.0, gain=2.0, readout=0.0, tier="exact")  # underflows to -0.0
@example(counts=5e-324, lam=1.0, gain=2.0, readout=0.0, tier="high-gain")
@given(
    counts=st.floats(-1e4, 1e8),
    lam=st.floats(1e-6, 1e6),
    gain=st.floats(1.0, 5000.0),
    readout=st.one_of(st.just(0.0), st.floats(1e-3, 300.0)),
    tier=st.sampled_from(["exact", "high-gain", "gaussian"]),
)
def test_log_likelihood_finite_and_warning_free_everywhere(counts, lam, gain, readout, tier):
    # warnings are errors in this suite, so any overflow/underflow/invalid would fail here
    cam = EMCCD(gain=gain, readout_sd=readout, likelihood=tier)
    value = cam.log_likelihood(counts, lam)
    if readout == 0 and counts < 0 and tier != "gaussian":
        assert value == -np.inf  # below the offset without readout: outside the support
    else:
        assert np.isfinite(value)
        assert value < 50.0  # a density in ADU cannot be astronomically large here


@pytest.mark.parametrize("gain,readout", [(1000.0, 1.0), (1000.0, 10.0), (300.0, 3.0)])
def test_high_gain_tier_error_bound(gain, readout):
    # documented domain: counts > 10 readout SDs above the offset; documented bound
    # |d log p| <= 3 (readout/gain)^2 (measured 1.1e-6 at r = 1e-3, 2.3e-4 at r = 1e-2)
    rng = np.random.default_rng(5)
    lam = 10 ** rng.uniform(0, 3, 20_000)
    exact = EMCCD(gain=gain, readout_sd=readout)
    counts = exact.sample(lam, rng)
    far = counts > 10 * readout
    high = EMCCD(gain=gain, readout_sd=readout, likelihood="high-gain")
    err = np.abs(high.log_likelihood(counts, lam) - exact.log_likelihood(counts, lam))[far]
    assert err.max() <= 3 * (readout / gain) ** 2


@pytest.mark.parametrize("lam_min", [1e2, 1e3, 1e4])
def test_gaussian_tier_error_bound(lam_min):
    # documented: within 3 SD of the mean |d log p| <= 10 / sqrt(lam) (the EM law's skewness
    # decays like 1/sqrt(lam)); measured 0.86, 0.17, 0.05 at lam_min = 1e2, 1e3, 1e4
    rng = np.random.default_rng(6)
    lam = 10 ** rng.uniform(np.log10(lam_min), np.log10(lam_min) + 1, 20_000)
    exact = EMCCD(gain=300.0, readout_sd=30.0)
    counts = exact.sample(lam, rng)
    z = np.abs(counts - 300.0 * lam) / np.sqrt(2 * lam * 300.0**2 + 900.0)
    gauss = EMCCD(gain=300.0, readout_sd=30.0, likelihood="gaussian")
    err = np.abs(gauss.log_likelihood(counts, lam) - exact.log_likelihood(counts, lam))
    assert err[z < 3].max() <= 10 / np.sqrt(lam_min)


def test_sampled_counts_follow_the_exact_law():
    # chi-square goodness of fit of 20 000 draws in 25 equiprobable-ish bins, using the exact
    # density integrated per bin; a fixed seed, so the p-value threshold 1e-3 is a real test
    cam = EMCCD(gain=200.0, readout_sd=40.0, offset=100.0, e_per_adu=10.0)
    lam = 2.5
    draws = cam.sample(np.full(20_000, lam), rng=7)
    edges = np.quantile(draws, np.linspace(0, 1, 26))
    edges[0], edges[-1] = draws.min() - 50.0, draws.max() + 50.0
    expected = np.array(
        [
            panel_quadrature(lambda c: np.exp(cam.log_likelihood(c, lam)), np.linspace(lo, hi, 40))
            for lo, hi in itertools.pairwise(edges)
        ]
    )
    observed = np.histogram(draws, edges)[0]
    chi2 = np.sum((observed - 20_000 * expected) ** 2 / (20_000 * expected))
    assert stats.chi2.sf(chi2, df=24) > 1e-3


def test_sample_moments_and_reproducibility():
    cam = EMCCD(gain=100.0, readout_sd=20.0, offset=300.0, e_per_adu=4.0)
    lam = np.full(200_000, 7.0)
    a = cam.sample(lam, rng=1)
    assert np.array_equal(a, cam.sample(lam, rng=np.random.default_rng(1)))
    mean, var = 300.0 + 700.0 / 4.0, (2 * 7.0 * 100.0**2 + 20.0**2) / 16.0
    # 6 standard errors of the sample mean / variance (kurtosis of this law is moderate)
    assert abs(a.mean() - mean) < 6 * np.sqrt(var / a.size)
    assert abs(a.var() - var) < 6 * var * np.sqrt(2.5 / a.size)


class TestFisherInformation:
    def test_bounds_and_limits_without_readout(self):
        cam = EMCCD(gain=300.0)
        lam = np.logspace(-6, 6, 25)
        li = lam * cam.fisher_information(lam)
        assert np.all(np.diff(li) < 0)  # from photon counting (1) to excess noise (1/2)
        assert li[0] == pytest.approx(1.0, abs=1e-5)
        assert li[-1] == pytest.approx(0.5, abs=1e-5)

    def test_table_matches_direct_quadrature_off_grid(self):
        from bayespsf.cameras import _emccd_fisher

        cam = EMCCD(gain=100.0, readout_sd=15.0)
        lam = np.array([3.7e-4, 0.37, 3.7, 37.0, 3.7e3])
        direct = _emccd_fisher.fisher_times_lam(lam, 0.15) / lam
        assert np.allclose(cam.fisher_information(lam), direct, rtol=1e-5)

    @pytest.mark.parametrize("r, bound", [(0.0, 5e-6), (0.25, 1e-6)])
    def test_spline_within_its_stated_error(self, r, bound):
        # the module's stated interpolation error, at the midpoint of every interval of the
        # grid (where a cubic spline is farthest from its knots), against the quadrature
        from bayespsf.cameras import _emccd_fisher

        knots = _emccd_fisher._table(r).x
        lam = 10.0 ** (0.5 * (knots[1:] + knots[:-1]))
        direct = _emccd_fisher.fisher_times_lam(lam, r) / lam
        assert np.max(np.abs(_emccd_fisher.fisher_information(lam, r) / direct - 1)) < bound

    def test_against_monte_carlo_score(self):
        # I = E[score^2] and E[score] = 0, with the score by central differences of the
        # likelihood itself; 4 Monte Carlo standard errors
        cam = EMCCD(gain=50.0, readout_sd=25.0, offset=100.0)
        for lam in (0.3, 4.0):
            c = cam.sample(np.full(4000, lam), rng=3)
            h = 1e-5 * lam
            score = (cam.log_likelihood(c, lam + h) - cam.log_likelihood(c, lam - h)) / (2 * h)
            se = score.std() / np.sqrt(score.size)
            assert abs(score.mean()) < 4 * se
            info = cam.fisher_information(lam)
            se2 = (score**2).std() / np.sqrt(score.size)
            assert abs((score**2).mean() - info) < 4 * se2

    def test_excess_noise_shortcut(self):
        cam = EMCCD(gain=100.0, readout_sd=50.0)
        lam = np.array([0.1, 10.0])
        assert np.allclose(cam.fisher_information(lam, method="excess-noise"), 1 / (2 * lam + 0.25))
        assert cam.fisher_information(0.0)[()] == np.inf


@pytest.mark.parametrize(
    "kwargs,name",
    [
        (dict(gain=0.5), "gain"),
        (dict(gain=100.0, readout_sd=-1.0), "readout_sd"),
        (dict(gain=100.0, e_per_adu=0.0), "e_per_adu"),
        (dict(gain=float("nan")), "gain"),
        (dict(gain=100.0, likelihood="fast"), "likelihood"),
    ],
)
def test_bad_camera_parameters_are_named(kwargs, name):
    with pytest.raises(ValueError, match=name):
        EMCCD(**kwargs)


def test_bad_inputs_are_named():
    cam = EMCCD(gain=100.0, readout_sd=10.0)
    with pytest.raises(ValueError, match="counts"):
        cam.log_likelihood([1.0, np.nan], 1.0)
    with pytest.raises(ValueError, match="expected"):
        cam.log_likelihood(1.0, -0.1)
    with pytest.raises(ValueError, match="expected"):
        cam.log_likelihood(1.0, np.inf)
    with pytest.raises(ValueError, match=r"counts.*expected"):
        cam.log_likelihood(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="method"):
        cam.fisher_information(1.0, method="F2")
    with pytest.raises(ValueError, match="rng"):
        cam.sample(1.0, rng=None)


def test_fisher_table_evaluation_is_the_spline():
    # the compiled evaluation of the Fisher table is the spline of log(lam I) in log10 lam
    # (knots included), inf at lam == 0, quadrature below the grid, the Gaussian limit above
    from bayespsf.cameras import _emccd_fisher

    spline = _emccd_fisher._table(0.25)
    lam = np.concatenate(
        [10 ** np.random.default_rng(2).uniform(-6, 6, 5000), 10.0**spline.x, [1e-6, 1e6]]
    )
    want = np.exp(spline(np.log10(lam))) / lam
    np.testing.assert_allclose(_emccd_fisher.fisher_information(lam, 0.25), want, rtol=1e-14)
    edge = np.array([[0.0, 2e6], [5e-7, 1.0]])
    got = _emccd_fisher.fisher_information(edge, 0.25)
    assert got.shape == (2, 2) and got[0, 0] == np.inf
    below = _emccd_fisher.fisher_times_lam(5e-7, 0.25) / 5e-7
    np.testing.assert_allclose(got[1, 0], below, rtol=1e-14)
    v = 2 * 2e6 + 0.25**2
    assert got[0, 1] == pytest.approx(1 / v + 2 / v**2, rel=1e-14)


@pytest.mark.parametrize("r", [0.0, 0.25, 2.0, 100.0, 1e4])
def test_fisher_information_above_the_grid_is_the_quadrature(r):
    # the Gaussian limit used above lam = 1e6 against the quadrature: its error is O(1/lam)
    # (measured 7.5e-7 at 1e6); 1e-6 relative is the table's own interpolation accuracy
    from bayespsf.cameras import _emccd_fisher

    lam = np.array([1.01e6, 3e6, 1e8])
    direct = _emccd_fisher.fisher_times_lam(lam, r) / lam
    np.testing.assert_allclose(_emccd_fisher.fisher_information(lam, r), direct, rtol=1e-6)
