"""The two nuisance quantities of detection: the background under a spot and the noise variance
of a pixel, from the camera law or estimated from the image itself."""

from __future__ import annotations

import numpy as np
from scipy import ndimage, stats

from bayespsf import psf
from bayespsf.errors import BayespsfInputError

MASK_SCORE = 3.0  # the least score whose neighbourhood is left out of the background
CLIP = 4.0  # differences of adjacent pixels beyond CLIP SDs are left out of the noise variance
# variance of a standard normal truncated to (-CLIP, CLIP)
_KEPT_VARIANCE = 1.0 - 2.0 * CLIP * stats.norm.pdf(CLIP) / (1.0 - 2.0 * stats.norm.sf(CLIP))


def camera_noise_variance(camera, background, frames: int = 1) -> np.ndarray:
    """Variance (photons², per pixel) of the mean of ``frames`` frames of background.

    Parameters
    ----------
    camera : bayespsf.cameras.Camera or bayespsf.Model
        The camera law (one gain and offset); a Model's camera is used.
    background : float or array_like
        Background in photons per pixel per frame (values below 0 are taken as 0).
    frames : int
        Frames averaged (K): a mean projection of K frames has ``1/K`` of a frame's variance.

    Returns
    -------
    numpy.ndarray
        ``camera.variance(b) * photons_per_adu**2 / K`` (``Model.photon_variance``): for an
        EMCCD ``(2 b + (readout_sd / gain)**2) / K``, for an ideal photon counter ``b / K``.
    """
    from bayespsf.movie.extract import photon_model

    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise BayespsfInputError(f"frames must be a whole number >= 1, got {frames!r}")
    lam = np.maximum(np.asarray(background, dtype=np.float64), 0.0)
    return photon_model(camera).photon_variance(lam) / int(frames)


def estimate_noise_variance(image) -> float:
    """Per-pixel noise variance of an image, robustly, from differences of adjacent pixels.

    The differences of horizontally and vertically adjacent pixels remove any smooth
    background; for independent pixels of variance σ² each difference has variance 2σ² and a
    symmetric law. Their scale is started from the median absolute deviation (scaled to a
    normal SD; Rousseeuw & Croux, J. Am. Stat. Assoc. 88 (1993) 1273), then refined as the
    variance of the differences within ``CLIP`` SDs of their mean (three passes), divided by
    the variance a normal law keeps within that range: the differences that spots raise are
    left out, and, unlike the MAD, the estimate is not quantised by integer photon counts.
    σ̂² is half that variance. Where the noise varies over the image (it grows with the
    background), σ̂² is that of a typical pixel.
    """
    image = np.asarray(image, dtype=np.float64)
    diffs = np.concatenate([np.diff(image, axis=0).ravel(), np.diff(image, axis=1).ravel()])
    sd = stats.median_abs_deviation(diffs, scale="normal") or diffs.std()
    deviations = np.abs(diffs - np.median(diffs))
    for _ in range(3):
        kept = diffs[deviations < CLIP * sd]
        sd = np.sqrt(kept.var() / _KEPT_VARIANCE) if kept.size > 1 else sd
    return float(sd**2 / 2.0)


def matched_filter(residual: np.ndarray, variance, spot: tuple[np.ndarray, np.ndarray]):
    """Score ``T`` and amplitude ``N̂`` maps of the template ``g = outer(*spot)`` (photon
    fractions along rows and columns: the spot is separable).

    Under Gaussian noise of per-pixel variance ``v``: ``N̂ = Σ g x / v / Σ g² / v`` (the
    amplitude's maximum-likelihood estimate) and ``T = Σ g x / v / sqrt(Σ g² / v)``, N(0, 1)
    where ``x`` is background only. Pixels beyond the image's edge count as absent (both sums
    run over the image only), so ``T`` keeps its null law up to the edge.
    """
    weight = np.broadcast_to(1.0 / np.asarray(variance, dtype=np.float64), residual.shape)
    num, info = residual * weight, np.array(weight)
    for axis, fractions in enumerate(spot):
        num = ndimage.correlate1d(num, fractions, axis, mode="constant")
        info = ndimage.correlate1d(info, fractions**2, axis, mode="constant")
    return num / np.sqrt(info), num / info


def estimate_background(
    image: np.ndarray,
    spot: tuple[np.ndarray, np.ndarray],
    size: int,
    mask_score: float,
    variance: float,
) -> np.ndarray:
    """Local mean of the background pixels around each pixel (photons per pixel).

    A mean over a ``size`` × ``size`` window (the median is biased on skewed or discrete
    counts, which would bias the score), after leaving out the pixels within the template's
    reach of any pixel whose matched-filter score exceeds ``mask_score`` (at least
    ``MASK_SCORE``; detection passes its threshold, so that the background's own noise
    excursions are not left out, which would bias it low): first against the plain local
    mean, then once more against the first estimate. A window with under a tenth
    of its pixels left keeps the previous estimate. ``variance``: the noise variance that
    scores the pixels (``estimate_noise_variance``).
    """
    back = ndimage.uniform_filter(image, size)
    reach = len(spot[0])
    for _ in range(2):
        score, _ = matched_filter(image - back, variance, spot)
        spots = ndimage.maximum_filter(score > max(mask_score, MASK_SCORE), reach)
        keep = (~spots).astype(np.float64)
        share = ndimage.uniform_filter(keep, size)
        total = ndimage.uniform_filter(image * keep, size)
        with np.errstate(divide="ignore", invalid="ignore"):
            back = np.where(share > 0.1, total / share, back)
    return back


def template(psf_sd, pixel_size, image_shape=None) -> tuple[np.ndarray, np.ndarray]:
    """The spot's photon fractions along rows and along columns (its pixel integral is their
    outer product, ``bayespsf.psf.expected_counts``) on ``2 ceil(4 psf_sd / a) + 1`` pixels,
    which must fit in an image of ``image_shape`` if given."""
    if isinstance(psf_sd, bool) or not isinstance(psf_sd, int | float | np.number):
        raise BayespsfInputError(f"psf_sd must be a number in nm, got {psf_sd!r}")
    if not (np.isfinite(psf_sd) and psf_sd > 0):
        raise BayespsfInputError(f"psf_sd must be > 0 nm and finite, got {psf_sd!r}")
    _, a = psf.check_geometry(1, pixel_size)
    side = 2 * int(np.ceil(4.0 * psf_sd / a)) + 1
    if image_shape is not None and side > min(image_shape):
        raise BayespsfInputError(
            f"psf_sd ({psf_sd:g} nm = {psf_sd / a:.3g} pixels of {a:g} nm) gives a spot "
            f"template of {side} pixels, larger than the image {tuple(image_shape)}: is it "
            "in nm?"
        )
    spot = psf.expected_counts([0.0, 0.0, psf_sd, psf_sd, 1.0, 0.0], side, a)
    fractions = spot.sum(axis=0)
    return fractions, fractions
