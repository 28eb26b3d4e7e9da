"""The sCMOS exact tier's score and curvature by lam, against 30-digit mpmath derivatives.

The camera takes both from the moments of the photoelectron count over its sum
(``E[n | y] / lam - 1`` and ``E[n (n - 1) | y] / lam^2 - (E[n | y] / lam)^2``); the truth here
differentiates a brute-force 30-digit sum over every count that matters (``mp.diff``), a route
that shares no code with ``bayespsf.cameras._scmos_law``.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest

from bayespsf.cameras import SCMOS
from bayespsf.cameras._scmos_fisher import fisher_exact
from bayespsf.cameras._scmos_law import log_mixture_and_score


def mp_log_q(y, lam, s):
    """``log sum_n Pois(n; lam) phi_s(y - n)`` in electrons, 30 digits, over ``n`` within
    ``40 sqrt(max(lam, y) + 1) + 40 s + 40`` of ``[min(lam, y), max(lam, y)]``."""
    top = max(lam, y, mp.mpf(0))
    width = 40 * mp.sqrt(top + 1) + 40 * s + 40
    lo = max(0, int(mp.floor(min(lam, y) - width)))
    hi = int(mp.ceil(top + width))
    terms = [
        n * mp.log(lam) - lam - mp.loggamma(n + 1) - (y - n) ** 2 / (2 * s * s)
        for n in range(lo, hi + 1)
    ]
    peak = max(terms)
    return peak + mp.log(mp.fsum(mp.exp(t - peak) for t in terms)) - mp.log(s)


# (lam, readout sd in e-, y = (counts - offset) / gain): bulk, tails, sharp and wide readout,
# a tiny lam whose counts lie far from both the light and the sum's mode
POINTS = [
    (3.7, 1.6, 5.2),
    (3.7, 1.6, -6.0),
    (250.0, 0.3, 251.5),
    (250.0, 5.0, 202.0),
    (1e4, 1.6, 1e4 + 410.0),
    (0.02, 0.5, 7.0),
    (1e-40, 0.3, 25.0),
    (40.0, 20.0, 400.0),
]


@pytest.mark.parametrize(("lam", "s", "y"), POINTS)
def test_score_and_curvature_match_mpmath(lam, s, y):
    g, o = 2.17, 100.0
    cam = SCMOS(g, o, (g * s) ** 2)
    c = np.array([o + g * y])
    expected = np.array([lam])
    score, curvature = cam.score_and_curvature_unchecked(c, expected)
    with mp.workdps(40):  # central differences of step lam / 1e8 (lam stays positive)
        y_mp, s_mp, lam_mp = mp.mpf(y), mp.mpf(s), mp.mpf(lam)
        want_score = mp.diff(lambda v: mp_log_q(y_mp, v, s_mp), lam_mp, h=lam_mp / 10**8)
        want_curve = mp.diff(lambda v: mp_log_q(y_mp, v, s_mp), lam_mp, 2, h=lam_mp / 10**8)
    # the moments carry the sum's relative error (~1e-15) times E[n | y] / lam, the scale
    # of each term of the score; 1e-9 of it is far above that and far below any difference
    # quotient's error
    scale = max(1.0, abs(float(want_score)) + 1.0)
    assert abs(score[0] - float(want_score)) <= 1e-9 * scale, (score[0], want_score)
    assert abs(curvature[0] - float(want_curve)) <= 1e-9 * scale**2, (curvature[0], want_curve)
    log_p, score_again = cam.log_likelihood_and_score_unchecked(c, expected)
    assert score_again[0] == score[0]
    assert log_p[0] == cam.log_likelihood_unchecked(c, expected)[0]


@pytest.mark.parametrize(
    ("lam", "s", "y"),
    [
        (1e-280, 1.0, 20.0),  # light far below a photoelectron: the walk's ratios by recurrence
        (1e-260, 0.3, 30.0),  # ... and where they would overflow, from their logarithms
    ],
)
def test_score_and_curvature_far_below_a_photoelectron(lam, s, y):
    """Where a difference quotient in lam is out of reach even for mpmath's ``diff``, the
    truth is the derivatives' moment form (verified against ``mp.diff`` above) over a 50-digit
    brute-force sum: ``E[n | y] / lam - 1`` and ``E[n (n - 1) | y] / lam^2 - (E[n | y] /
    lam)^2``."""
    cam = SCMOS(1.0, 0.0, s * s)
    score, curvature = cam.score_and_curvature_unchecked(np.array([y]), np.array([lam]))
    with mp.workdps(50):
        y_mp, s_mp, lam_mp = mp.mpf(y), mp.mpf(s), mp.mpf(lam)
        ns = range(int(y + 60 * s + 60))
        logs = [
            n * mp.log(lam_mp) - mp.loggamma(n + 1) - (y_mp - n) ** 2 / (2 * s_mp**2) for n in ns
        ]
        peak = max(logs)
        weights = [mp.exp(v - peak) for v in logs]
        total = mp.fsum(weights)
        mean = mp.fsum(w * n for w, n in zip(weights, ns, strict=True)) / total / lam_mp
        pairs = mp.fsum(w * n * (n - 1) for w, n in zip(weights, ns, strict=True)) / total
        want_score, want_curve = float(mean - 1), float(pairs / lam_mp**2 - mean**2)
    assert score[0] == pytest.approx(want_score, rel=1e-12)
    assert curvature[0] == pytest.approx(want_curve, rel=1e-9)


def test_no_light_takes_the_one_sided_difference():
    """At lam = 0 the law has only a derivative from above: the score is the forward
    difference over 1e-8 photoelectrons and the curvature the secant of the score over 1e-4,
    as ``Camera.score_unchecked`` and ``Camera.score_and_curvature_unchecked`` take them."""
    g, o, s = 2.0, 100.0, 1.2
    cam = SCMOS(g, o, (g * s) ** 2)
    c = o + g * np.array([-2.0, 0.3, 1.0, 4.0])
    zero = np.zeros(c.size)
    score, curvature = cam.score_and_curvature_unchecked(c, zero)
    ll = cam.log_likelihood_unchecked
    forward = (ll(c, zero + 1e-8) - ll(c, zero)) / 1e-8
    # the camera's log p carries -log g, whose rounding (~2e-16 of |log p|) the difference
    # divides by 1e-8: 1e-7 absolute
    np.testing.assert_allclose(score, forward, rtol=0, atol=1e-7)
    above = cam.score_unchecked(c, zero + 1e-4)
    np.testing.assert_allclose(curvature, (above - score) / 1e-4, rtol=1e-12)
    # the derivative from above is phi(y - 1) / phi(y) - 1 in closed form
    y = (c - o) / g
    np.testing.assert_allclose(score, np.expm1((2 * y - 1) / (2 * s * s)), rtol=1e-6)


def test_readout_free_pixels_keep_the_lattice_score():
    """A map with readout-free pixels: those take the Poisson score on their lattice, the
    others the exact tier's, in one call."""
    g = np.array([[2.0, 2.0]])
    cam = SCMOS(g, 100.0, np.array([[0.0, 9.0]]))
    c = np.array([[106.0, 107.3]])
    lam = np.array([[2.5, 2.5]])
    log_p, score = cam.log_likelihood_and_score_unchecked(c, lam)
    assert score[0, 0] == pytest.approx(3.0 / 2.5 - 1.0, rel=1e-14)
    alone = SCMOS(2.0, 100.0, 9.0)
    assert score[0, 1] == alone.score_unchecked(c[:, 1:], lam[:, 1:])[0, 0]
    np.testing.assert_array_equal(log_p, cam.log_likelihood_unchecked(c, lam))


@pytest.mark.parametrize(
    ("lam", "s", "y"), [(3.7, 1.6, 5.2), (250.0, 5.0, 202.0), (0.02, 0.5, -0.2)]
)
def test_huang_score_and_curvature_match_mpmath(lam, s, y):
    """Huang et al.'s tier: ``y + s^2`` as Poisson with mean ``lam + s^2`` (``gammaln``)."""
    g, o = 2.17, 100.0
    cam = SCMOS(g, o, (g * s) ** 2, likelihood="huang")
    c, expected = np.array([o + g * y]), np.array([lam])
    score, curvature = cam.score_and_curvature_unchecked(c, expected)
    with mp.workdps(40):
        k = mp.mpf(y) + mp.mpf(s) ** 2

        def log_p(v):
            return k * mp.log(v + mp.mpf(s) ** 2) - (v + mp.mpf(s) ** 2) - mp.loggamma(k + 1)

        lam_mp = mp.mpf(lam)
        want = [float(mp.diff(log_p, lam_mp, order, h=lam_mp / 10**8)) for order in (1, 2)]
    np.testing.assert_allclose([score[0], curvature[0]], want, rtol=1e-12)
    assert cam.score_unchecked(c, expected)[0] == score[0]
    # outside the tier's support (y + s^2 < 0) there is no derivative
    below = np.array([o - g * (s * s + 1.0)])
    assert np.isnan(cam.score_and_curvature_unchecked(below, expected)).all()


def test_light_below_the_smallest_normal_number_is_finite_and_quiet():
    """lam in the subnormal range (a spot's tail at b = 0): lam^2 underflows to 0 there, which
    divided the curvature's moment by zero, and a one-element call passed a read-only
    broadcast to the compiled loop (a FutureWarning); the score approaches the one-sided
    ``phi(y - 1) / phi(y) - 1`` of lam = 0."""
    s, y = 0.7, np.array([0.3, 2.0, -1.0])
    cam = SCMOS(1.0, 0.0, s * s)
    lam = np.array([1e-310, 1e-320, 1e-300])
    score, curvature = cam.score_and_curvature_unchecked(y, lam)
    assert np.all(np.isfinite(score)) and np.all(np.isfinite(curvature))
    assert score[0] == pytest.approx(np.expm1((2 * y[0] - 1) / (2 * s * s)), rel=1e-9)
    one = cam.log_likelihood_and_score_unchecked(np.array([2.0]), np.array([3.0]))
    assert np.all(np.isfinite(one))


def test_broadcast_no_light_and_inputs_outside_the_domain():
    """lam == 0 broadcast against several counts takes the one-sided difference at each of
    them (a scalar or list lam was not recognised as dark); unchecked input outside the law's
    domain (a count, lam or readout not finite, lam < 0, s <= 0) gets NaN, not a walk from a
    mode of NaN."""
    y = np.array([0.0, 1.0, 2.0])
    scalar = log_mixture_and_score(y, 0.0, 1.0, True)
    full = log_mixture_and_score(y, np.zeros(3), 1.0, True)
    for a, b in zip(scalar, full, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.isfinite(scalar[1]))
    bad = log_mixture_and_score(
        np.array([np.nan, np.inf, 1.0, 1.0, 1.0, 1.0]),
        np.array([1.0, 1.0, np.nan, -1.0, 1.0, 1.0]),
        np.array([1.0, 1.0, 1.0, 1.0, 0.0, np.nan]),
        True,
    )
    assert all(np.isnan(part).all() for part in bad)
    assert np.isnan(fisher_exact(np.array([np.nan, -1.0, 2.0]), np.array([1.0, 1.0, 0.0]))).all()
