"""The local background surface and the detection threshold map against direct computation:
the window sums against a loop over the pixels, the fit against surfaces it must reproduce
exactly (a quartic, and a quadratic where the quartic is poorly determined), the threshold map
against the saddlepoint threshold computed at each pixel's own level."""

import numpy as np
import pytest

from bayespsf.cameras import EMCCD
from bayespsf.movie import _background, _noise

DEGREE = _background.DEGREE


def _surface(shape, degree, rng):
    """A positive polynomial of ``degree`` in (row, column) over the image, ~10 to 30."""
    r, c = np.meshgrid(*(np.linspace(-1.0, 1.0, n) for n in shape), indexing="ij")
    out = np.full(shape, 20.0)
    for t in range(1, degree + 1):
        for b in range(t + 1):
            out += rng.uniform(-1.0, 1.0) * r ** (t - b) * c**b
    return out


def test_window_sums_match_a_loop_over_the_pixels():
    """``_moments`` (stacked sparse products) against the sums ``Σ values u^a v^b`` over each
    anchor's window written out pixel by pixel, for every ``a + b <= 8``: equal to rounding
    (1e-12 relative to the largest sum)."""
    rng = np.random.default_rng(1)
    shape, size = (37, 29), 15
    values = rng.uniform(0.0, 5.0, shape)
    axes = [_background._axis(n, size) for n in shape]
    found = _background._moments(axes, values, 2 * DEGREE)
    half = size // 2
    row_anchors = np.unique(np.r_[np.arange(0, shape[0], size // 8), shape[0] - 1])
    col_anchors = np.unique(np.r_[np.arange(0, shape[1], size // 8), shape[1] - 1])
    expected = np.zeros_like(found)
    for i, r0 in enumerate(row_anchors):
        rows = np.arange(max(0, r0 - half), min(shape[0], r0 + half + 1))
        for j, c0 in enumerate(col_anchors):
            cols = np.arange(max(0, c0 - half), min(shape[1], c0 + half + 1))
            u, v = (rows - r0) / half, (cols - c0) / half
            block = values[np.ix_(rows, cols)]
            for a in range(2 * DEGREE + 1):
                for b in range(2 * DEGREE + 1 - a):
                    expected[a, b, i, j] = (u[:, None] ** a * v[None, :] ** b * block).sum()
    assert np.abs(found - expected).max() < 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("masked", [False, True])
def test_a_quartic_background_is_reproduced(masked):
    """The local quartic is unbiased for a quartic background: without noise, fitted to every
    pixel (the windows' inverses kept per shape) or to the pixels left by 30 discs of radius 6
    (each window's normal equations solved), it returns the surface (~20 photons) to 1e-7
    photons: the ridge (1e-12 of the normal matrix's trace) and rounding through its condition
    leave ~2e-8."""
    rng = np.random.default_rng(2)
    shape = (160, 120)
    image = _surface(shape, DEGREE, rng)
    keep = np.ones(shape, dtype=bool)
    if masked:
        rr, cc = np.indices(shape)
        centres = zip(rng.integers(0, shape[0], 30), rng.integers(0, shape[1], 30), strict=True)
        for r0, c0 in centres:
            keep &= (rr - r0) ** 2 + (cc - c0) ** 2 > 36
    window = _background._Window(shape, 63, 13)
    assert window.curved
    back = window.fit(image, keep, None)
    assert np.abs(back - image).max() < 1e-7


def test_a_window_mostly_left_out_falls_back_to_the_quadratic():
    """Where the kept pixels leave the quartic poorly determined (a hole of radius 20 in the
    middle of 128 x 128 pixels: the quartic's value at the nearby anchors varies beyond 4 times
    the full window's), the quadratic is fitted there and no window falls back to a constant:
    the fit is exact on a quadratic background (1e-7 photons, as the quartic's test)."""
    rng = np.random.default_rng(3)
    shape = (128, 128)
    image = _surface(shape, 2, rng)
    rr, cc = np.indices(shape)
    keep = (rr - 64) ** 2 + (cc - 64) ** 2 > 20**2
    window = _background._Window(shape, 63, 13)
    masked = _background._moments(window.axes, keep.astype(float), 2 * DEGREE)
    data = _background._moments(window.axes, keep * image, DEGREE)
    rhs = np.stack([data[a, b] for a, b in _background._TERMS], axis=-1)
    coef = np.full((*masked.shape[2:], len(_background._TERMS)), np.nan)
    _background._masked_fit(masked, rhs, window.variance, coef.reshape(-1, rhs.shape[-1]))
    coef = coef.reshape(-1, rhs.shape[-1])
    quadratic = np.isfinite(coef[:, 0]) & np.isnan(coef[:, 6])
    assert quadratic.sum() >= 5
    assert np.isfinite(coef[:, 0]).all()  # no anchor left to the constant
    back = window.fit(image, keep, None)
    assert np.abs(back - image).max() < 1e-7


def test_the_threshold_map_matches_the_saddlepoint_at_each_level():
    """``threshold_map`` interpolates the saddlepoint threshold from a fixed lattice of levels
    2 % apart: against ``null_thresholds`` at each sampled pixel's own background (an EMCCD
    frame on a ramp from 0.5 to 40 photons, and on one level), within 1e-4 relative (the
    threshold is smooth in log background: the interpolation's error is second order in the
    2 % step)."""
    camera = EMCCD(gain=100.0, offset=100.0, readout_sd=10.0)
    law = _noise.pixel_law(camera, 1)
    spot = _noise.template(130.0, 100.0)
    alpha = 0.01 / 256**2
    back = np.geomspace(0.5, 40.0, 256)[:, None] * np.ones((1, 8))
    found = _noise.threshold_map(law, spot, back, alpha)
    rows = np.arange(0, 256, 17)
    direct = _noise.null_thresholds(law, spot, back[rows, 0], alpha)
    assert np.abs(found[rows, 0] / direct - 1.0).max() < 1e-4
    level = _noise.threshold_map(law, spot, 7.3, alpha)
    assert isinstance(level, float)
    assert abs(level / _noise.null_thresholds(law, spot, 7.3, alpha)[0] - 1.0) < 1e-4


def _fits_by_hand(image, spot, size, level, variance):
    """``estimate_background``'s fits written out, both mask passes always made."""
    window = _background._Window(image.shape, size, len(spot[0]))
    back = window.fit(image, np.ones(image.shape, dtype=bool), None)
    for _ in range(2):
        clip = np.abs(image - back) < _background.PIXEL_CLIP * np.sqrt(variance)
        back = window.fit(image, clip, back)
    for _ in range(2):
        keep = _background.background_pixels(image, back, variance, spot, level)
        back = window.fit(image, keep, back)
    return back, keep


def test_a_fit_repeated_on_its_own_mask_and_result_is_itself():
    """What skipping a repeated mask's fit rests on: ``fit(image, keep, fit(image, keep, p))``
    is ``fit(image, keep, p)`` to the last bit, also where windows keep under a tenth of their
    pixels and take the previous surface (a hole of radius 45 pixels in 128 x 128, with an
    arbitrary previous surface ``p``)."""
    rng = np.random.default_rng(4)
    shape = (128, 128)
    image = rng.poisson(_surface(shape, 2, rng)).astype(float)
    rr, cc = np.indices(shape)
    keep = (rr - 64) ** 2 + (cc - 64) ** 2 > 45**2
    previous = rng.uniform(0.0, 50.0, shape)
    window = _background._Window(shape, 63, 13)
    once = window.fit(image, keep, previous)
    assert np.sum(once == previous) > 100  # windows that fell back to the previous surface
    assert np.array_equal(window.fit(image, keep, once), once)


def test_a_second_mask_like_the_first_is_not_fitted_again_and_changes_nothing(monkeypatch):
    """Where the second mask pass keeps the pixels the first kept, its fit is skipped, and the
    background and the mask are the ones that making it gives, to the last bit; where it
    keeps others, it is made. Frames: a quadratic background (~20 photons) with 40 spots of
    300-3 000 photons (SD 1.3 pixels) and Poisson noise."""
    spot = _noise.template(130.0, 100.0)
    shape, size, level = (128, 128), 63, 5.0
    fits = []
    fit = _background._Window.fit

    def counted(self, image, keep, previous):
        fits.append(1)
        return fit(self, image, keep, previous)

    rr, cc = np.indices(shape)
    made = set()
    for seed in range(8):
        rng = np.random.default_rng(seed)
        mean = _surface(shape, 2, rng)
        (rows, cols), photons = rng.uniform(5, 123, (2, 40)), rng.uniform(3e2, 3e3, 40)
        for r0, c0, n in zip(rows, cols, photons, strict=True):
            gauss = np.exp(-((rr - r0) ** 2 + (cc - c0) ** 2) / (2 * 1.3**2))
            mean += n * gauss / (2 * np.pi * 1.3**2)
        image = rng.poisson(mean).astype(float)
        variance = float(np.median(mean))
        expected = _fits_by_hand(image, spot, size, level, variance)
        fits.clear()
        with monkeypatch.context() as patch:
            patch.setattr(_background._Window, "fit", counted)
            back, keep, degree = _background.estimate_background(image, spot, size, level, variance)
        assert degree == DEGREE
        assert np.array_equal(back, expected[0]) and np.array_equal(keep, expected[1])
        made.add(len(fits))
    assert made == {4, 5}  # both cases occur among these frames
