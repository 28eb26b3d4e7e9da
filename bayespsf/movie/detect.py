"""Detecting molecules: a likelihood-ratio test of "spot + background"
against "background only" at every pixel, with a threshold set by the expected number of false
detections per image.

The test. Under Gaussian noise of known per-pixel variance ``v``, an image ``x`` (photons,
background removed) either holds only noise or a spot ``N g`` of known shape ``g`` (the
pixel-integrated Gaussian of SD ``psf_sd``, ``bayespsf.psf.expected_counts``) and unknown
amplitude ``N >= 0``. The generalised likelihood-ratio test replaces ``N`` by its
maximum-likelihood estimate ``N̂ = Σ g x / v / Σ g² / v`` and reduces to the (prewhitened)
matched filter ``T = Σ g x / v / sqrt(Σ g² / v)``, which is N(0, 1) under the null and
N(N sqrt(Σ g² / v), 1) with a spot: Kay, *Fundamentals of Statistical Signal Processing,
Vol. II: Detection Theory* (Prentice Hall, 1998), sec. 4.3 (matched filter and its detection
probability ``Q(Q⁻¹(P_FA) - sqrt(d²))``), sec. 4.5 (generalised matched filter for unequal
variances) and sec. 7.4 (unknown amplitude: the GLRT). ``T`` is computed at every pixel by
one correlation (``scipy.ndimage.correlate``).

The threshold. With ``n`` pixels, ``t`` is set so that a background pixel's ``T`` exceeds it
with probability ``false_positives / n``: the expected number of background pixels above ``t``
is then ``false_positives`` (linearity of expectation); every false candidate is such a pixel,
so ``false_positives`` bounds the expected number of false candidates per image, and the
probability of any (Bonferroni). Given the camera (``detect_movie``, ``detect_frames``: a mean
projection or single frames, noise from the camera law), ``t`` comes from the law of ``T``
under that camera: the saddlepoint approximation of a weighted sum of EMCCD or Poisson pixels
(``_noise.null_thresholds``), at each pixel's background. Without it, ``t = Φ⁻¹(1 -
false_positives / n)``, the central-limit approximation, which skewed counts (EMCCD, a few
photons per pixel, single frames) exceed in the far tail: one 4096 × 4096 EMCCD frame at 3
photons per pixel gave 9 false candidates against a stated 0.01 (docs/movies.md).

The background. ``b`` is local: at each pixel, a least-squares quartic surface of the pixels
around it away from the spots (``_background``; a window of three ROI sides, and at least
three sides of the spot's own ROI, so that a frame detected with the fitted window as its ROI
still gets the quartic), which follows a ramp or an illumination profile (a beam narrower
than the window too) to the image's edge, so that the threshold is set against the
background and the camera law at each pixel's own level; without a camera the noise variance
is estimated pixel by pixel over the same window. With a camera, the variance the
background pixels show beyond the law (a per-pixel offset pattern, which a projection keeps
whole) is added to the law as a Gaussian term (``_background.fixed_pattern_variance``).

Neighbours. Every candidate is a source of light, its amplitude ``N̂`` spread as the spot
(``geometry.window_light``). One is ``rejected: neighbour`` when another puts more than one SD
of the summed noise of its ``fit`` x ``fit`` window into that window (each pixel's variance with
its own spot on it), or when masking its neighbours' light out of its periphery leaves fewer
pixels than the photon aperture's (``_peaks.crowded``, ``bayespsf.movie.geometry``). The rule
holds whoever is brighter: a faint candidate that barely touches a bright spot's window leaves
it, a bright one takes a faint one's place, and of two that overlap both go. ``min_distance``
replaces it by the fixed rule: both of any pair closer than that in rows or in columns go
(``min_distance=roi``: the paper's isolated molecules, ROIs that never overlap).

Flags. ``saturated`` counts the pixels of the spot's template window at the ADC's full scale
(the camera's declared ``saturation`` or an integer type's largest value) in some frame;
``elongated`` marks a spot whose second moments reject one round spot
(``_peaks.elongation``): two molecules closer than the detector resolves (1-2 pixels: one
candidate), a moving or an astigmatic spot. Flagged candidates keep their status; a
projection, a frame or counts that cannot be a camera's (below its offset, constant, mostly
saturated) are refused with the numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy import stats

from bayespsf import psf
from bayespsf._validate import finite_array, scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.movie._background import background_and_noise
from bayespsf.movie._metadata import check_pixel_size, resolve_pixel_size
from bayespsf.movie._noise import (
    at_type_maximum,
    camera_noise_variance,
    check_background,
    check_offset,
    check_signal,
    estimate_noise_variance,
    matched_filter,
    pixel_law,
    saturation_level,
    spot_variance,
    template,
    threshold_map,
)
from bayespsf.movie._peaks import STATUSES, crowded, elongation, find_peaks, saturated_near
from bayespsf.movie.extract import check_sizes, frame_span, open_movie, photon_model
from bayespsf.movie.geometry import geometry_for_psf, min_periphery
from bayespsf.movie.project import project_with_saturation

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from bayespsf.cameras import Camera
    from bayespsf.model import Model
    from bayespsf.movie.read import Movie

__all__ = [
    "COLUMNS",
    "camera_noise_variance",
    "detect",
    "detect_movie",
    "estimate_noise_variance",
]

_NAMES = (
    "molecule x y row col score amplitude background status threshold noise_var noise_source "
    "saturated elongation elongated"
)
COLUMNS = tuple(_NAMES.split())


def detect(
    image: ArrayLike,
    *,
    psf_sd: float,
    pixel_size: float,
    noise_var: float | ArrayLike | None = None,
    background: float | ArrayLike | None = None,
    false_positives: float = 0.01,
    roi: int | None = None,
    fit: int | None = None,
    min_distance: float | None = None,
) -> pd.DataFrame:
    """Candidate molecules in one image (photons): local maxima of the matched-filter score.

    Parameters
    ----------
    image : array_like, shape (h, w)
        In photons: a temporal projection of an immobile-molecule movie, or one frame.
    psf_sd : float
        SD of the spot's Gaussian in nm (> 0); the template is its pixel integral.
    pixel_size : float
        Pixel side in nm (> 0).
    noise_var : float or array_like (h, w), optional
        Noise variance per pixel in photons² (``camera_noise_variance`` gives it from the
        camera law); by default estimated from the image pixel by pixel, from the differences
        of adjacent pixels away from spots over the background's window.
    background : float or array_like (h, w), optional
        Background in photons per pixel; by default the least-squares quartic surface of the
        pixels away from spots over a window of three ROI sides around each pixel, and at
        least three sides of the spot's own ROI (``geometry_for_psf``; 63 pixels for a 130 nm
        spot on 100 nm pixels), whatever ``roi`` is given.
    false_positives : float, default 0.01
        Expected number of background pixels above the threshold per image (> 0, below the
        number of pixels): a bound on the expected number of false candidates per image.
    roi, fit : int, optional
        Odd sides (pixels) of the ROI to be cut around each molecule and of its fitted centre;
        default ``geometry_for_psf(psf_sd, pixel_size)``'s (25 and 15 for the paper's 120 nm
        spot on 79 nm pixels; ``fit`` at most ``roi``). A candidate whose ROI would cross the
        image's edge is ``rejected: edge``.
    min_distance : float, optional
        The fixed rule instead of the light rule (module docstring): two candidates whose peak
        pixels are closer than this in rows or in columns (Chebyshev distance, pixels) are
        both ``rejected: neighbour`` (``min_distance=roi``: the paper's isolated molecules,
        ROIs that never overlap).

    Returns
    -------
    pandas.DataFrame
        One row per candidate, in image order, with the columns ``COLUMNS``:

        - ``molecule``: id, from 0;
        - ``x``, ``y``: sub-pixel position in camera pixels, picasso's convention (column
          ``j``'s centre is ``x = j``);
        - ``row``, ``col``: the peak pixel;
        - ``score``: the matched-filter statistic ``T`` at the peak;
        - ``amplitude``: ``N̂``, photons of a spot centred on the peak pixel;
        - ``background``: photons per pixel at the peak;
        - ``status``: one of ``STATUSES`` (``accepted``, ``rejected: edge``,
          ``rejected: neighbour``);
        - ``threshold``: ``t`` at the peak (the same in every row without a camera);
        - ``noise_var``: noise variance at the peak, photons²;
        - ``noise_source``: ``given``, ``camera`` or ``estimated``;
        - ``saturated``: pixels of the spot's window at the ADC's full scale (in an integer
          image, its type's maximum);
        - ``elongation``: major over minor SD of the spot's second moments (1: round);
        - ``elongated``: True where they reject one round spot (p < 0.001): e.g. two
          molecules 1-2 pixels apart, seen as one candidate.

        ``attrs["detection"]`` holds the settings, the number of pixels above the threshold,
        the ``null`` law of the threshold, the background's source, the ``fixed_pattern_var``
        added to a camera law (photons², 0 without one), the counts by status and the number
        of ``saturated_pixels``.

    Raises
    ------
    BayespsfInputError
        An image that is not 2-D of at least 3 x 3 finite values, constant (named: all zero,
        saturated), mostly saturated or without noise; a ``noise_var`` or ``background`` of
        the wrong shape, a noise variance <= 0, a background below 0 beyond the noise; a
        ``false_positives`` outside (0, number of pixels); a bad ``roi`` or ``fit``; a
        ``pixel_size`` outside 1 nm to 10 µm.

    See Also
    --------
    detect_movie : on a temporal projection of a movie in ADU.
    detect_frames : on every frame of a movie (blinking data).
    camera_noise_variance : the noise variance from a camera law.
    find_molecules : detection, traces and selection together.

    Notes
    -----
    The test (Kay, vol. II, secs. 4.3, 4.5 and 7.4), its threshold, the neighbour rule and
    the flags are stated in the module docstring; here ``T`` is taken as N(0, 1) under the
    null, ``t = Φ⁻¹(1 - false_positives / n)`` over ``n`` pixels.

    Positions are refined by fitting a Gaussian through the score at the peak pixel and its
    two neighbours along each axis (a parabola through ``log T``; a parabola through ``T``
    where a neighbour's score is not positive).

    Examples
    --------
    One spot of 2 000 photons on a background of 10 photons per pixel, Poisson noise:

    >>> import numpy as np
    >>> from bayespsf import psf
    >>> from bayespsf.movie import detect
    >>> image = np.full((64, 64), 10.0)
    >>> spot = psf.expected_counts([0.0, 0.0, 120.0, 120.0, 2000.0, 0.0], 15, 79.0)
    >>> image[25:40, 30:45] += spot  # centred on row 32, column 37
    >>> counts = np.random.default_rng(0).poisson(image)
    >>> found = detect(counts, psf_sd=120.0, pixel_size=79.0, roi=15)
    >>> found[["molecule", "x", "y", "status"]].round(1)
       molecule     x     y    status
    0         0  37.0  32.0  accepted
    """
    options = (noise_var, background, false_positives, roi, fit, min_distance)
    return _detect(image, psf_sd, pixel_size, *options)


def _detect(
    image,
    psf_sd,
    pixel_size,
    noise_var,
    background,
    false_positives=0.01,
    roi=None,
    fit=None,
    min_distance=None,
    *,
    law=None,
    saturated=None,
    what="the image",
) -> pd.DataFrame:
    """``detect``; ``law`` (a ``PixelLaw``): the threshold from the camera law's exact tail;
    ``saturated``: pixels at the ADC's full scale in some frame (default: in an integer image,
    those at its type's maximum); ``what``: the image's name in errors."""
    if saturated is None:
        saturated = at_type_maximum(image)
    image = finite_array("image", image)
    if image.ndim != 2 or min(image.shape) < 3:
        raise BayespsfInputError(f"image must be 2-D (h, w) with h, w >= 3, got {image.shape}")
    check_pixel_size(pixel_size, "pixel_size=")
    spot = template(psf_sd, pixel_size, image.shape)
    sides = geometry_for_psf(psf_sd, pixel_size)
    roi = sides[0] if roi is None else psf.check_geometry(roi, pixel_size)[0]
    fit = min(sides[1], roi) if fit is None else fit
    check_sizes(roi, fit)
    window = 3 * max(roi, sides[0])  # the background's: three ROI sides, at least the spot's
    if min_distance is not None:
        min_distance = scalar_in_range("min_distance", min_distance, 0.0)
    fp = scalar_in_range("false_positives", false_positives, 0.0, image.size, low_inclusive=False)
    if fp >= image.size:
        raise BayespsfInputError(f"false_positives must be below the {image.size} pixels")
    fp_p = fp / image.size  # per pixel
    gaussian = float(stats.norm.isf(fp_p))
    check_signal(image, saturated, "photons", what)
    estimate = None
    if noise_var is None or background is None:
        estimate = estimate_noise_variance(image)
        if estimate <= 0:
            raise BayespsfInputError(
                "the image has no noise (adjacent pixels are equal): give noise_var, or an "
                "image of counts with their noise"
            )
    # pixels left out of the estimates: those near a score above the threshold (the law's)
    level = gaussian if law is None else threshold_map(law, spot, np.median(image), fp_p)
    found = background_and_noise(image, spot, window, level, estimate, background, noise_var, law)
    back, back_source, var, source, law, pattern = found
    if np.any(var <= 0):
        raise BayespsfInputError("noise_var must be > 0 photons²")
    if law is None:  # the image's own noise, else five readout SDs of one frame (ADU check)
        tolerance = 3.0 * float(np.sqrt(np.median(var)))
    else:
        tolerance = 5.0 * float(np.sqrt(law.readout_var)) + 1e-9
    check_background(back, tolerance, back_source)
    threshold = gaussian if law is None else threshold_map(law, spot, back, fp_p)
    score, amplitude = matched_filter(image - back, var, spot)
    peaks = rows, cols, status, dy, dx = find_peaks(score, threshold, roi, min_distance)
    variance = spot_variance(law, var, back)

    def at(values):  # a map's (or a number's) values at the peaks
        return np.broadcast_to(values, image.shape)[rows, cols]

    if min_distance is None:  # the light rule
        sides = (psf_sd / pixel_size, roi, fit, min_periphery(psf_sd, pixel_size))
        status[crowded(peaks, at(amplitude), variance, at(var), *sides)] = STATUSES[2]
    shape = elongation(image - back, variance, rows, cols, dy, dx, psf_sd, pixel_size)
    threshold = np.broadcast_to(threshold, image.shape)

    values = (np.arange(rows.size), cols + dx, rows + dy, rows, cols, at(score), at(amplitude))
    values += (at(back), status, at(threshold), at(var), source)
    values += (saturated_near(saturated, rows, cols, len(spot[0]) // 2), *shape)
    table = pd.DataFrame(dict(zip(COLUMNS, values, strict=True)))
    table.attrs["detection"] = {
        "psf_sd": float(psf_sd),
        "pixel_size": float(pixel_size),
        "false_positives": fp,
        "pixels": int(image.size),
        "pixels_above": int(np.count_nonzero(score > threshold)),
        "threshold": float(np.median(threshold)),
        "null": "gaussian" if law is None else "camera law (saddlepoint)",
        "noise_source": source,
        "noise_var": float(np.median(var)),
        "fixed_pattern_var": pattern,
        "background_source": back_source,
        "roi": roi,
        "fit": fit,
        "min_distance": None if min_distance is None else float(min_distance),
        "counts": {s: int(np.count_nonzero(status == s)) for s in STATUSES},
        "saturated_pixels": 0 if saturated is None else int(np.count_nonzero(saturated)),
    }
    return table


def detect_movie(
    movie: Movie | str | Path,
    *,
    psf_sd: float,
    pixel_size: float | None = None,
    camera: Camera | Model | None = None,
    projection: str = "mean",
    frames: slice | range | None = None,
    **options,
) -> pd.DataFrame:
    """Candidate molecules of an immobile-molecule movie, detected on a temporal projection.

    Parameters
    ----------
    movie : Movie or path
        From ``read_movie`` (or a path it opens); counts in ADU.
    psf_sd : float
        SD of the spot's Gaussian in nm, as ``detect``.
    pixel_size : float, optional
        Pixel side in nm; defaults to the Model's, else the movie's metadata.
    camera : Camera or Model, optional
        Converts counts (ADU) to photons (``Model.to_photons``) and, for a mean projection,
        gives the noise variance from the camera law at the background level divided by the
        number of frames (``camera_noise_variance``) and the threshold from its exact tail.
        Without it the movie is taken to be in photons and the noise is estimated from the
        projection.
    projection : {"mean", "median"}, default "mean"
        The projection (``bayespsf.movie.project``, memory bounded).
    frames : slice or range, optional
        Consecutive frames to project (default all).
    **options
        ``noise_var``, ``background``, ``false_positives``, ``roi``, ``fit``,
        ``min_distance``: as ``detect``.

    Returns
    -------
    pandas.DataFrame
        As ``detect`` (columns ``COLUMNS``); ``attrs["detection"]`` also names the
        ``projection`` and its ``frames`` (first, stop).

    Raises
    ------
    BayespsfInputError
        An unknown ``projection``, frames that are not consecutive frames of the movie, no
        pixel size from the arguments or the movie, counts below the camera's offset beyond
        its readout noise, or any error of ``detect``.

    See Also
    --------
    detect : the test on one image in photons.
    detect_frames : frame by frame instead of on a projection.
    """
    movie = open_movie(movie)
    if projection not in ("mean", "median"):
        raise BayespsfInputError(f"projection must be 'mean' or 'median', got {projection!r}")
    span = frame_span(movie, frames)
    level = saturation_level(movie.dtype, camera)
    image, counts = project_with_saturation(movie, projection, level, frames=span)
    averaged = len(span) if projection == "mean" or len(span) == 1 else None
    what = f"{movie.path}: the {projection} projection of frames {span.start}-{span.stop - 1}"
    mask = None if counts is None else counts > 0
    pixel_size = resolve_pixel_size(pixel_size, camera, movie)
    table = _detect_photons(image, averaged, psf_sd, pixel_size, camera, options, mask, what)
    table.attrs["detection"].update(projection=projection, frames=[span.start, span.stop])
    return table


def _detect_photons(image, frames, psf_sd, pixel_size, camera, options, saturated, what):
    """``detect`` on a frame or projection (``what``) in ADU, ``pixel_size`` resolved
    (``resolve_pixel_size``): checked against the camera (``check_signal``, ``check_offset``),
    converted with ``camera`` (if any), the noise from the camera law over ``frames`` frames
    and the threshold from its exact tail (if a camera, a mean or one frame, and no
    noise_var)."""
    options = {"noise_var": None, "background": None} | options
    law = None
    if camera is not None:
        model = photon_model(camera)
        template(psf_sd, pixel_size, image.shape)  # the spot's size is named first
        check_signal(image, saturated, "ADU", what)
        check_offset(image, model.camera, what)
        image = model.to_photons(image)
        if frames is not None and options["noise_var"] is None:
            options["noise_var"] = lambda back: camera_noise_variance(model, back, frames)
            law = pixel_law(model, frames)
    given = options.pop("noise_var"), options.pop("background")
    return _detect(
        image, psf_sd, pixel_size, *given, **options, law=law, saturated=saturated, what=what
    )
