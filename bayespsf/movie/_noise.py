"""The noise of detection: a pixel's noise variance from the camera law or estimated from the
image itself, the matched filter and its threshold from the camera law's tail (the local
background under a spot is estimated in ``_background``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, special, stats

from bayespsf import psf
from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError

MASK_SCORE = 3.0  # the least score whose neighbourhood is left out of the background
CLIP = 4.0  # differences of adjacent pixels beyond CLIP SDs are left out of the noise variance
# variance of a standard normal truncated to (-CLIP, CLIP)
KEPT_VARIANCE = 1.0 - 2.0 * CLIP * stats.norm.pdf(CLIP) / (1.0 - 2.0 * stats.norm.sf(CLIP))
_MAD_SCALE = float(stats.norm.ppf(0.75))  # a normal law's median absolute deviation over its SD


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
    deviations = np.abs(diffs - np.median(diffs))
    sd = float(np.median(deviations)) / _MAD_SCALE or diffs.std()
    for _ in range(3):
        kept = diffs[deviations < CLIP * sd]
        sd = np.sqrt(kept.var() / KEPT_VARIANCE) if kept.size > 1 else sd
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


@dataclass(frozen=True)
class PixelLaw:
    """A background pixel's law in detected photons, for the exact null of the score.

    Per frame: ``n ~ Poisson(lam)`` photoelectrons; an EM register (``amplified``) turns each
    into an exponential number of gain units of mean 1 (``Gamma(n, G) / G``); readout adds
    ``Normal(0, readout_var)``; the detector sees the mean of ``frames`` such frames. Its
    cumulant generating function per frame is ``lam kappa(theta) + readout_var theta**2 / 2``
    with ``kappa(theta) = theta / (1 - theta)`` (EMCCD, ``theta < 1``; Basden, Haniff & Mackay,
    MNRAS 345 (2003) 985: the compound Poisson of exponentials) or ``exp(theta) - 1``
    (Poisson).
    """

    amplified: bool
    readout_var: float
    frames: int

    def variance(self, lam):
        """Variance of the ``frames``-frame mean at ``lam`` photons per pixel per frame."""
        return ((2.0 if self.amplified else 1.0) * lam + self.readout_var) / self.frames

    def kappa(self, theta, order: int):
        """``kappa`` (order 0) and its first two derivatives at ``theta``."""
        if self.amplified:
            return theta / (1.0 - theta) if order == 0 else order / (1.0 - theta) ** (order + 1)
        return np.expm1(theta) if order == 0 else np.exp(theta)


def pixel_law(camera, frames: int) -> PixelLaw:
    """The ``PixelLaw`` of a camera (or Model) for a mean of ``frames`` frames: EMCCDs are
    amplified, other cameras Poisson; the readout variance in photons² is the camera law's
    variance at no light (its median over an sCMOS map)."""
    from bayespsf.cameras import EMCCD
    from bayespsf.movie.extract import photon_model

    model = photon_model(camera)
    readout = float(np.median(model.photon_variance(np.zeros((1, 1)))))
    return PixelLaw(isinstance(model.camera, EMCCD), readout, int(frames))


def null_thresholds(law: PixelLaw, spot, lam, alpha: float) -> np.ndarray:
    """The score ``t`` exceeded with probability ``alpha`` by a background pixel of ``lam``
    photons (one per value of ``lam``), from the saddlepoint approximation of the score's law.

    On a flat background of ``lam`` photons and the law's variance ``v``, the score is
    ``T = Σ c_i (x_i - lam) / sqrt(v)`` with ``c = g / ||g||``, a weighted sum of independent
    pixels, whose cumulant generating function ``K(u)`` follows from the law's (``PixelLaw``).
    Its upper tail at the saddlepoint ``K'(û) = t`` is Robinson's formula
    ``P(T > t) ≈ exp(K(û) - û t + ẑ²/2) Q(ẑ)``, ``ẑ = û sqrt(K''(û))``: the exponentially
    tilted law (mean ``t``) taken as normal (Robinson, J. R. Stat. Soc. B 44 (1982) 91;
    Daniels, Int. Stat. Rev. 55 (1987) 37). It is accurate in relative terms far into the
    tail, where the normal law of the central limit theorem is not (EMCCD pixels at a few
    photons are exponential-like, and ``alpha`` is of order ``1e-9`` on a large image). Against
    Monte Carlo of 2.4e7 scores (EMCCD and ideal cameras, 1 to 10 photons, 1 and 5 frames)
    the observed over the stated rate was 0.9 to 1.05 at ``alpha`` 1e-3 and 1e-4, 0.7 to 1.1
    at 1e-5 (low where the tail is heaviest: safe); on backgrounds far below the readout
    noise it errs high (safe), up to a factor of 3, where the Lugannani–Rice formula fails
    (negative tails). An upper bound on it is Chernoff's, ``exp(K(û) - û t)``.
    """
    g = np.outer(*spot).ravel()
    c = g / np.sqrt(np.sum(g**2))
    return np.array([_threshold(law, c, float(x), alpha) for x in np.atleast_1d(lam)])


def _threshold(law: PixelLaw, c: np.ndarray, lam: float, alpha: float) -> float:
    gauss = float(stats.norm.isf(alpha))
    v = law.variance(lam)
    if lam <= 0 or v <= 0 or gauss < 1.0:
        return gauss
    k = law.frames
    a = c / np.sqrt(v)  # T = Σ a_i (x_i - lam)
    total = a.sum()

    def cumulants(u):
        theta = a * u / k
        k0 = (
            k * (lam * law.kappa(theta, 0) + law.readout_var * theta**2 / 2).sum() - u * lam * total
        )
        k1 = (a * (lam * law.kappa(theta, 1) + law.readout_var * theta)).sum() - lam * total
        k2 = (a**2 * (lam * law.kappa(theta, 2) + law.readout_var)).sum() / k
        return k0, k1, k2

    def log_tail(u):  # log P(T > K'(u)) - log alpha, Robinson's formula
        k0, t, k2 = cumulants(u)
        z = u * np.sqrt(k2)
        mills = np.sqrt(np.pi / 2.0) * special.erfcx(z / np.sqrt(2.0))
        return k0 - u * t + np.log(mills) - 0.5 * np.log(2.0 * np.pi) - np.log(alpha)

    high = (k / a.max()) * (1.0 - 1e-12) if law.amplified else 2.0 * gauss
    while not law.amplified and log_tail(high) > 0:
        high *= 2.0
    u = optimize.brentq(log_tail, 1e-3, high, xtol=1e-10, rtol=1e-10)
    return float(cumulants(u)[1])


def check_signal(image: np.ndarray, saturated, unit: str, what: str = "the image") -> None:
    """Refuse an image without signal, naming why: every pixel equal (saturated, all zero or
    constant), or most pixels at the ADC's full scale (``saturated``: a mask, or None)."""
    flat = image.ravel()
    share = 0.0 if saturated is None else float(np.mean(saturated))
    if flat.size and np.all(flat == flat[0]):
        value = float(flat[0])
        if share == 1.0:
            why = (
                "every pixel is saturated (at the ADC's full scale, or the camera's declared "
                "saturation): lower the EM gain, the exposure or the excitation"
            )
        elif value == 0.0:
            why = "an all-zero image: a blank or unconnected camera, or frames never filled"
        else:
            why = "a constant image carries no spot and no noise: not a camera's counts"
        raise BayespsfInputError(f"{what}: every pixel is {value:g} {unit}: {why}")
    if share > 0.5:
        raise BayespsfInputError(
            f"{what}: {np.count_nonzero(saturated)} of {saturated.size} pixels ({share:.0%}) are "
            "saturated (at the ADC's full scale in some frame): lower the EM gain, the "
            "exposure or the excitation, or declare the camera's saturation ([camera] "
            "saturation) if this is not it"
        )


def check_background(back, tolerance: float, source: str) -> None:
    """Refuse a background whose median lies more than ``tolerance`` photons below 0."""
    level = float(np.median(back))
    if level < -tolerance:
        raise BayespsfInputError(
            f"background: {level:.4g} photons per pixel ({source}, median), more than "
            f"{tolerance:.3g} below 0 (the noise allows no less): the counts were converted "
            "with too large an offset, or are not above one; check the camera's offset "
            "([camera] offset in the camera file) or give a background >= 0"
        )


def check_offset(image: np.ndarray, camera, what: str) -> None:
    """Refuse counts (ADU) whose median lies below the camera's offset by more than five
    readout SDs of one frame (and one ADU): the offset is wrong or was already subtracted."""
    _, offset = camera.photons_per_adu()
    offset = float(np.median(offset))
    readout = float(np.sqrt(np.median(camera.variance(np.zeros((1, 1))))))
    step = max(1, int(np.sqrt(image.size / 1e5)))  # a median of ~1e5 pixels is enough
    median = float(np.median(image[::step, ::step]))
    if median < offset - max(5.0 * readout, 1.0):
        raise BayespsfInputError(
            f"{what}: its median count {median:.6g} ADU lies {offset - median:.6g} ADU below "
            f"the camera's offset {offset:g} ADU (more than 5 readout SDs of {readout:.3g} "
            "ADU): is the offset right ([camera] offset in the camera file, the camera's "
            "offset=), or was it already subtracted from the movie?"
        )


_LEVEL_STEP = np.log(1.02)  # the lattice of background levels: 2 % apart in log background
_MOST_LEVELS = 64


def threshold_map(law, spot, back, alpha):
    """The exact-tail threshold at each pixel's background (a number or a map): computed at the
    levels of a fixed lattice, ``1.02**k`` photons (every ``s``-th, ``s`` the least stride
    that spans the image's backgrounds down to 1e-3 of the highest in ``_MOST_LEVELS``), and
    interpolated in log background. Each level's threshold is computed once per process
    (``_level_threshold``), so that the frames of a movie share them."""
    lam = np.maximum(np.asarray(back, dtype=np.float64), 0.0)
    low, high = float(lam.min()), float(lam.max())
    if high <= 0:
        return float(stats.norm.isf(alpha))
    low = max(low, 1e-3 * high)
    first, last = np.log(low) / _LEVEL_STEP, np.log(high) / _LEVEL_STEP
    stride = max(1, int(np.ceil((np.ceil(last) - np.floor(first)) / (_MOST_LEVELS - 1))))
    ks = np.arange(np.floor(first / stride), np.ceil(last / stride) + 1, dtype=int) * stride
    g = np.outer(*spot).ravel()
    key = (g / np.sqrt(np.sum(g**2))).tobytes()
    levels = [_level_threshold(law, key, int(k), float(alpha)) for k in ks]
    found = np.interp(np.log(np.maximum(lam, low)), ks * _LEVEL_STEP, levels)
    return float(found) if not lam.ndim else found


@functools.lru_cache(maxsize=4096)
def _level_threshold(law: PixelLaw, weights: bytes, k: int, alpha: float) -> float:
    """``null_thresholds`` at ``1.02**k`` photons, for the template weights ``c`` (bytes of
    ``g / ||g||``)."""
    return _threshold(law, np.frombuffer(weights), float(np.exp(k * _LEVEL_STEP)), alpha)


def spot_variance(law, var, back):
    """Each window pixel's variance with ``spot`` photons on it: the camera law's at background
    plus spot (``law``), else the background's noise ``var`` times ``1 + spot / background``,
    which bounds it for a Poisson or EMCCD pixel (readout does not grow with the light)."""
    var = np.asarray(var, dtype=np.float64)
    back = np.asarray(back, dtype=np.float64)

    def at(win_r, win_c, spot):
        b = back[win_r[:, :, None], win_c[:, None, :]] if back.ndim else back
        if law is not None:
            return law.variance(np.maximum(b, 0.0) + spot)
        v = var[win_r[:, :, None], win_c[:, None, :]] if var.ndim else var
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(b > 0, v * (1.0 + spot / b), v + 2.0 * spot)

    return at


def at_type_maximum(image):
    """Pixels at the largest value of an integer image's type (an ADC's full scale), or None."""
    dtype = getattr(image, "dtype", None)
    if dtype is None or np.dtype(dtype).kind not in "iu":
        return None
    return np.asarray(image) == np.iinfo(dtype).max


def saturation_level(dtype, camera) -> float | None:
    """The count at which the movie saturates: the camera's declared ``saturation`` (a Model's,
    if > 0) or the largest value of an integer data type, whichever is lower; None for float
    data without a declared saturation."""
    declared = getattr(camera, "saturation", 0.0) or 0.0
    levels = [float(declared)] if declared > 0 else []
    if np.dtype(dtype).kind in "iu":
        levels.append(float(np.iinfo(dtype).max))
    return min(levels) if levels else None


def checked_map(name: str, value, shape) -> np.ndarray:
    """A scalar or ``shape`` array of finite values."""
    arr = finite_array(name, value)
    if arr.ndim and arr.shape != shape:
        raise BayespsfInputError(f"{name} must be a number or an array {shape}, got {arr.shape}")
    return arr
