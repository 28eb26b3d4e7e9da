"""Photon gain calibration from a movie of one immobile molecule (the paper's Eq. photonConv).

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), "Photon gain calibration": with
``<N_i*>`` and ``sigma_i*^2`` the mean and variance over frames of pixel i's counts, and
``<b*>`` and ``sigma_b*^2`` those of background pixels,

    M = (sigma_i*^2 - sigma_b*^2) / (2 (<N_i*> - <b*>))        (Eq. photonConv)

is the camera's ADU per photon (the EM register's excess noise makes the variance of the
signal 2 M^2 N_i). It is averaged over the nine centre pixels, or taken from the centre pixel
alone when the signal-to-noise ratio ``I0 / sqrt(I0 + sigma_b^2)`` (photons) is below 3. It
assumes Poisson photon statistics without frame-to-frame changes of N, and a background that is
the same in every pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayespsf._checks import finite_array
from bayespsf.errors import BayespsfInputError


@dataclass(frozen=True)
class GainCalibration:
    """Result of ``calibrate_gain`` (ADU per photon and what it was computed from)."""

    adu_per_photon: float
    pixel_estimates: np.ndarray  # Eq. photonConv of each pixel used
    background_mean: float  # <b*>, ADU
    background_variance: float  # sigma_b*^2, ADU^2
    snr: float  # I0 / sqrt(I0 + sigma_b^2) in photons, from the centre pixel's estimate
    centre: tuple[int, int]  # row, column of the centre pixel


def calibrate_gain(movie, snr_threshold: float = 3.0) -> GainCalibration:
    """ADU per photon from a movie ``(frames, roi, roi)`` of one immobile molecule.

    Background pixels are the ROI's border; the centre is the brightest pixel of the
    background-subtracted mean image (kept one pixel from the border).
    """
    m = finite_array("movie", movie)
    if m.ndim != 3 or m.shape[0] < 3 or min(m.shape[1:]) < 5:
        raise BayespsfInputError(
            f"movie must have shape (frames >= 3, rows >= 5, columns >= 5), got {m.shape}"
        )
    mean = m.mean(axis=0)
    var = m.var(axis=0, ddof=1)
    border = np.ones(mean.shape, bool)
    border[1:-1, 1:-1] = False
    b_mean, b_var = mean[border].mean(), var[border].mean()
    inner = np.where(border, -np.inf, mean)
    row, col = np.unravel_index(np.argmax(inner), mean.shape)
    row, col = int(np.clip(row, 1, mean.shape[0] - 2)), int(np.clip(col, 1, mean.shape[1] - 2))

    def photon_conv(r, c):
        signal = mean[r, c] - b_mean
        if signal <= 0:
            raise BayespsfInputError("movie: the centre pixel is not brighter than the background")
        return (var[r, c] - b_var) / (2.0 * signal)

    centre_m = photon_conv(row, col)
    i0 = (mean[row, col] - b_mean) / centre_m
    snr = i0 / np.sqrt(i0 + b_var / centre_m**2)
    if snr > snr_threshold:
        estimates = np.array(
            [photon_conv(row + dr, col + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
        )
    else:
        estimates = np.array([centre_m])
    return GainCalibration(
        float(estimates.mean()), estimates, float(b_mean), float(b_var), float(snr), (row, col)
    )
