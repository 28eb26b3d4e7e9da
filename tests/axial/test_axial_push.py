"""z from width draws (bayespsf.axial.push): exact on the curve, both modes of the symmetric
curve, and the delta method's SD where the widths' spread is small."""

import numpy as np
import pytest

from bayespsf.axial import first_order_z_sd, nearest_z, z_draws
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus, HuangCurve

ASTIGMATIC = Defocus.astigmatic(w0=130.0, separation=400.0, depth=400.0, A=0.1, B=0.05)


def test_widths_on_the_curve_give_their_z_back():
    z = np.linspace(-600, 600, 121)
    found, distance = nearest_z(ASTIGMATIC, *ASTIGMATIC.widths(z), covariance=[[4, 1], [1, 2]])
    assert np.allclose(found, z, rtol=0, atol=1e-6) and distance.max() < 1e-6
    _, off = nearest_z(ASTIGMATIC, 400.0, 90.0)  # a pair the curve never makes
    assert off > 50.0


def test_the_symmetric_curve_gives_both_modes():
    # 2 000 draws at z = 300 nm: half of them at -300 (binomial SE 0.011; 4 SE)
    symmetric = Defocus.symmetric(120.0, 400.0)
    s = np.full(2000, symmetric.x.width(300.0))
    z = z_draws(symmetric, s, s, rng=1)
    assert np.allclose(np.abs(z), 300.0, atol=1e-6)
    assert abs(np.mean(z < 0) - 0.5) < 4 * np.sqrt(0.25 / 2000)


@pytest.mark.parametrize("z_true", [-350.0, 0.0, 250.0])
def test_small_width_errors_give_the_delta_methods_sd(z_true):
    # widths ~ N(w(z), S) with S small (1 nm SDs, correlation 0.3): the curve is linear over
    # that spread, so the z draws' SD (in the metric of the draws' covariance) is the delta
    # method's 1 / sqrt(g' S^-1 g). 40 000 draws: the SD's Monte Carlo error is 0.35%;
    # tolerance 3% (the curve's bend over a few nm). Unweighted distances read 4.6% wider here
    rng = np.random.default_rng(2)
    cov = np.array([[1.0, 0.3], [0.3, 1.0]])
    centre = np.array(ASTIGMATIC.widths(z_true))
    draws = rng.multivariate_normal(centre, cov, 40_000)
    z = z_draws(ASTIGMATIC, draws[:, 0], draws[:, 1], rng=3)
    assert np.std(z) == pytest.approx(first_order_z_sd(ASTIGMATIC, z_true, cov), rel=0.03)
    assert np.mean(z) == pytest.approx(z_true, abs=5 * np.std(z) / np.sqrt(40_000) + 0.5)


def test_bad_range_is_named():
    with pytest.raises(BayespsfInputError, match="z_range"):
        nearest_z(ASTIGMATIC, 130.0, 130.0, (100.0, -100.0))
    with pytest.raises(BayespsfInputError, match="positive definite"):
        nearest_z(ASTIGMATIC, 130.0, 130.0, covariance=[[1.0, 2.0], [2.0, 1.0]])


def test_curves_even_about_one_plane_give_both_modes_inside_the_range():
    # x and y of different widths and depths, both in focus at c = 100 nm: z = 100 +- 300 give
    # the same widths, so both are reported (once all draws went to the lower mode by the
    # grid's tie-break); a range that holds only one of them gives that one
    even = Defocus(HuangCurve(120.0, 100.0, 400.0), HuangCurve(140.0, 100.0, 300.0, B=0.1))
    n = 2000
    sx, sy = (np.full(n, w) for w in even.widths(400.0))
    z = z_draws(even, sx, sy, rng=2)
    assert np.allclose(np.abs(z - 100.0), 300.0, atol=1e-6)
    assert abs(np.mean(z < 100.0) - 0.5) < 4 * np.sqrt(0.25 / n)
    assert np.allclose(z_draws(even, sx, sy, rng=2, z_range=(0.0, 800.0)), 400.0, atol=1e-6)


def test_refinement_never_ends_worse_than_its_start():
    # draws far off the curve in a skewed metric: the refined z is the brute-force optimum
    # (a 0.001 nm grid) within 0.01 nm; plain Gauss-Newton once ended up to 1.8 nm away
    rng = np.random.default_rng(4)
    metric_cov = np.linalg.inv([[4.0, -1.0], [-1.0, 1.0]])
    draws = np.array(ASTIGMATIC.widths(150.0)) + rng.normal(0, 60, (300, 2))
    draws = np.abs(draws) + 1.0
    z, _ = nearest_z(ASTIGMATIC, draws[:, 0], draws[:, 1], (-800, 800), metric_cov)
    fine = np.linspace(-800, 800, 1_600_001)
    wx, wy = ASTIGMATIC.widths(fine)
    best = []
    for sx, sy in draws:
        rx, ry = sx - wx, sy - wy
        best.append(fine[np.argmin(4 * rx * rx - 2 * rx * ry + ry * ry)])
    assert np.max(np.abs(z - np.array(best))) < 0.01


def test_bad_widths_and_ranges_are_named():
    with pytest.raises(BayespsfInputError, match="must be > 0"):
        nearest_z(ASTIGMATIC, -130.0, 130.0)
    with pytest.raises(BayespsfInputError, match="does not broadcast"):
        nearest_z(ASTIGMATIC, np.ones(5), np.ones(3))
    with pytest.raises(BayespsfInputError, match="z_range must be two numbers"):
        z_draws(ASTIGMATIC, 130.0, 130.0, rng=1, z_range=5)
