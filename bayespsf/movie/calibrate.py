"""Camera calibration from a movie's dark frames: the offset and the readout noise (issue 13,
item 2, first part).

Frames recorded without light hold the camera's offset plus its readout noise (and, on an
EMCCD, clock-induced charge, which this estimate counts as noise). Per pixel, the mean over
frames is that pixel's offset and the variance its readout variance in ADU^2 (an sCMOS camera's
maps); the camera's scalar offset and readout SD are robust averages over pixels (a trimmed
mean and a median), insensitive to hot pixels. Both are computed with
``bayespsf.movie.project`` (mean and SD streamed over blocks of frames), so the dark movie is
never in memory whole. An ADC that rounds to whole ADU adds 1/12
ADU^2 to every variance (the rounding error of a uniform quantiser, Widrow & Kollar,
Quantization Noise (2008), ch. 4); it is reported, not removed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from bayespsf.errors import BayespsfInputError
from bayespsf.movie.extract import frame_span, open_movie
from bayespsf.movie.project import project


@dataclass(frozen=True)
class DarkCalibration:
    """Offset and readout noise from dark frames.

    Attributes
    ----------
    offset : float
        The 10%-trimmed mean over pixels of each pixel's mean, ADU: robust to hot pixels, and
        not tied to the 1/frames grid of whole-ADU means as their median is.
    offset_se : float
        Its standard error for normal data: 1.03 (the 10%-trimmed mean's efficiency, 0.94,
        Huber & Ronchetti, Robust Statistics (2009), table 3.1) times the readout SD over the
        square root of the number of pixel values used.
    readout_sd : float
        The readout SD in ADU: the square root of the median per-pixel variance divided by
        the median of ``chi2_k / k`` (``k`` = frames - 1), which a pixel's sample variance
        follows for normal noise (unbiased for normal pixels, robust to hot ones).
    readout_sd_se : float
        Its standard error for normal data, ``1.2533 * readout_sd / sqrt(2 n)``, with ``n``
        the pixels' degrees of freedom.
    offset_map, variance_map : numpy.ndarray
        Per-pixel mean (ADU) and variance (ADU^2, ``ddof=1``).
    frames : int
    """

    offset: float
    offset_se: float
    readout_sd: float
    readout_sd_se: float
    offset_map: np.ndarray
    variance_map: np.ndarray
    frames: int

    def describe(self) -> str:
        return (
            f"offset {self.offset:.6g} +- {self.offset_se:.2g} ADU and readout "
            f"{self.readout_sd:.6g} +- {self.readout_sd_se:.2g} ADU from {self.frames} dark frames"
        )

    def camera_table(self, e_per_adu: float) -> dict:
        """The ``[camera]`` entries this calibration gives: ``offset`` (ADU) and
        ``readout_sd`` in electrons (the ADU SD times ``e_per_adu``)."""
        if not np.isfinite(e_per_adu) or e_per_adu <= 0:
            raise BayespsfInputError(f"e_per_adu must be a number > 0, got {e_per_adu!r}")
        return {"offset": self.offset, "readout_sd": self.readout_sd * float(e_per_adu)}


def dark_calibration(movie, frames=None) -> DarkCalibration:
    """The offset and readout noise of a camera from its dark frames (``movie``: a ``Movie``,
    a path, or frames as ``read_movie`` opens them; ``frames``: a slice or range of them)."""
    movie = open_movie(movie)
    span = frame_span(movie, frames)
    count = len(span)
    if count < 2:
        raise BayespsfInputError(
            f"dark frames: {count} frame(s); a variance needs at least 2 (use 20 or more)"
        )
    mean = project(movie, "mean", frames=span)
    variance = project(movie, "std", frames=span) ** 2 * count / (count - 1)
    # a pixel's sample variance is sigma^2 chi2_k / k (k = frames - 1): its median is
    # sigma^2 times the chi2 median over k, which the median over pixels must be divided by
    dof = count - 1
    readout = float(np.sqrt(np.median(variance) / (stats.chi2.median(dof) / dof)))
    pixels = mean.size
    return DarkCalibration(
        offset=float(stats.trim_mean(mean, 0.1, axis=None)),
        offset_se=float(1.03 * readout / np.sqrt(pixels * count)),
        readout_sd=readout,
        readout_sd_se=float(1.2533 * readout / np.sqrt(2 * pixels * (count - 1))),
        offset_map=mean,
        variance_map=variance,
        frames=count,
    )


__all__ = ["DarkCalibration", "dark_calibration"]
