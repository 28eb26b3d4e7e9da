"""The unified interval of the distance from focus on a
curve even about a plane, and the posterior's highest-density region of z."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.special import ndtri

from bayespsf.axial import ZPosterior, bounded_mean_interval, distance_from_focus
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus, HuangCurve, PolynomialCurve

SYMMETRIC = Defocus.symmetric(130.0, 400.0)


@pytest.mark.parametrize("prob", [0.68, 0.95])
@pytest.mark.parametrize("mu", [0.0, 0.2, 0.7, 1.5, 3.0, 8.0])
def test_bounded_mean_interval_covers_at_its_level_at_every_mean(mu, prob):
    # 40 000 Gaussian draws: binomial SE of the coverage 0.0023 (68%), 0.0011 (95%); 4 SE
    rng = np.random.default_rng(int(10 * mu) + int(100 * prob))
    x = mu + rng.standard_normal(40_000)
    lower, upper = bounded_mean_interval(x, prob)
    se = np.sqrt(prob * (1 - prob) / len(x))
    assert abs(np.mean((lower <= mu) & (mu <= upper)) - prob) < 4 * se
    assert np.all(lower >= 0) and np.all(upper > lower)


def test_bounded_mean_interval_turns_from_an_upper_limit_into_the_central_interval():
    for prob in (0.68, 0.9, 0.95):
        c = ndtri((1 + prob) / 2)
        lower, upper = bounded_mean_interval(np.array([-4.0, -1.0, 0.0, 10.0]), prob)
        # at x = 0 the belt's edge x1(mu) = mu - c reaches 0 at mu = c (Feldman & Cousins
        # 1998, Sec. IV.B): the interval is [0, c] exactly
        assert lower[2] == 0.0 and upper[2] == pytest.approx(c, abs=1e-4)
        assert np.all(lower[:3] == 0.0) and 0 < upper[0] < upper[1] < upper[2]
        np.testing.assert_allclose([lower[3], upper[3]], [10 - c, 10 + c], atol=1e-9)
    grid = np.linspace(-5, 6, 500)
    lower, upper = bounded_mean_interval(grid, 0.95)
    assert np.all(np.diff(lower) >= 0) and np.all(np.diff(upper) > 0)


@pytest.mark.parametrize("prob", [0.0, 1.0, 1.5, "0.9"])
def test_bounded_mean_interval_names_a_bad_level(prob):
    with pytest.raises(BayespsfInputError, match="prob"):
        bounded_mean_interval([0.0], prob)


@pytest.mark.parametrize("kind", [HuangCurve, PolynomialCurve])
def test_tau_is_recovered_exactly_from_widths_on_the_curve(kind):
    defocus = Defocus(kind(125.0, 30.0, 350.0), kind(140.0, 30.0, 450.0))
    t = np.array([0.0, 40.0, 150.0, 500.0])
    s_x, s_y = defocus.widths(30.0 + t)
    out = distance_from_focus(defocus, s_x, s_y, np.diag([1e-6, 1e-6]))
    np.testing.assert_allclose(out["tau_hat"], t**2, atol=1e-6)
    assert np.all(out["plane"] == 30.0)
    # far from the edge (tau >> its SD) the unified interval is the central one, tau +- 1.96 SD
    far, c = out.iloc[1:], ndtri(0.975)
    np.testing.assert_allclose(far["lower"], np.sqrt(t[1:] ** 2 - c * far["tau_sd"]), rtol=1e-9)
    np.testing.assert_allclose(far["upper"], np.sqrt(t[1:] ** 2 + c * far["tau_sd"]), rtol=1e-9)
    assert out["upper"].iloc[0] == pytest.approx(np.sqrt(c * out["tau_sd"].iloc[0]), rel=1e-4)


def test_distance_interval_covers_under_gaussian_width_errors_in_focus_and_away():
    # widths drawn from their Gaussian about the curve (the interval's own assumption, first
    # order): coverage at its level within 4 binomial SE (4 000 draws: 0.0074 and 0.0034)
    rng = np.random.default_rng(3)
    cov = np.array([[4.0, 1.0], [1.0, 5.0]])  # nm^2
    for t in (0.0, 30.0, 80.0, 250.0):
        w = np.array(SYMMETRIC.widths(t)).ravel()
        s = rng.multivariate_normal(w, cov, 4000)
        for prob in (0.68, 0.95):
            out = distance_from_focus(SYMMETRIC, s[:, 0], s[:, 1], cov, prob)
            hit = np.mean((out["lower"] <= t) & (t <= out["upper"]))
            assert abs(hit - prob) < 4 * np.sqrt(prob * (1 - prob) / 4000), (t, prob, hit)


def test_distance_interval_takes_one_covariance_per_roi():
    s_x, s_y = np.array([131.0, 140.0]), np.array([129.0, 141.0])
    covs = np.stack([np.diag([4.0, 4.0]), np.diag([9.0, 9.0])])
    both = distance_from_focus(SYMMETRIC, s_x, s_y, covs)
    second = distance_from_focus(SYMMETRIC, s_x[1:], s_y[1:], covs[1])
    pd.testing.assert_frame_equal(both.iloc[1:].reset_index(drop=True), second)


def test_distance_interval_names_what_it_cannot_take():
    with pytest.raises(BayespsfInputError, match="even about a plane"):
        distance_from_focus(Defocus.astigmatic(130.0, 400.0, 400.0), 130.0, 130.0, np.eye(2))
    quartic = Defocus(HuangCurve(130.0, 0.0, 400.0, B=0.1), HuangCurve(130.0, 0.0, 400.0, B=0.1))
    with pytest.raises(BayespsfInputError, match=r"B = 0\.1"):
        distance_from_focus(quartic, 130.0, 130.0, np.eye(2))
    with pytest.raises(BayespsfInputError, match="positive definite"):
        distance_from_focus(SYMMETRIC, 130.0, 130.0, np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(BayespsfInputError, match="finite"):
        distance_from_focus(SYMMETRIC, 130.0, 130.0, np.full((2, 2), np.nan))
    with pytest.raises(BayespsfInputError, match="s_x"):
        distance_from_focus(SYMMETRIC, -1.0, 130.0, np.eye(2))
    with pytest.raises(BayespsfInputError, match=r"covariance must be 2 x 2 or one"):
        distance_from_focus(SYMMETRIC, 130.0, 130.0, np.eye(3))
    with pytest.raises(BayespsfInputError, match=r"\(2, 2, 2\); got \(3, 2, 2\)"):
        distance_from_focus(SYMMETRIC, [130.0, 131.0], [130.0, 131.0], np.stack([np.eye(2)] * 3))


def _posterior(z, plane=None):
    info = {} if plane is None else {"plane": plane}
    return ZPosterior(pd.DataFrame({"z": z}), info)


def test_hdi_gives_both_modes_and_one_interval_across_a_symmetric_focus():
    rng = np.random.default_rng(0)
    bimodal = np.concatenate([rng.normal(-200, 10, 2000), rng.normal(200, 10, 2000)])
    region = _posterior(bimodal).hdi(0.95)
    assert len(region) == 2
    # each mode holds half: its 95% region is about +-1.96 x 10 nm wide (KDE smoothing: 15%)
    np.testing.assert_allclose(region["upper"] - region["lower"], 39.2, rtol=0.15)
    # in focus on a symmetric curve: draws on one side only are mirrored, and the density,
    # greatest at the plane, gives one interval across it that covers an emitter in focus
    one_side = np.abs(rng.normal(0, 30, 3000)) + 50.0
    post = _posterior(one_side, plane=50.0)
    region = post.hdi(0.68)
    assert len(region) == 1
    # symmetric about the plane within the KDE grid's step (range / 512 ~ 0.6 nm)
    assert region["lower"].iloc[0] == pytest.approx(100.0 - region["upper"].iloc[0], abs=1.0)
    assert post.covers(50.0, 0.68) and not post.covers(200.0, 0.68)
    # the shortest interval of the folded draws starts at the smallest draw, above the plane
    assert one_side.min() > 50.0


@pytest.mark.parametrize("prob", [0.0, 1.0, None])
def test_hdi_names_a_bad_level(prob):
    with pytest.raises(BayespsfInputError, match="prob"):
        _posterior(np.arange(10.0)).hdi(prob)
