"""Camera calibration from calibration frames: the offset and the readout noise from dark
frames, and an sCMOS camera's per-pixel gain from flat fields.

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

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from bayespsf.cameras import SCMOS
from bayespsf.errors import BayespsfInputError
from bayespsf.movie import Movie
from bayespsf.movie.extract import frame_span, open_movie
from bayespsf.movie.project import mean_and_variance


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
    offset_map, variance_map : numpy.ndarray, shape (h, w)
        Per-pixel mean (ADU) and variance (ADU^2, ``ddof=1``).
    frames : int
        Dark frames used.

    See Also
    --------
    dark_calibration : makes one.
    """

    offset: float
    offset_se: float
    readout_sd: float
    readout_sd_se: float
    offset_map: np.ndarray
    variance_map: np.ndarray
    frames: int

    def describe(self) -> str:
        """One line: the offset and readout with their standard errors, and the frames.

        Returns
        -------
        str
        """
        return (
            f"offset {self.offset:.6g} +- {self.offset_se:.2g} ADU and readout "
            f"{self.readout_sd:.6g} +- {self.readout_sd_se:.2g} ADU from {self.frames} dark frames"
        )

    def camera_table(self, e_per_adu: float) -> dict:
        """The ``[camera]`` entries this calibration gives: ``offset`` (ADU) and
        ``readout_sd`` in electrons (the ADU SD times ``e_per_adu``).

        Parameters
        ----------
        e_per_adu : float
            Electrons per ADU, to give the readout SD in electrons.

        Returns
        -------
        dict
            ``offset`` and ``readout_sd``.
        """
        if not np.isfinite(e_per_adu) or e_per_adu <= 0:
            raise BayespsfInputError(
                f"e_per_adu must be a number > 0 (the camera's electrons per ADU; "
                f"--e-per-adu), got {e_per_adu!r}"
            )
        return {"offset": self.offset, "readout_sd": self.readout_sd * float(e_per_adu)}


def dark_calibration(
    movie: Movie | str | Path, frames: slice | range | None = None
) -> DarkCalibration:
    """The offset and readout noise of a camera from its dark frames.

    Parameters
    ----------
    movie : Movie or path
        Frames recorded without light, in counts (ADU): a ``Movie``, or a path that
        ``read_movie`` opens.
    frames : slice or range, optional
        Consecutive frames to use (default all); at least 2 (20 or more are advised).

    Returns
    -------
    DarkCalibration
        The scalar ``offset`` and ``readout_sd`` (ADU) with their standard errors, and the
        per-pixel ``offset_map`` (ADU) and ``variance_map`` (ADU^2).

    Raises
    ------
    BayespsfInputError
        Fewer than 2 frames, frames outside the movie, a movie that cannot be read, dark
        frames whose median pixel holds the same count in every frame (a readout of 0 ADU),
        or frames that hold light (their brighter pixels vary more: ``LIGHT_RATIO``).

    See Also
    --------
    flat_field_gain : an sCMOS camera's per-pixel gain, given this.
    DarkCalibration.camera_table : the ``[camera]`` entries of a camera file.
    bayespsf.calibrate_camera : the whole camera file from a movie.

    Notes
    -----
    The module docstring states the estimates: per pixel, the mean over frames (the offset)
    and the variance (the readout variance); the camera's offset is their 10%-trimmed mean
    over pixels, and its readout SD the median per-pixel variance corrected by the median of
    ``chi2_k / k`` (``k`` = frames - 1). An ADC that rounds to whole ADU adds 1/12 ADU^2 to
    every variance; it is reported, not removed.

    A readout of 0 is an error, not a result: the cameras these frames calibrate (EMCCD,
    sCMOS, CCD: ``calibrate_camera``'s kinds) all add readout noise, and their ADC's rounding
    adds 1/12 ADU^2 more, so dark frames whose median pixel never changes are not raw dark
    frames of a working camera (an average, one frame repeated, a processed or clipped image).
    Only an ideal photon counter (``bayespsf.cameras.Photon``) reads no noise, and it needs no
    dark frames.

    Examples
    --------
    The ``paper-movie`` scene's EMCCD: offset 100 ADU, readout 50 e- at 12 e- per ADU
    (4.17 ADU; 4.18 with the ADC's rounding), 20 dark frames of 64 x 64 pixels:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> from bayespsf.calibration import dark_calibration
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 2, "height": 64, "width": 64, "molecules": 1, "dark_frames": 20}
    ... )
    >>> made = bayespsf.simulate_movie(scene, seed=4, out=Path(tempfile.mkdtemp()) / "m")
    >>> dark = dark_calibration(made.files["dark"])
    >>> print(dark.describe())
    offset 99.9997 +- 0.015 ADU and readout 4.18894 +- 0.013 ADU from 20 dark frames
    >>> round(dark.camera_table(e_per_adu=12.0)["readout_sd"], 1)  # electrons
    50.3
    """
    movie = open_movie(movie)
    span = frame_span(movie, frames)
    count = len(span)
    if count < 2:
        raise BayespsfInputError(
            f"dark frames: {count} frame(s); a variance needs at least 2 (use 20 or more; --dark)"
        )
    mean, variance = mean_and_variance(movie, frames=span)
    # a pixel's sample variance is sigma^2 chi2_k / k (k = frames - 1): its median is
    # sigma^2 times the chi2 median over k, which the median over pixels must be divided by
    dof = count - 1
    readout = float(np.sqrt(np.median(variance) / (stats.chi2.median(dof) / dof)))
    if not readout > 0:
        raise BayespsfInputError(_no_variance(variance, count))
    lit = _light(movie, span)
    if lit:
        raise BayespsfInputError(lit)
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


LIGHT_RATIO = 1.5  # dark frames: the brightest tenth's median spread over the dimmest's
LIGHT_CROP = 128  # ... judged on the central crop of at most this many pixels a side


def _light(movie, span: range) -> str:
    """Why frames whose pixels' spread rises with their level hold light (a photon transfer
    slope; in dark frames the readout noise is the same whatever a pixel's offset), or "".

    Per pixel of the central crop, the mean and SD over frames with a tenth of the frames cut
    at each end (its level and spread): robust to an EMCCD's clock-induced charge, rare
    amplified electrons that raise a pixel's mean and variance in dark frames, and not
    quantised as a median of whole ADU would be. The median spread of the
    brightest tenth of pixels (by level) over that of the dimmest tenth: 0.99-1.21 on
    simulated dark frames (EMCCD with clock-induced charge up to 0.05 per pixel and frame,
    5-100 frames; sCMOS with per-pixel offsets and readout SDs of 0.6-3 ADU), 2.4-2.5 on
    movies of molecules over an uneven background; judged where each tenth holds 100 pixels
    and there are 5 frames. Frames lit evenly everywhere are not caught (paper-movie's, 3
    photons per pixel: 1.46-1.49): every pixel's spread is then the light's."""
    if len(span) < 5:
        return ""
    h, w = movie.shape[1:]
    r0, c0 = max(0, (h - LIGHT_CROP) // 2), max(0, (w - LIGHT_CROP) // 2)
    rows = slice(r0, r0 + LIGHT_CROP)
    crop = movie.frames(span.start, span.stop, rows=rows)[:, :, c0 : c0 + LIGHT_CROP]
    crop = crop.astype(np.float64).reshape(len(span), -1)
    if crop.shape[1] < 1000:
        return ""
    crop.sort(axis=0)  # per pixel, the frames' values in order: a tenth cut at each end
    cut = max(1, len(span) // 10)
    kept = crop[cut:-cut]
    level, spread = kept.mean(axis=0), kept.std(axis=0)
    low, high = np.quantile(level, [0.1, 0.9])
    dim, bright = np.median(spread[level <= low]), np.median(spread[level >= high])
    if not bright > LIGHT_RATIO * dim:
        return ""
    rise = np.median(level[level >= high]) - np.median(level[level <= low])
    return (
        f"dark frames: they hold light; the brightest tenth of their pixels (by level, "
        f"{rise:.3g} ADU above the dimmest) spread {bright / dim:.2g} times as much as the "
        "dimmest, where the readout noise of dark frames is the same whatever a pixel's "
        "offset. Give frames recorded with no light on the camera (--dark)"
    )


def _no_variance(variance: np.ndarray, count: int) -> str:
    """Why dark frames whose median pixel never changes are not a camera's dark frames."""
    constant = int(np.count_nonzero(variance == 0))
    return (
        f"dark frames: {constant} of {variance.size} pixels hold the same count in all {count} "
        "frames, so the readout noise reads 0 ADU; the dark frames of a working camera vary "
        "from frame to frame by its readout noise. Check "
        "that the dark frames (--dark) are the camera's raw frames, not an average, a copy of "
        "one frame, a background-subtracted or clipped image; a readout far below 1 ADU shows "
        "only over more frames (give 20 or more)"
    )


@dataclass(frozen=True)
class FlatFieldGain:
    """Per-pixel gain of an sCMOS camera from flat fields (``flat_field_gain``).

    Attributes
    ----------
    gain_map, gain_se_map : numpy.ndarray
        ADU per photoelectron of every pixel, and its standard error.
    levels : int
        Illumination levels used.
    frames : tuple of int
        Frames per level.

    See Also
    --------
    flat_field_gain : makes one.
    """

    gain_map: np.ndarray
    gain_se_map: np.ndarray
    levels: int
    frames: tuple[int, ...]

    def camera(self, dark: DarkCalibration, likelihood: str = "exact") -> SCMOS:
        """The per-pixel ``SCMOS`` of these gains and ``dark``'s offset and variance maps.

        Each pixel's variance is that of its own dark frames: for normal readout noise its
        relative standard error is ``sqrt(2 / (frames - 1))``, 100% from 3 frames, 32% from
        21 and 10% from 201, and an error in it is an error in the likelihood's pixel weights.
        Per-pixel maps want hundreds of dark frames or more; the scalar camera
        (``DarkCalibration.camera_table``) pools the pixels and needs far fewer.

        Parameters
        ----------
        dark : DarkCalibration
            The offset and readout maps.
        likelihood : str, optional
            The sCMOS likelihood tier.

        Returns
        -------
        SCMOS
        """
        return SCMOS(self.gain_map, dark.offset_map, dark.variance_map, likelihood=likelihood)


def flat_field_gain(flats: Iterable[Movie | str | Path], dark: DarkCalibration) -> FlatFieldGain:
    """Each pixel's gain of an sCMOS camera from flat fields at one or more light levels.

    Parameters
    ----------
    flats : sequence of Movie or path
        One movie per illumination level, each of the camera's frames (ADU) under uniform
        light, at least 2 frames each, of the dark frames' shape.
    dark : DarkCalibration
        The same camera's dark frames (``dark_calibration``).

    Returns
    -------
    FlatFieldGain
        ``gain_map`` (ADU per photoelectron) and ``gain_se_map`` of every pixel (NaN for a
        stuck pixel or a slope that is not positive), the levels and frames used.

    Raises
    ------
    BayespsfInputError
        ``dark`` not a ``DarkCalibration``, no flat field, frames of another shape, fewer than
        2 frames in a level, or a level within 5 SEs of the dark offset (no light).

    See Also
    --------
    dark_calibration : the offset and variance maps.
    FlatFieldGain.camera : the per-pixel ``SCMOS`` camera.

    Notes
    -----
    Huang et al., Nat. Methods 10, 653 (2013), supplement: a pixel's variance over frames,
    less its dark variance, grows with its mean above the dark offset as ``g (mean - offset)``
    (Poisson photoelectrons times ``g`` ADU each). Per pixel, ``g`` is the weighted least
    squares slope through the dark point, ``sum w x y / sum w x^2`` with ``x`` = mean - offset
    and ``y`` = variance - dark variance of each level. The weights are ``1 / Var(y) = (K - 1)
    / (2 v^2)`` (K frames; normal counts) with ``v`` the *fitted* variance ``g x + dark
    variance``, iterated from equal weights: weights from each level's own sample variance
    would favour the levels whose variance came out low, and bias ``g`` low. The standard
    error adds to ``1 / sqrt(sum w x^2)`` the dark variance's own error, common to every level
    (``sum w x / sum w x^2`` times its SD ``v_dark sqrt(2 / (K_dark - 1))``). A pixel that does
    not vary in some level (stuck, dead), or whose slope is not positive, gets NaN; a level
    whose pixels lie within 5 SEs of the dark offset (no light) is an error.

    References
    ----------
    .. [1] F. Huang et al., "Video-rate nanoscopy using sCMOS camera-specific single-molecule
       localization algorithms", Nat. Methods 10, 653 (2013).
    """
    if not isinstance(dark, DarkCalibration):
        raise BayespsfInputError(f"dark must be a DarkCalibration (dark_calibration), got {dark!r}")
    if isinstance(flats, str | bytes) or not hasattr(flats, "__iter__"):
        raise BayespsfInputError("flats must be a sequence of movies, one per illumination level")
    flats = [open_movie(f) for f in flats]
    if not flats:
        raise BayespsfInputError("flats: no flat-field movie given")
    xs, ys, counts = [], [], []
    for k, movie in enumerate(flats):
        if movie.shape[1:] != dark.offset_map.shape:
            raise BayespsfInputError(
                f"flats[{k}]: frames {movie.shape[1:]}, the dark frames' {dark.offset_map.shape}"
            )
        count = len(movie)
        if count < 2:
            raise BayespsfInputError(f"flats[{k}]: {count} frame(s); a variance needs 2 or more")
        counts.append(count)
        mean, variance = mean_and_variance(movie)
        above = float(np.median(mean - dark.offset_map))
        noise = float(np.sqrt(np.median(dark.variance_map) / count))
        if not above > 5 * noise:
            raise BayespsfInputError(
                f"flats[{k}]: its pixels lie {above:.3g} ADU above the dark offset, within 5 "
                f"SEs ({noise:.2g} ADU) of it: no light to calibrate against"
            )
        xs.append(mean - dark.offset_map)
        ys.append(variance - dark.variance_map)
    x, y = np.stack(xs), np.stack(ys)
    k = np.asarray(counts, dtype=float).reshape(-1, *([1] * dark.offset_map.ndim))
    w = np.ones_like(x)
    with np.errstate(divide="ignore", invalid="ignore"):  # a stuck pixel: NaN, below
        for _ in range(3):  # equal weights, then those of the fitted variances, twice
            sxx = (w * x * x).sum(axis=0)
            gain = (w * x * y).sum(axis=0) / sxx
            w = (k - 1) / (2 * (gain * x + dark.variance_map) ** 2)
        sxx, sx = (w * x * x).sum(axis=0), (w * x).sum(axis=0)
        gain = (w * x * y).sum(axis=0) / sxx
        dark_sd = dark.variance_map * np.sqrt(2 / (dark.frames - 1))
        se = np.sqrt(1 / sxx + (sx / sxx * dark_sd) ** 2)
    stuck = np.any(y + dark.variance_map == 0, axis=0) | ~(gain > 0) | ~np.isfinite(se)
    gain, se = np.where(stuck, np.nan, gain), np.where(stuck, np.nan, se)
    return FlatFieldGain(gain, se, len(flats), tuple(counts))


__all__ = ["DarkCalibration", "FlatFieldGain", "dark_calibration", "flat_field_gain"]
