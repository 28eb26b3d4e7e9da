"""Tests of bayespsf.psf against independent truth.

Truth comes from mpmath (30 significant digits, erfc differences that never cancel), from
closed-form identities (sum rule, Sheppard's a**2/12 correction of Eq. tophat), from finite
differences, and from the analytic Eq. A3.1 written out here independently of the module.
"""

from __future__ import annotations

import math
import warnings

import mpmath as mp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal
from scipy import special

from bayespsf import psf
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import (
    PARAMETER_NAMES,
    expected_counts,
    expected_counts_and_jacobian,
    pixel_centres,
    sampled_gaussian,
)

DPS = 30  # working precision of every mpmath reference (digits)


# --------------------------------------------------------------------------------------------
# Independent mpmath reference
# --------------------------------------------------------------------------------------------


def _mp_axis_fractions(centre, width, roi, pixel_size):
    """Mass of N(centre, width**2) in each of the ``roi`` pixels along one axis (mpmath list).

    Pixel k spans [(k - roi/2) a, (k + 1 - roi/2) a]. Each mass is a difference of upper-tail
    probabilities taken on the side of the centre the pixel lies on, so it never cancels.
    """
    c, s, a = mp.mpf(float(centre)), mp.mpf(float(width)), mp.mpf(float(pixel_size))
    half = mp.mpf(roi) / 2
    out = []
    for k in range(roi):
        lo = ((k - half) * a - c) / s
        hi = ((k + 1 - half) * a - c) / s
        r2 = mp.sqrt(2)
        if lo >= 0:  # right of the centre: Q(lo) - Q(hi)
            m = (mp.erfc(lo / r2) - mp.erfc(hi / r2)) / 2
        elif hi <= 0:  # left of the centre: Phi(hi) - Phi(lo) = Q(-hi) - Q(-lo)
            m = (mp.erfc(-hi / r2) - mp.erfc(-lo / r2)) / 2
        else:  # straddles the centre: erf values of opposite sign, no cancellation
            m = (mp.erf(hi / r2) - mp.erf(lo / r2)) / 2
        out.append(m)
    return out


def mp_expected_counts(params, roi, pixel_size):
    """N * Py[i] * Px[j] + b in mpmath, returned as a float64 (roi, roi) array."""
    x0, y0, sx, sy, n, b = (float(v) for v in params)
    with mp.workdps(DPS):
        px = _mp_axis_fractions(x0, sx, roi, pixel_size)
        py = _mp_axis_fractions(y0, sy, roi, pixel_size)
        n, b = mp.mpf(n), mp.mpf(b)
        return np.array([[float(n * py[i] * px[j] + b) for j in range(roi)] for i in range(roi)])


def _params(x0=0.0, y0=0.0, sx=100.0, sy=100.0, n=1000.0, b=0.0):
    return np.array([x0, y0, sx, sy, n, b], dtype=float)


# --------------------------------------------------------------------------------------------
# 1. expected_counts against mpmath
# --------------------------------------------------------------------------------------------

REFERENCE_CASES = [
    # (params, roi, pixel_size)
    pytest.param(_params(0.0, 0.0, 130.0, 130.0, 1000.0, 0.0), 7, 100.0, id="round-centred"),
    pytest.param(_params(12.3, -27.1, 90.0, 160.0, 5000.0, 3.5), 9, 100.0, id="elliptical"),
    pytest.param(_params(140.0, -75.0, 110.0, 95.0, 2.0e4, 0.0), 9, 100.0, id="off-centre"),
    pytest.param(_params(-180.0, 260.0, 70.0, 220.0, 777.0, 12.0), 11, 107.0, id="ellip-off"),
    # a / s = 0.05: pixels much smaller than the spot
    pytest.param(_params(3.7, -6.1, 200.0, 200.0, 1.0e4, 0.0), 41, 10.0, id="a/s=0.05"),
    # a / s = 5: the spot sits inside a single pixel
    pytest.param(_params(37.0, -220.0, 100.0, 100.0, 3000.0, 0.0), 5, 500.0, id="a/s=5"),
    pytest.param(_params(0.0, 0.0, 20.0, 100.0, 1.0, 0.0), 3, 100.0, id="a/sx=5-ellip"),
]


@pytest.mark.parametrize(("params", "roi", "a"), REFERENCE_CASES)
def test_expected_counts_matches_mpmath(params, roi, a):
    got = expected_counts(params, roi, a)
    want = mp_expected_counts(params, roi, a)
    assert got.shape == (roi, roi)
    # rtol 1e-12: every pixel mass is a double-precision special-function value (relative error
    # ~1e-15, times at most z**2 ~ 1e2 from rounding of the standardised edges in these cases);
    # 1e-12 leaves three orders of margin yet would catch any cancellation or formula error.
    assert_allclose(got, want, rtol=1e-12, atol=0)


def test_mpmath_reference_agrees_with_quadrature():
    """The erfc-based reference itself against plain numerical integration of the density."""
    x0, s, a, roi = 23.0, 80.0, 100.0, 5
    with mp.workdps(DPS):
        ref = _mp_axis_fractions(x0, s, roi, a)
        c, sd = mp.mpf(x0), mp.mpf(s)
        for k in range(roi):
            lo = (k - mp.mpf(roi) / 2) * a
            hi = lo + a
            q = mp.quad(lambda x: mp.npdf(x, c, sd), [lo, hi])
            # 1e-25: both are evaluated at 30 digits; quad on a smooth integrand is near exact.
            assert abs(q - ref[k]) <= mp.mpf("1e-25") * abs(ref[k])


# --------------------------------------------------------------------------------------------
# 2. Far tails keep full relative precision
# --------------------------------------------------------------------------------------------

# Geometry: a = 100 nm, roi = 7 -> edges at +-50, +-150, +-250, +-350 nm. With the centre at
# +50 nm and s = 10 nm, the standardised near edges are +10, +20, +30 to the right and -10, -20,
# -30 to the left (and the pixel [-50, 50] ends exactly at the centre).
TAIL_A, TAIL_ROI, TAIL_C, TAIL_S = 100.0, 7, 50.0, 10.0


def _tail_near_edges(centre, width):
    edges = (np.arange(TAIL_ROI + 1) - TAIL_ROI / 2) * TAIL_A
    z = (edges - centre) / width
    lo, hi = z[:-1], z[1:]
    return np.where(lo >= 0, lo, np.where(hi <= 0, -hi, 0.0)), lo >= 0, hi <= 0


def test_tail_geometry_covers_10_and_20_sigma_on_both_sides():
    near, right, left = _tail_near_edges(TAIL_C, TAIL_S)
    assert {10.0, 20.0} <= set(near[right])
    assert {10.0, 20.0} <= set(near[left])


@pytest.mark.parametrize("axis", ["x", "y"])
def test_far_tail_pixels_relative_accuracy(axis):
    # The other axis is a broad centred spot so that N * Py * Px does not underflow.
    if axis == "x":
        params = _params(TAIL_C, 0.0, TAIL_S, 200.0, 1.0, 0.0)
    else:
        params = _params(0.0, TAIL_C, 200.0, TAIL_S, 1.0, 0.0)
    got = expected_counts(params, TAIL_ROI, TAIL_A)
    want = mp_expected_counts(params, TAIL_ROI, TAIL_A)
    # Pixels 10, 20 and 30 sigma away hold 1e-23 ... 1e-198 of the mass relative to their
    # neighbours: a difference of erf values would give 0 (or noise) here. Tolerance 1e-10:
    # erfc keeps ~1e-15 relative precision at any z until it underflows (z ~ 38), and edge
    # rounding adds ~z**2 eps ~ 1e-13; 1e-10 keeps a safe margin.
    assert np.all(want > 0)
    assert np.all(got > 0)
    assert_allclose(got, want, rtol=1e-10, atol=0)
    # The 1-D marginal along the tail axis must show both far sides (not only by symmetry).
    line = got[TAIL_ROI // 2, :] if axis == "x" else got[:, TAIL_ROI // 2]
    want_line = want[TAIL_ROI // 2, :] if axis == "x" else want[:, TAIL_ROI // 2]
    # left-most pixel: z in [-40, -30]; right-most: z in [20, 30] -> really tiny masses
    assert line[0] < 1e-190 and line[-1] < 1e-85
    assert_allclose(line, want_line, rtol=1e-10, atol=0)


def test_naive_erf_difference_fails_in_tail():
    """Sanity check that the tail test discriminates: the naive formula loses everything."""
    z_lo, z_hi = 10.0, 12.0
    naive = 0.5 * (special.erf(z_hi / math.sqrt(2)) - special.erf(z_lo / math.sqrt(2)))
    with mp.workdps(DPS):
        true = float((mp.erfc(z_lo / mp.sqrt(2)) - mp.erfc(z_hi / mp.sqrt(2))) / 2)
    assert abs(naive - true) > 0.5 * true  # naive erf: 0 (or garbage), i.e. 100 % error
    got = expected_counts(_params(-50.0, 0.0, 50.0, 1e4, 1.0, 0.0), 27, 100.0)
    # pixel 23 of roi 27 spans [950, 1050] nm, i.e. [1000, 1100] nm from the centre at -50:
    # z in [20, 22]; pixel 2 spans [-1100, -1000] nm from the centre: z in [-22, -20]
    with mp.workdps(DPS):
        t = (mp.erfc(20 / mp.sqrt(2)) - mp.erfc(22 / mp.sqrt(2))) / 2
        py = _mp_axis_fractions(0.0, 1e4, 27, 100.0)[13]
        want = float(t * py)
    assert_allclose(got[13, 23], want, rtol=1e-10)
    assert_allclose(got[13, 2], want, rtol=1e-10)  # mirror pixel


# --------------------------------------------------------------------------------------------
# 3. Sum rule
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("params", "a"),
    [
        (_params(0.0, 0.0, 100.0, 100.0, 1234.5, 7.25), 100.0),
        (_params(31.0, -44.0, 60.0, 140.0, 9.9e5, 0.0), 80.0),
        (_params(-3.0, 2.0, 25.0, 25.0, 1.0, 1000.0), 10.0),
    ],
)
def test_sum_rule(params, a):
    s_max = max(params[2], params[3])
    # ROI covering at least +-12 s around the spot from any pixel position: the mass lost
    # outside is 2 Q(12) ~ 4e-33, far below double precision.
    half = math.ceil((12 * s_max + max(abs(params[0]), abs(params[1]))) / a) + 1
    roi = 2 * half + 1
    mu = expected_counts(params, roi, a)
    total = params[4] + roi**2 * params[5]
    # 1e-12: summing ~roi**2 (<= 10**4) positive terms accumulates at most ~1e-13 relative.
    assert_allclose(mu.sum(), total, rtol=1e-12)
    # the background is uniform and the spot part is the rest
    assert_allclose((mu - params[5]).sum(), params[4], rtol=1e-12, atol=1e-12 * total)


# --------------------------------------------------------------------------------------------
# 4. Jacobian
# --------------------------------------------------------------------------------------------

JAC_CASES = [
    pytest.param(_params(23.7, -41.2, 110.0, 85.0, 3000.0, 4.0), 9, 100.0, id="elliptical"),
    pytest.param(_params(-160.0, 95.0, 60.0, 60.0, 500.0, 0.0), 11, 100.0, id="off-centre"),
    pytest.param(_params(7.0, -3.0, 200.0, 220.0, 1e4, 1.0), 21, 10.0, id="a/s=0.05"),
    pytest.param(_params(37.0, -120.0, 100.0, 70.0, 800.0, 2.0), 5, 500.0, id="a/s=5"),
]


@pytest.mark.parametrize(("params", "roi", "a"), JAC_CASES)
def test_jacobian_matches_central_differences(params, roi, a):
    mu, jac = expected_counts_and_jacobian(params, roi, a)
    assert mu.shape == (roi, roi)
    assert jac.shape == (6, roi, roi)
    for k, name in enumerate(PARAMETER_NAMES):
        up, dn = params.copy(), params.copy()
        if k < 4:
            # Central difference, step 1e-4 of the width: truncation ~ (h / s)**2 ~ 1e-8
            # relative; rounding ~ eps * mu / h stays < 1e-9 of the largest derivative.
            h = 1e-4 * params[2 + k % 2]
            up[k] += h
            dn[k] -= h
            step = 2 * h
        else:
            # mu is linear in N and b: a forward difference with a unit step (b = 0 must not
            # step below 0) is exact up to rounding ~ eps * mu.
            up[k] += 1.0
            step = 1.0
        fd = (expected_counts(up, roi, a) - expected_counts(dn, roi, a)) / step
        # rtol 1e-6 per pixel, plus an absolute floor of 1e-7 of this parameter's largest
        # derivative for pixels where the derivative crosses zero (e.g. the spot's centre).
        floor = 1e-7 * np.max(np.abs(jac[k]))
        assert_allclose(jac[k], fd, rtol=1e-6, atol=floor, err_msg=f"d mu / d {name}")


@pytest.mark.parametrize(("params", "roi", "a"), JAC_CASES)
def test_jacobian_trivial_columns(params, roi, a):
    _, jac = expected_counts_and_jacobian(params, roi, a)
    # d mu / d b = 1 exactly; d mu / d N = Py Px = (expected_counts(N=1, b=0)).
    assert_array_equal(jac[5], np.ones((roi, roi)))
    unit = params.copy()
    unit[4], unit[5] = 1.0, 0.0
    assert_allclose(jac[4], expected_counts(unit, roi, a), rtol=1e-15, atol=0)


@pytest.mark.parametrize(("params", "roi", "a"), JAC_CASES)
def test_jacobian_mu_equals_expected_counts_to_rounding(params, roi, a):
    mu, _ = expected_counts_and_jacobian(params, roi, a)
    # Same arithmetic up to the association of N * Py * Px: at most an ulp or two apart.
    assert_allclose(mu, expected_counts(params, roi, a), rtol=5e-16, atol=0)


def test_jacobian_mu_equals_expected_counts_exactly():
    rng = np.random.default_rng(0)
    m = 200
    p = np.column_stack(
        [
            rng.uniform(-300, 300, m),
            rng.uniform(-300, 300, m),
            rng.uniform(30, 300, m),
            rng.uniform(30, 300, m),
            rng.uniform(0, 1e5, m),
            rng.uniform(0, 100, m),
        ]
    )
    mu, _ = expected_counts_and_jacobian(p, 9, 100.0)
    assert_array_equal(mu, expected_counts(p, 9, 100.0))


def test_jacobian_matches_mpmath_diff():
    params = _params(23.7, -41.2, 110.0, 85.0, 3000.0, 4.0)
    roi, a = 5, 100.0
    _, jac = expected_counts_and_jacobian(params, roi, a)
    x0, y0, sx, sy, n, _b = params
    with mp.workdps(DPS):
        py = _mp_axis_fractions(y0, sy, roi, a)

        def px_j(j, centre, width):
            # a fresh evaluation at arbitrary precision for mp.diff (no float rounding)
            c, s, half = mp.mpf(centre), mp.mpf(width), mp.mpf(roi) / 2
            lo = ((j - half) * a - c) / (s * mp.sqrt(2))
            hi = ((j + 1 - half) * a - c) / (s * mp.sqrt(2))
            return (mp.erf(hi) - mp.erf(lo)) / 2  # no tail cancellation within +-3 s here

        d_x0 = [mp.diff(lambda c, j=j: px_j(j, c, sx), mp.mpf(x0)) for j in range(roi)]
        d_sx = [mp.diff(lambda s, j=j: px_j(j, x0, s), mp.mpf(sx)) for j in range(roi)]
        want_x0 = np.array([[float(n * py[i] * d_x0[j]) for j in range(roi)] for i in range(roi)])
        want_sx = np.array([[float(n * py[i] * d_sx[j]) for j in range(roi)] for i in range(roi)])
    # rtol 1e-9: the analytic derivative is a difference of two Gaussian densities (mild
    # cancellation, <1e-13 here); mp.diff is exact to ~20 digits. The absolute floor (1e-12 of
    # the largest entry) only matters for entries that happen to lie near a sign change.
    for k, want in ((0, want_x0), (2, want_sx)):
        assert_allclose(jac[k], want, rtol=1e-9, atol=1e-12 * np.max(np.abs(want)))
        assert np.all(np.abs(want) > 1e-6 * np.max(np.abs(want)))  # no entry is ~0 by accident


# --------------------------------------------------------------------------------------------
# 5. Broadcasting
# --------------------------------------------------------------------------------------------


def _batch(shape, seed=1):
    rng = np.random.default_rng(seed)
    p = np.empty((*shape, 6))
    p[..., 0] = rng.uniform(-250, 250, shape)
    p[..., 1] = rng.uniform(-250, 250, shape)
    p[..., 2] = rng.uniform(40, 300, shape)
    p[..., 3] = rng.uniform(40, 300, shape)
    p[..., 4] = rng.uniform(0, 1e4, shape)
    p[..., 5] = rng.uniform(0, 50, shape)
    return p


@pytest.mark.parametrize("func", [expected_counts, sampled_gaussian])
def test_broadcasting_batch_equals_single(func):
    p, roi, a = _batch((3, 4)), 7, 100.0
    out = func(p, roi, a)
    assert out.shape == (3, 4, roi, roi)
    for idx in np.ndindex(3, 4):
        # Same element-wise arithmetic; allow a couple of ulp in case SIMD and scalar loops of
        # exp/erf differ on some platform (they are identical here).
        assert_allclose(out[idx], func(p[idx], roi, a), rtol=4e-16, atol=0)


def test_broadcasting_jacobian_batch_equals_single():
    p, roi, a = _batch((3, 4)), 7, 100.0
    mu, jac = expected_counts_and_jacobian(p, roi, a)
    assert mu.shape == (3, 4, roi, roi)
    assert jac.shape == (3, 4, 6, roi, roi)
    for idx in np.ndindex(3, 4):
        mu1, jac1 = expected_counts_and_jacobian(p[idx], roi, a)
        assert_allclose(mu[idx], mu1, rtol=4e-16, atol=0)
        assert_allclose(jac[idx], jac1, rtol=4e-16, atol=1e-300)


def test_broadcasting_accepts_lists_and_empty_batches():
    p = _params(10.0, -10.0, 90.0, 120.0, 100.0, 1.0)
    assert_array_equal(expected_counts(p.tolist(), 5, 100.0), expected_counts(p, 5, 100.0))
    assert expected_counts(np.empty((0, 6)), 5, 100.0).shape == (0, 5, 5)


# --------------------------------------------------------------------------------------------
# 6. Orientation
# --------------------------------------------------------------------------------------------


def _centroid(img):
    rows, cols = np.indices(img.shape)
    w = img / img.sum()
    return (w * rows).sum(), (w * cols).sum()


def test_orientation_x0_moves_columns_y0_moves_rows():
    roi, a = 9, 100.0
    base = expected_counts(_params(0, 0, 100, 100, 1000, 0), roi, a)
    r0, c0 = _centroid(base)
    assert_allclose([r0, c0], [roi // 2, roi // 2], atol=1e-12)

    shifted_x = expected_counts(_params(200, 0, 100, 100, 1000, 0), roi, a)
    r, c = _centroid(shifted_x)
    assert c > c0 + 1.5 and abs(r - r0) < 1e-12
    assert np.unravel_index(np.argmax(shifted_x), shifted_x.shape) == (roi // 2, roi // 2 + 2)

    shifted_y = expected_counts(_params(0, 200, 100, 100, 1000, 0), roi, a)
    r, c = _centroid(shifted_y)
    assert r > r0 + 1.5 and abs(c - c0) < 1e-12
    assert np.unravel_index(np.argmax(shifted_y), shifted_y.shape) == (roi // 2 + 2, roi // 2)

    # negative x0 moves mass to lower column indices
    neg = expected_counts(_params(-100, 0, 100, 100, 1000, 0), roi, a)
    assert np.argmax(neg[roi // 2]) == roi // 2 - 1


def test_orientation_sx_widens_columns():
    roi, a = 15, 100.0
    img = expected_counts(_params(0, 0, 250, 80, 1000, 0), roi, a)
    col_profile = img.sum(axis=0)  # marginal over rows: profile along x (columns)
    row_profile = img.sum(axis=1)
    idx = np.arange(roi) - roi // 2
    var_x = (col_profile * idx**2).sum() / col_profile.sum()
    var_y = (row_profile * idx**2).sum() / row_profile.sum()
    assert var_x > 4 * var_y
    # and the transposed parameters give the transposed image
    img_t = expected_counts(_params(0, 0, 80, 250, 1000, 0), roi, a)
    assert_allclose(img_t, img.T, rtol=1e-15)


def test_symmetry_mirror_images():
    roi, a = 9, 100.0
    img = expected_counts(_params(37, -58, 90, 130, 1000, 2), roi, a)
    mirrored = expected_counts(_params(-37, 58, 90, 130, 1000, 2), roi, a)
    # mirroring x0 and y0 through the centre mirrors the image exactly (edges are symmetric)
    assert_allclose(mirrored, img[::-1, ::-1], rtol=1e-14)


# --------------------------------------------------------------------------------------------
# 7. Eq. tophat: per-axis variance s**2 + a**2 / 12
# --------------------------------------------------------------------------------------------


def _x_marginal_moments(x0_values, s, a, roi):
    p = np.zeros((len(x0_values), 6))
    p[:, 0] = x0_values
    p[:, 2] = s
    p[:, 3] = s
    p[:, 4] = 1.0
    mu = expected_counts(p, roi, a)
    px = mu.sum(axis=-2)  # mass per column
    c = pixel_centres(roi, a)
    mean = (px * c).sum(axis=-1)
    var_about_mean = (px * (c - mean[:, None]) ** 2).sum(axis=-1)
    second_about_x0 = (px * (c - np.asarray(x0_values)[:, None]) ** 2).sum(axis=-1)
    return mean, var_about_mean, second_about_x0


def _roi_for(s, a):
    return 2 * math.ceil((12 * s + a) / a) + 1  # +-12 s beyond any x0 within the centre pixel


def _uniform_in_pixel(a, m=200):
    return a * ((np.arange(m) + 0.5) / m - 0.5)  # midpoints of m equal cells of one pixel


def test_tophat_second_moment_averaged_over_pixel_phase():
    """With x0 uniform over a pixel, the quantisation error e = c_J - X is U(-a/2, a/2) and
    independent of X - x0 ~ N(0, s**2), so E[(c_J - x0)**2] = s**2 + a**2/12 exactly, for any
    a / s. The average over x0 is of a smooth periodic function, so the 200-point midpoint
    rule is exact to rounding. a / s = 2 is chosen where the fixed-x0 version is visibly off."""
    s, a = 50.0, 100.0
    _, _, m2 = _x_marginal_moments(_uniform_in_pixel(a), s, a, _roi_for(s, a))
    target = s**2 + a**2 / 12
    assert_allclose(m2.mean(), target, rtol=1e-10)  # exact identity; 1e-10 covers rounding
    # ...whereas for a single x0 it is not exact at this coarse a / s
    assert np.max(np.abs(m2 / target - 1)) > 1e-4


def test_tophat_variance_averaged_over_pixel_phase():
    """Variance about the per-x0 mean, averaged over x0: s**2 + a**2/12 minus the variance of
    the centroid bias over x0, which is ~ (a / pi)**2 exp(-4 pi**2 s**2 / a**2) / 2 relative
    ~1e-18 at a / s = 1, so 1e-6 is a loose bound."""
    s, a = 100.0, 100.0
    _, var, _ = _x_marginal_moments(_uniform_in_pixel(a), s, a, _roi_for(s, a))
    assert_allclose(var.mean(), s**2 + a**2 / 12, rtol=1e-6)


def test_tophat_fixed_x0_at_pixel_centre():
    """For fixed x0 = 0, Poisson summation gives Var = s**2 + a**2/12 + O(exp(-2 pi**2 s**2/a**2))
    (Euler-Maclaurin / aliasing); at a / s = 0.5 that is exp(-79) ~ 1e-34, so the 1e-3 asked for
    is very loose; we also check 1e-12, which only float rounding could threaten."""
    s, a = 200.0, 100.0
    mean, var, _ = _x_marginal_moments([0.0], s, a, _roi_for(s, a))
    target = s**2 + a**2 / 12
    assert abs(mean[0]) < 1e-10 * s
    assert_allclose(var[0], target, rtol=1e-3)
    assert_allclose(var[0], target, rtol=1e-12)
    # the a**2/12 term is really there: without it the error would be ~2 %
    assert abs(var[0] / s**2 - 1) > 1e-2


# --------------------------------------------------------------------------------------------
# 8. sampled_gaussian (Eq. A3.1)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("params", "roi", "a"),
    [
        (_params(12.0, -33.0, 90.0, 140.0, 5000.0, 2.5), 7, 100.0),
        (_params(-260.0, 180.0, 60.0, 60.0, 1.0, 0.0), 9, 80.0),
    ],
)
def test_sampled_gaussian_formula(params, roi, a):
    x0, y0, sx, sy, n, b = params
    want = np.empty((roi, roi))
    for i in range(roi):
        y = (i - (roi - 1) / 2) * a
        for j in range(roi):
            x = (j - (roi - 1) / 2) * a
            want[i, j] = (
                n
                * a
                * a
                / (2 * math.pi * sx * sy)
                * math.exp(-((x - x0) ** 2) / (2 * sx**2) - (y - y0) ** 2 / (2 * sy**2))
                + b
            )
    # rtol 1e-13: the same expression in different operation order (exp of a sum vs product of
    # exps); the exponent is <= ~15 so its rounding costs ~1e-15 relative.
    assert_allclose(sampled_gaussian(params, roi, a), want, rtol=1e-13, atol=0)


def test_sampled_gaussian_converges_to_pixel_integral_quadratically():
    """Midpoint rule: Px = a phi(z_c)/s (1 + (a/s)**2 (z_c**2 - 1)/24 + O((a/s)**4)), so the
    relative gap between Eq. A3.1 and the integrated pixel shrinks like (a/s)**2."""
    s = 100.0

    def rel_gap(a):
        p = _params(0.0, 0.0, s, s, 1.0, 0.0)
        roi = 5
        exact = expected_counts(p, roi, a)
        sampled = sampled_gaussian(p, roi, a)
        return abs(sampled[2, 2] / exact[2, 2] - 1)

    g1, g2 = rel_gap(10.0), rel_gap(5.0)  # a/s = 0.1 and 0.05
    assert_allclose(g1, (0.1**2) / 12, rtol=2e-2)  # leading term 2 * (a/s)**2 / 24 at z_c = 0
    # ratio is 4 (1 + O((a/s)**2)): within 1 %
    assert_allclose(g1 / g2, 4.0, rtol=1e-2)
    # and the whole image converges (max relative gap over a 9 x 9 ROI, off-centre spot)
    p = _params(13.0, -21.0, s, 1.3 * s, 1.0, 0.0)
    gaps = []
    for a in (10.0, 5.0):
        exact = expected_counts(p, 9, a)
        gaps.append(np.max(np.abs(sampled_gaussian(p, 9, a) / exact - 1)))
    assert 3.8 < gaps[0] / gaps[1] < 4.2


# --------------------------------------------------------------------------------------------
# 9. pixel_centres
# --------------------------------------------------------------------------------------------


def test_pixel_centres_values():
    assert_array_equal(pixel_centres(5, 100.0), [-200.0, -100.0, 0.0, 100.0, 200.0])
    assert_array_equal(pixel_centres(1, 65.0), [0.0])
    assert_allclose(pixel_centres(3, 107.5), [-107.5, 0.0, 107.5], rtol=0, atol=0)
    assert pixel_centres(np.int64(7), 1).shape == (7,)


@pytest.mark.parametrize(("roi", "a"), [(3, 100.0), (9, 64.5), (21, 160.0)])
def test_pixel_centres_are_edge_midpoints(roi, a):
    c = pixel_centres(roi, a)
    k = np.arange(roi)
    lo = (k - roi / 2) * a
    hi = (k + 1 - roi / 2) * a
    assert_allclose(c, (lo + hi) / 2, rtol=0, atol=1e-12 * a)
    assert_allclose(np.diff(c), a, rtol=1e-14)
    assert_array_equal(c, -c[::-1])  # symmetric about the central pixel
    assert c[roi // 2] == 0.0


def test_pixel_centres_consistent_with_counts():
    # A narrow spot placed at a pixel centre puts its maximum in that pixel.
    roi, a = 7, 100.0
    c = pixel_centres(roi, a)
    for j in range(roi):
        img = expected_counts(_params(c[j], c[roi - 1 - j], 20, 20, 1, 0), roi, a)
        assert np.unravel_index(np.argmax(img), img.shape) == (roi - 1 - j, j)


# --------------------------------------------------------------------------------------------
# 10. Bad input
# --------------------------------------------------------------------------------------------

PARAM_FUNCS = [expected_counts, expected_counts_and_jacobian, sampled_gaussian]
GOOD = _params(0.0, 0.0, 100.0, 100.0, 1000.0, 1.0)


def _with(k, value):
    p = GOOD.copy()
    p[k] = value
    return p


@pytest.mark.parametrize("func", PARAM_FUNCS)
@pytest.mark.parametrize(
    ("params", "match"),
    [
        pytest.param(np.zeros(5), "params", id="last-dim-5"),
        pytest.param(np.zeros((2, 7)), "params", id="last-dim-7"),
        pytest.param(1.0, "params", id="scalar"),
        pytest.param(_with(0, np.nan), "params", id="nan-x0"),
        pytest.param(_with(4, np.inf), "params", id="inf-N"),
        pytest.param("abc", "params", id="non-numeric"),
        pytest.param(_with(2, 0.0), "s_x", id="sx-zero"),
        pytest.param(_with(2, -5.0), "s_x", id="sx-negative"),
        pytest.param(_with(3, 0.0), "s_y", id="sy-zero"),
        pytest.param(_with(4, -1.0), r"\(N\)", id="N-negative"),
        pytest.param(_with(5, -1e-3), r"\(b\)", id="b-negative"),
    ],
)
def test_bad_params_raise(func, params, match):
    with pytest.raises(ValueError, match=match):
        func(params, 5, 100.0)


def test_bad_param_in_batch_raises():
    p = np.tile(GOOD, (3, 2, 1))
    p[2, 1, 2] = -1.0
    with pytest.raises(ValueError, match="s_x"):
        expected_counts(p, 5, 100.0)


@pytest.mark.parametrize("func", [*PARAM_FUNCS, None])
@pytest.mark.parametrize(
    ("roi", "a", "match"),
    [
        pytest.param(4, 100.0, "roi", id="roi-even"),
        pytest.param(0, 100.0, "roi", id="roi-zero"),
        pytest.param(-3, 100.0, "roi", id="roi-negative"),
        pytest.param(5.0, 100.0, "roi", id="roi-float"),
        pytest.param(True, 100.0, "roi", id="roi-bool"),
        pytest.param(5, 0.0, "pixel_size", id="a-zero"),
        pytest.param(5, -100.0, "pixel_size", id="a-negative"),
        pytest.param(5, float("nan"), "pixel_size", id="a-nan"),
        pytest.param(5, float("inf"), "pixel_size", id="a-inf"),
        pytest.param(5, None, "pixel_size", id="a-none"),
    ],
)
def test_bad_geometry_raises(func, roi, a, match):
    with pytest.raises(ValueError, match=match):
        if func is None:
            pixel_centres(roi, a)
        else:
            func(GOOD, roi, a)


def test_errors_are_valueerror_subclass():
    from bayespsf.errors import BayespsfInputError

    assert issubclass(BayespsfInputError, ValueError)
    with pytest.raises(BayespsfInputError):
        psf.expected_counts(GOOD, 2, 100.0)


# --------------------------------------------------------------------------------------------
# 11. Property test
# --------------------------------------------------------------------------------------------

_finite = {"allow_nan": False, "allow_infinity": False}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    x0=st.floats(-5000, 5000, **_finite),
    y0=st.floats(-5000, 5000, **_finite),
    sx=st.floats(1, 5000, **_finite),
    sy=st.floats(1, 5000, **_finite),
    n=st.floats(0, 1e7, **_finite),
    b=st.floats(0, 1e4, **_finite),
    roi=st.sampled_from([1, 3, 7, 15]),
    a=st.floats(1, 500, **_finite),
)
def test_property_finite_bounded(x0, y0, sx, sy, n, b, roi, a):
    p = np.array([x0, y0, sx, sy, n, b])
    with warnings.catch_warnings(), np.errstate(over="raise", invalid="raise", divide="raise"):
        warnings.simplefilter("error")
        mu = expected_counts(p, roi, a)
        mu_j, jac = expected_counts_and_jacobian(p, roi, a)
        sg = sampled_gaussian(p, roi, a)
    assert mu.shape == (roi, roi)
    assert np.all(np.isfinite(mu))
    assert np.all(mu >= b)
    # total of a partial plane cannot exceed N + roi**2 b; 1e-9 relative slack for rounding
    total = n + roi**2 * b
    assert mu.sum() <= total * (1 + 1e-9)
    # the Jacobian path gives the same mu (to rounding) and finite derivatives
    assert np.all(np.isfinite(jac))
    assert_allclose(mu_j, mu, rtol=1e-15, atol=1e-300)  # atol: subnormal N
    assert np.all(np.isfinite(sg)) and np.all(sg >= b)
    # pixel masses are probabilities: every one-axis fraction in [0, 1]
    unit = p.copy()
    unit[4], unit[5] = 1.0, 0.0
    frac = expected_counts(unit, roi, a)
    assert np.all((frac >= 0) & (frac <= 1 + 1e-15))


def test_sampled_jacobian_matches_central_differences():
    # the sampled pixel model's analytic derivatives (d/dcentre = m z / w, d/dwidth =
    # m (z^2 - 1) / w) against central differences with step 1e-5 of each parameter (error
    # O(h^2) ~ 1e-10 relative), and its counts equal sampled_gaussian
    p, roi, a = _params(13.0, -27.0, 95.0, 140.0, 800.0, 3.0), 9, 100.0
    mu, jac = expected_counts_and_jacobian(p, roi, a, pixel_model="sampled")
    assert_allclose(mu, sampled_gaussian(p, roi, a), rtol=1e-14)
    for k in range(6):
        h = 1e-5 * max(abs(p[k]), 1.0)
        up, down = p.copy(), p.copy()
        up[k] += h
        down[k] -= h
        numeric = (sampled_gaussian(up, roi, a) - sampled_gaussian(down, roi, a)) / (2 * h)
        assert_allclose(jac[k], numeric, rtol=1e-6, atol=1e-9 * np.abs(numeric).max())


def test_unknown_pixel_model_is_named():
    with pytest.raises(BayespsfInputError, match="pixel_model"):
        expected_counts_and_jacobian(_params(0, 0, 100, 100, 100, 1), 5, 100.0, "binned")
