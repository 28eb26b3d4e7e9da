"""The offset and readout noise from the movie itself, when no dark frames exist: photon
transfer with the counts' higher cumulants.

A background pixel's counts over frames are ``offset + M Y + readout``: ``M`` ADU per
photoelectron, readout ``Normal(0, sigma^2)`` and ``Y`` the pixel's amplified photoelectrons in
photoelectron units. For Poisson(lam) photons ``Y`` is a compound Poisson sum (each
photoelectron becomes an ``Exp(1)`` amount on an EMCCD, which is what ``Gamma(n, gain)`` is,
and exactly 1 on a CCD or sCMOS), so its cumulants are ``kappa_j(Y) = c_j lam`` with
``c_j = j!`` (EMCCD) or 1 (excess noise 1), and those of the counts are

    K1 = offset + lam M,   K2 = c2 lam M^2 + sigma^2,   K3 = c3 lam M^3,   K4 = c4 lam M^4

(a Gaussian's cumulants beyond the second vanish). The mean-variance relation alone (K1, K2:
the classic photon transfer, Janesick, Photon Transfer (2007)) cannot tell the offset from the
readout noise; the third cumulant can, because the readout adds nothing to it:

    offset = K1 - K3 / (c3 M^2),   sigma^2 = K2 - c2 K3 / (c3 M),

and ``K4 / K3 = (c4 / c3) M`` gives a first ``M`` for detection before the molecules give
the final one (``bayespsf.calibration.gain``, which needs no offset). Each pixel's cumulants are its
unbiased k-statistics over frames (Fisher 1930; Kendall & Stuart, The Advanced Theory of
Statistics, vol. 1, ch. 12), streamed from shifted power sums; the formulas are linear in them,
so the camera's values are means over background pixels, with standard errors from the pixels'
scatter (independent pixels) and from ``M``'s error.

It assumes what the model assumes: Poisson background photons that do not change over the
frames used. A sub-Poisson background (the paper-movie scene's rounded Gaussian photon numbers)
or a background that drifts biases the offset; molecules that bleach are kept out by a mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayespsf._validate import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.movie.extract import frame_span, molecule_pixels, open_movie
from bayespsf.movie.project import block_frames, blocks

CUMULANT_FACTORS = {  # c2, c3, c4 of the amplified photoelectrons, by excess-noise factor
    2.0: (2.0, 6.0, 24.0),  # EMCCD: Exp(1) per photoelectron, kappa_j = lam E[Exp(1)^j] = lam j!
    1.0: (1.0, 1.0, 1.0),  # CCD, sCMOS: one photoelectron is one
}
MIN_FRAMES = 20  # a third cumulant over fewer frames is too noisy to be worth it
POISSON_CHECK_SE = 5.0  # a declared readout this many SEs from the cumulants' is refused


@dataclass(frozen=True)
class PixelCumulants:
    """Per-pixel k-statistics ``k1 .. k4`` (ADU, ADU^2, ...) of a movie over ``frames``."""

    k1: np.ndarray
    k2: np.ndarray
    k3: np.ndarray
    k4: np.ndarray
    frames: int


def pixel_cumulants(
    movie, frames=None, block: int | None = None, budget: int = 256 * 2**20
) -> PixelCumulants:
    """The unbiased k-statistics of every pixel's counts over frames, ``block`` frames in
    memory at a time (default: as many as fit ``budget`` bytes, as ``project``'s), from power
    sums of the counts less the first frame's, so that they do not cancel. A NaN or infinite
    count is an error naming its frame: it would make its pixel's cumulants NaN."""
    movie = open_movie(movie)
    span = frame_span(movie, frames)
    block = block_frames(movie, block, budget, 24)  # float64 data, deviations and powers
    n = len(span)
    if n < MIN_FRAMES:
        raise BayespsfInputError(
            f"the movie has {n} frame(s); the offset from the movie's own cumulants needs at "
            f"least {MIN_FRAMES} (or give dark frames: --dark)"
        )
    shift = None
    sums = None
    for part in blocks(movie, span, block):
        data = np.asarray(part, dtype=np.float64)  # finite: ``Movie.frames`` refuses NaN
        if shift is None:
            shift = data[0].copy()
            sums = np.zeros((4, *shift.shape))
        d = data - shift
        power = d.copy()
        for j in range(4):
            sums[j] += power.sum(axis=0)
            power *= d
    s1, s2, s3, s4 = sums
    k1 = s1 / n + shift
    k2 = (n * s2 - s1**2) / (n * (n - 1))
    k3 = (2 * s1**3 - 3 * n * s1 * s2 + n * n * s3) / (n * (n - 1) * (n - 2))
    k4 = (
        -6 * s1**4
        + 12 * n * s1**2 * s2
        - 3 * n * (n - 1) * s2**2
        - 4 * n * (n + 1) * s1 * s3
        + n * n * (n + 1) * s4
    ) / (n * (n - 1) * (n - 2) * (n - 3))
    return PixelCumulants(k1, k2, k3, k4, n)


@dataclass(frozen=True)
class MovieOffset:
    """Offset and readout noise from a movie's background pixels (``offset_from_cumulants``).

    ``offset`` and ``readout_sd`` in ADU, each with its standard error (``readout_sd_se`` 0
    where the readout was declared: ``readout_declared``); ``photons`` the mean background
    photoelectrons per pixel and frame (``lam``); ``pixels`` and ``frames`` used.
    """

    offset: float
    offset_se: float
    readout_sd: float
    readout_sd_se: float
    photons: float
    pixels: int
    frames: int
    readout_declared: bool = False

    def describe(self) -> str:
        readout = (
            f"readout {self.readout_sd:.6g} ADU as declared"
            if self.readout_declared
            else f"readout {self.readout_sd:.6g} +- {self.readout_sd_se:.2g} ADU"
        )
        return (
            f"offset {self.offset:.6g} +- {self.offset_se:.2g} ADU and {readout} from the "
            f"movie's {self.pixels} background pixels over {self.frames} frames (no dark "
            f"frames: their third cumulant, {self.photons:.3g} photoelectrons per pixel; "
            "assumes Poisson background photons)"
        )


def _check_excess(excess) -> tuple[float, float, float]:
    if excess not in CUMULANT_FACTORS:
        raise BayespsfInputError(
            f"excess must be 2 (EMCCD) or 1 (CCD, sCMOS; --kind), got {excess!r}"
        )
    return CUMULANT_FACTORS[excess]


def _background(cumulants: PixelCumulants, mask) -> tuple[np.ndarray, ...]:
    keep = np.ones(cumulants.k1.shape, bool) if mask is None else np.asarray(mask, bool)
    if keep.shape != cumulants.k1.shape:
        raise BayespsfInputError(
            f"mask has shape {keep.shape}, the movie's frames {cumulants.k1.shape}"
        )
    if keep.sum() < 100:
        raise BayespsfInputError(
            f"{int(keep.sum())} background pixels; the offset from the movie needs at least "
            "100 (pixels no molecule's ROI touches: give dark frames, --dark, or a movie with "
            "fewer molecules or a smaller --roi)"
        )
    return tuple(k[keep] for k in (cumulants.k1, cumulants.k2, cumulants.k3, cumulants.k4))


def _require_photon_noise(*cumulants: float) -> None:
    """The background's mean higher cumulants must be positive (amplified photons are)."""
    if not all(c > 0 for c in cumulants):
        raise BayespsfInputError(
            "the movie's background pixels have no photon noise to calibrate against (their "
            "third or fourth cumulant is not positive): give dark frames (--dark)"
        )


def first_adu_per_photon(cumulants: PixelCumulants, excess: float, mask=None) -> float:
    """``M`` from ``K4 / K3 = (c4 / c3) M`` over the background pixels: good enough to detect
    molecules with, before they give the final ``M``."""
    _, c3, c4 = _check_excess(excess)
    _, _, k3, k4 = _background(cumulants, mask)
    third, fourth = float(k3.mean()), float(k4.mean())
    _require_photon_noise(third, fourth)
    return c3 * fourth / (c4 * third)


def offset_from_cumulants(
    cumulants: PixelCumulants,
    adu_per_photon: float,
    excess: float,
    mask=None,
    adu_per_photon_se: float = 0.0,
    readout_adu: float | None = None,
    check: bool = True,
) -> MovieOffset:
    """Offset and readout from background pixels (``mask``: True where a pixel is background
    throughout; default all) given ``M`` (and its SE, propagated), module docstring.

    ``readout_adu``, the camera's readout SD in ADU where it is known (its specification), is
    used instead of the estimate, and checks the background: a readout variance more than
    ``POISSON_CHECK_SE`` standard errors from what the cumulants leave beyond Poisson photon
    noise means the photons are not Poisson (or not stationary), and is an error (``check``;
    off for a first pass whose ``M`` carries an error it does not state).

    Without it, a readout variance that is not above twice its standard error is an error:
    the photon noise of the background then hides the readout (an EMCCD at high gain:
    ``c2 lam M^2`` is ~100 times ``sigma^2``, and ``M``'s error alone moves the estimate by
    ``c2 lam M SE(M)``).
    """
    c2, c3, _ = _check_excess(excess)
    m = scalar_in_range("adu_per_photon", adu_per_photon, 0.0, low_inclusive=False)
    adu_per_photon_se = scalar_in_range("adu_per_photon_se", adu_per_photon_se, 0.0)
    if readout_adu is not None:
        readout_adu = scalar_in_range("readout_adu", readout_adu, 0.0)
    k1, k2, k3, _ = _background(cumulants, mask)
    pixels = k1.size
    lam = float(k3.mean() / (c3 * m**3))
    offset_p = k1 - k3 / (c3 * m * m)
    # d offset / dM = 2 lam and d sigma^2 / dM = c2 lam M, at the mean lam
    offset_se = np.hypot(offset_p.std(ddof=1) / np.sqrt(pixels), 2 * lam * adu_per_photon_se)
    common = dict(
        offset=float(offset_p.mean()),
        offset_se=float(offset_se),
        photons=lam,
        pixels=int(pixels),
        frames=cumulants.frames,
    )
    variance_p = k2 - c2 * k3 / (c3 * m)
    variance = float(variance_p.mean())
    variance_se = float(
        np.hypot(variance_p.std(ddof=1) / np.sqrt(pixels), c2 * lam * m * adu_per_photon_se)
    )
    if readout_adu is not None:
        if check and not abs(variance - readout_adu**2) <= POISSON_CHECK_SE * variance_se:
            raise BayespsfInputError(
                f"the movie's background is not Poisson photons over the declared readout at "
                f"{m:.4g} ADU per photoelectron: what its variance holds beyond the photon noise "
                f"of {lam:.3g} photoelectrons reads {variance:.4g} +- {variance_se:.2g} ADU^2, "
                f"not the readout's {readout_adu**2:.4g} ADU^2 (a sub-Poisson, drifting or "
                "structured background, or an ADU per photoelectron further off than its SE), "
                "so the offset from its cumulants would be biased: give dark frames (--dark), "
                "or check the declared readout (--readout-sd, electrons)"
            )
        _require_photon_noise(lam)
        return MovieOffset(
            readout_sd=float(readout_adu), readout_sd_se=0.0, readout_declared=True, **common
        )
    if not variance > 2 * variance_se:
        raise BayespsfInputError(
            f"the readout noise cannot be measured from this movie's background: its variance "
            f"reads {variance:.3g} +- {variance_se:.2g} ADU^2, under the photon noise of "
            f"{lam:.3g} photoelectrons per pixel. State the camera's readout noise (--readout-sd "
            "in electrons, from its specification) or give dark frames (--dark)"
        )
    _require_photon_noise(lam)
    readout = float(np.sqrt(variance))
    return MovieOffset(readout_sd=readout, readout_sd_se=variance_se / (2 * readout), **common)


def away_from(molecules, shape: tuple[int, int], half: int) -> np.ndarray:
    """True at the pixels farther than ``half`` pixels (in rows or columns) from every
    molecule's nearest pixel: the background that no molecule's light reaches."""
    keep = np.ones(shape, bool)
    _, rows, cols = molecule_pixels(molecules)
    for r, c in zip(rows, cols, strict=True):
        keep[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1] = False
    return keep


__all__ = [
    "MovieOffset",
    "PixelCumulants",
    "away_from",
    "first_adu_per_photon",
    "offset_from_cumulants",
    "pixel_cumulants",
]
