"""A molecule's windows sized from its spot, and the light that neighbours put into them.

Sizes. The paper cut 25 x 25 pixels around each molecule, fitted the central 15 x 15 and took
the background from the periphery between them (DeSantis, DeCenzo, Li & Wang, Opt. Express 18
(2010), "Data acquisition and selection"; s0 = 120 nm on 79 nm pixels, s0 / a = 1.52).
``geometry_for_psf`` keeps those sizes in units of the spot's SD: the fitted window's
half-side is ``round(K_FIT s0 / a)`` pixels (4.5 s0: 6.84 -> 7 at the paper's) and the cut's
``round(K_ROI s0 / a)`` (8 s0: 12.2 -> 12), each side ``2 half + 1``. 4.5 SDs hold all but
1.4e-5 of the spot's light; the periphery starts there and runs to 8 SDs. Floors: a fitted
window of at least ``MIN_FIT`` (7) pixels (the 3 x 3 core of a narrow spot with a border of two
pixels on each side, where the six-parameter fit measures b) and a periphery at least
``MIN_RING`` (2) pixels wide.

Light. A neighbour of amplitude ``A`` (photons) centred at ``(x, y)`` (camera pixels) puts
``A [Φ((r + w/2 - y)/s) - Φ((r - w/2 - y)/s)] [Φ((c + w/2 - x)/s) - Φ((c - w/2 - x)/s)]``
photons into the ``w`` x ``w`` window centred on pixel ``(r, c)``, ``s = s0 / a``: the sum of
its pixel-integrated Gaussian (``bayespsf.psf.expected_counts``) over the window
(``window_light``). Outside a disc of radius ``R`` around it lies ``A exp(-R² / 2 s²)`` of it,
so the pixels whose centres lie within ``R + √2/2`` cover that disc, and the rest of the image
receives at most that much (``mask_radius``).

The periphery. ``periphery_masks`` leaves out of a molecule's periphery the pixels within
``mask_radius`` of every other candidate whose light there would exceed ``B = sqrt(n v)``, one
SD of the periphery's summed noise (``n`` pixels of noise variance ``v``, the detection image's
at the molecule): what such a candidate leaves in the kept pixels biases the background by at
most ``B / n_kept`` photons per pixel. ``periphery_background`` is the background of the kept
pixels. Detection rejects a molecule whose kept periphery has fewer pixels than
``min_periphery`` (those within 2.5 s0 of the centre: ``traces``' photon aperture), below which
the background's SE would add more to the photons' variance than the aperture's own noise.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import spatial, special

from bayespsf import psf
from bayespsf.errors import BayespsfInputError
from bayespsf.movie._metadata import resolve_pixel_size
from bayespsf.movie.extract import RoiStack, check_sizes, photon_model

K_FIT = 4.5  # fitted window's half-side in SDs of the spot
K_ROI = 8.0  # cut's half-side in SDs of the spot
MIN_FIT = 7  # pixels: the 3 x 3 core and a border of two for b
MIN_RING = 2  # pixels: the periphery's least width
MAX_SIDE = 401  # pixels: the largest ROI a scene declares
APERTURE = 2.5  # SDs: traces' photon aperture, the kept periphery's least size
MIN_SD_PIXELS = 0.1  # the least spot SD in pixels: below it, a unit mistaken (pixels, µm for nm)

__all__ = [
    "K_FIT",
    "K_ROI",
    "MIN_FIT",
    "MIN_RING",
    "geometry_for_psf",
    "mask_radius",
    "min_periphery",
    "movie_geometry",
    "periphery_background",
    "periphery_masks",
    "resolve_geometry",
    "window_light",
]


def _ratio(s0, pixel_size) -> float:
    """``s0 / pixel_size`` (pixels) of a checked ``s0`` and pixel size."""
    where = "--psf-sd on the command line, [emitter] s0x and s0y in a camera file"
    if isinstance(s0, bool) or not isinstance(s0, int | float | np.number):
        raise BayespsfInputError(f"s0 (the spot's SD, nm) must be a number ({where}), got {s0!r}")
    if not (np.isfinite(s0) and s0 > 0):
        raise BayespsfInputError(
            f"s0 (the spot's SD) must be > 0 nm and finite ({where}), got {s0!r}"
        )
    _, a = psf.check_geometry(1, pixel_size)
    if s0 / a < MIN_SD_PIXELS:  # no microscope's spot: a width in pixels or µm taken for nm
        raise BayespsfInputError(
            f"s0 (the spot's SD) is {s0:g} nm, {s0 / a:.3g} of a {a:g} nm pixel: it is in nm "
            f"({where}); a spot of {s0:g} pixels is {s0 * a:g} nm"
        )
    return float(s0) / a


def _half(value: float) -> int:
    """``value`` rounded to the nearest whole number, halves up."""
    return int(np.floor(value + 0.5))


def geometry_for_psf(s0: float, pixel_size: float) -> tuple[int, int]:
    """The cut and fitted window (odd sides, pixels) for a spot of SD ``s0``.

    Parameters
    ----------
    s0 : float
        The spot's SD in nm (> 0).
    pixel_size : float
        Pixel side in nm (> 0).

    Returns
    -------
    roi : int
        ``2 max(round(K_ROI s0 / a), fit half + MIN_RING) + 1``: the cut around a molecule.
    fit : int
        ``2 max(round(K_FIT s0 / a), 3) + 1``: its fitted centre (at least ``MIN_FIT``).

    Raises
    ------
    BayespsfInputError
        ``s0`` or ``pixel_size`` not a finite number > 0, or a cut wider than ``MAX_SIDE``
        (401) pixels (``s0`` or ``pixel_size`` in another unit than nm?).

    Notes
    -----
    ``K_FIT = 4.5`` and ``K_ROI = 8`` give the paper's 15 and 25 at s0 = 120 nm on 79 nm
    pixels (module docstring); halves are rounded up.

    Examples
    --------
    >>> from bayespsf.movie import geometry_for_psf
    >>> geometry_for_psf(120.0, 79.0)
    (25, 15)
    >>> geometry_for_psf(150.0, 160.0)
    (17, 9)
    """
    s = _ratio(s0, pixel_size)
    fit_half = max((MIN_FIT - 1) // 2, _half(K_FIT * s))
    roi_half = max(fit_half + MIN_RING, _half(K_ROI * s))
    if 2 * roi_half + 1 > MAX_SIDE:
        raise BayespsfInputError(
            f"s0 ({s0:g} nm) is {s:.4g} pixels of {pixel_size:g} nm: a cut of "
            f"{2 * roi_half + 1} pixels, wider than {MAX_SIDE}; are s0 and the pixel size both "
            "in nm? (or state roi= and fit=, --roi and --fit)"
        )
    return 2 * roi_half + 1, 2 * fit_half + 1


def resolve_geometry(roi, fit, s0, pixel_size) -> tuple[int | None, int | None, str]:
    """``(roi, fit, source)``: the sides given, the others from ``geometry_for_psf``.

    Parameters
    ----------
    roi, fit : int or None
        Odd sides in pixels; None takes ``geometry_for_psf(s0, pixel_size)``'s.
    s0 : float or None
        The spot's SD in nm; None (to be estimated) leaves a missing side None.
    pixel_size : float
        Pixel side in nm.

    Returns
    -------
    roi, fit : int or None
        The sides (None only where missing and ``s0`` is None).
    source : str
        ``"given"``, ``"from s0"``, ``"roi given, fit from s0"`` or ``"fit given, roi from
        s0"``.

    Raises
    ------
    BayespsfInputError
        A side that is not an odd whole number >= 1, or a ``fit`` above ``roi`` (naming
        which came from s0), or any error of ``geometry_for_psf``.
    """
    check_sizes(roi, fit, missing_ok=True)
    if roi is not None and fit is not None:
        return int(roi), int(fit), "given"
    if roi is None and fit is None:
        source = "from s0"
    else:
        source = "roi given, fit from s0" if fit is None else "fit given, roi from s0"
    if s0 is None:
        return roi, fit, source
    auto_roi, auto_fit = geometry_for_psf(s0, pixel_size)
    roi, fit = (auto_roi if roi is None else int(roi)), (auto_fit if fit is None else int(fit))
    if fit > roi:
        raise BayespsfInputError(
            f"fit ({fit}) must be at most roi ({roi}, {source} = {s0:g} nm on {pixel_size:g} nm "
            "pixels): state both (roi= and fit=, --roi and --fit)"
        )
    return roi, fit, source


def movie_geometry(movie, camera, roi, fit, s0) -> tuple[int | None, int | None, str]:
    """``resolve_geometry`` for a movie: the pixel size from ``camera`` (a Model's) or the
    movie's metadata, looked up only where a side follows ``s0``.

    Parameters
    ----------
    movie : Movie
        The movie (its metadata may hold the pixel size).
    camera : Model or Camera
        The camera, a Model's pixel size first.
    roi, fit, s0
        As ``resolve_geometry``.

    Returns
    -------
    tuple
        As ``resolve_geometry``.
    """
    pixel_size = None
    if s0 is not None and (roi is None or fit is None):
        pixel_size = resolve_pixel_size(None, camera, movie)
    return resolve_geometry(roi, fit, s0, pixel_size)


def window_light(amplitude, y, x, row, col, s: float, side: int) -> np.ndarray:
    """Photons that spots of ``amplitude`` at ``(x, y)`` (camera pixels) put into the ``side``
    x ``side`` windows centred on pixels ``(row, col)``; ``s`` is the spot's SD in pixels
    (module docstring). Arrays broadcast.

    Parameters
    ----------
    amplitude, y, x : array_like
        The spots' photons and centres (camera pixels, picasso's convention).
    row, col : array_like
        The windows' central pixels.
    s : float
        The spot's SD in pixels.
    side : int
        The windows' side in pixels.

    Returns
    -------
    numpy.ndarray
        Photons in each window.
    """
    half = side / 2.0

    def fraction(centre, position):
        offset = np.asarray(centre, dtype=np.float64) - np.asarray(position, dtype=np.float64)
        return special.ndtr((offset + half) / s) - special.ndtr((offset - half) / s)

    return np.asarray(amplitude, dtype=np.float64) * fraction(row, y) * fraction(col, x)


def mask_radius(amplitude, bound, s: float) -> np.ndarray:
    """Radius (pixels) of the pixel centres to leave out around spots of ``amplitude`` so that
    at most ``bound`` photons of each fall elsewhere: ``s sqrt(2 ln(A / bound)) + √2/2`` where
    ``A > bound``, else 0 (module docstring).

    Parameters
    ----------
    amplitude, bound : array_like
        The spots' photons and the light allowed outside the left-out pixels (> 0).
    s : float
        The spot's SD in pixels.

    Returns
    -------
    numpy.ndarray
        The radii, broadcast.
    """
    ratio = np.asarray(amplitude, dtype=np.float64) / np.asarray(bound, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = s * np.sqrt(2.0 * np.log(np.where(ratio > 1.0, ratio, 1.0))) + np.sqrt(0.5)
    return np.where(ratio > 1.0, radius, 0.0)


def min_periphery(s0: float, pixel_size: float) -> int:
    """The fewest periphery pixels a molecule keeps: those whose centres lie within
    ``APERTURE`` (2.5) SDs of the central pixel's centre (module docstring).

    Parameters
    ----------
    s0 : float
        The spot's SD in nm.
    pixel_size : float
        Pixel side in nm.

    Returns
    -------
    int
        The number of pixels (at least 1).
    """
    r = APERTURE * _ratio(s0, pixel_size)
    k = np.arange(-int(np.ceil(r)), int(np.ceil(r)) + 1)
    return max(1, int(np.count_nonzero(k[:, None] ** 2 + k[None, :] ** 2 <= r * r)))


def ring_masks(rows, cols, own, y, x, amplitude, bound, s: float, roi: int, fit: int):
    """Kept periphery pixels ``(n, roi, roi)`` of the molecules on pixels ``(rows, cols)``:
    the ring outside the central ``fit`` x ``fit``, less the pixels within ``mask_radius`` of
    each source ``(x, y, amplitude)`` but its own (index ``own``, -1 for none), with
    ``bound[k]`` the light allowed for molecule ``k``."""
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    y, x, amplitude = (np.asarray(v, dtype=np.float64) for v in (y, x, amplitude))
    ring = np.ones((roi, roi), dtype=bool)
    k = (roi - fit) // 2
    ring[k : k + fit, k : k + fit] = False
    kept = np.broadcast_to(ring, (rows.size, roi, roi)).copy()
    if not (rows.size and y.size) or roi == fit:
        return kept
    low = float(np.min(bound))
    widest = float(mask_radius(np.max(amplitude), low, s)) if low > 0 else np.inf
    if widest == 0:
        return kept
    reach = roi // 2 + 1 + (widest if np.isfinite(widest) else np.hypot(roi, roi))
    tree = spatial.cKDTree(np.column_stack([y, x]))
    near = tree.query_ball_point(np.column_stack([rows, cols]), reach, p=np.inf)
    offsets = np.arange(roi) - roi // 2
    for m, sources in enumerate(near):
        sources = [j for j in sources if j != own[m]]
        if not sources:
            continue
        radius = mask_radius(amplitude[sources], bound[m], s)
        dy = rows[m] + offsets[:, None, None] - y[sources]
        dx = cols[m] + offsets[None, :, None] - x[sources]
        kept[m] &= ~np.any(dy**2 + dx**2 <= radius**2, axis=-1)
    return kept


def periphery_masks(
    molecules: pd.DataFrame,
    neighbours: pd.DataFrame,
    *,
    s0: float,
    pixel_size: float,
    roi: int,
    fit: int,
) -> np.ndarray:
    """Each molecule's periphery less the pixels its neighbours' light reaches.

    Parameters
    ----------
    molecules : pandas.DataFrame
        ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention), as ``cut_rois``.
    neighbours : pandas.DataFrame
        The detection table the molecules come from (``detect``'s ``molecule``, ``x``,
        ``y``, ``amplitude``, ``noise_var``; every molecule among its rows): every other row
        is a source of light.
    s0 : float
        The spot's SD in nm.
    pixel_size : float
        Pixel side in nm.
    roi, fit : int
        The cut's and the fitted window's sides (pixels).

    Returns
    -------
    numpy.ndarray of bool, shape (molecules, roi, roi)
        True on the periphery pixels kept for the background (module docstring).

    Raises
    ------
    BayespsfInputError
        A column missing from ``neighbours``, or a molecule that is not among its rows.
    """
    missing = [c for c in ("molecule", "x", "y", "amplitude", "noise_var") if c not in neighbours]
    if missing:
        raise BayespsfInputError(
            f"neighbours: missing column(s) {', '.join(missing)} (give detect's table)"
        )
    check_sizes(roi, fit)
    index = pd.Index(neighbours["molecule"])
    own = index.get_indexer(molecules["molecule"])
    if np.any(own < 0):
        absent = molecules["molecule"].to_numpy()[own < 0][:5].tolist()
        raise BayespsfInputError(
            f"neighbours: molecule(s) {absent} are not in the table (give the detection table "
            "the molecules come from)"
        )
    y, x = (neighbours[c].to_numpy(np.float64) for c in ("y", "x"))
    bound = np.sqrt((roi * roi - fit * fit) * neighbours["noise_var"].to_numpy(np.float64)[own])
    return ring_masks(
        np.floor(molecules["y"].to_numpy(np.float64) + 0.5),
        np.floor(molecules["x"].to_numpy(np.float64) + 0.5),
        own,
        y,
        x,
        np.maximum(neighbours["amplitude"].to_numpy(np.float64), 0.0),
        bound,
        _ratio(s0, pixel_size),
        roi,
        fit,
    )


def periphery_background(stack: RoiStack, camera, kept=None, which=None) -> pd.DataFrame:
    """Background photons per pixel of each ROI from its kept periphery.

    Parameters
    ----------
    stack : RoiStack
        The ROIs (``cut_rois``, ``iter_rois``).
    camera : Camera or Model
        Converts counts (ADU) to photons (``RoiStack.periphery_background``).
    kept : numpy.ndarray of bool, shape (molecules, roi, roi), optional
        The periphery pixels to use per molecule (``periphery_masks``); default the whole ring
        outside the stack's ``fit``.
    which : array_like of int, optional
        The row of ``kept`` of each ROI (default: ROI ``k`` uses row ``k``).

    Returns
    -------
    pandas.DataFrame
        ``b`` and ``b_se`` (the kept pixels' mean in photons and its SE: their SD over the
        square root of their number) and ``pixels`` (their number), indexed like the table.

    Raises
    ------
    BayespsfInputError
        A ``kept`` that is not ``(molecules, roi, roi)``, a ``which`` outside its rows, or a
        mask that keeps fewer than 2 pixels of a ROI.
    """
    if kept is None:
        ring = stack.periphery_background(camera)
        return ring.assign(pixels=stack.roi**2 - stack.fit**2)
    kept = np.asarray(kept, dtype=bool)
    which = np.arange(len(stack)) if which is None else np.asarray(which)
    if kept.ndim != 3 or kept.shape[1:] != stack.counts.shape[1:]:
        raise BayespsfInputError(
            f"periphery must have shape (molecules, {stack.roi}, {stack.roi}), got {kept.shape}"
        )
    if which.shape != (len(stack),) or np.any((which < 0) | (which >= len(kept))):
        raise BayespsfInputError(
            f"periphery has {len(kept)} molecule(s): one mask per molecule (periphery_masks)"
        )
    kept = kept[which]
    pixels = kept.sum(axis=(1, 2))
    if np.any(pixels < 2):
        raise BayespsfInputError(
            "periphery: fewer than 2 pixels left for a ROI's background (neighbours too close: "
            "detection rejects such molecules)"
        )
    photons = photon_model(camera).to_photons(stack.counts)
    mean = np.where(kept, photons, 0.0).sum(axis=(1, 2)) / pixels
    spread = np.where(kept, photons - mean[:, None, None], 0.0)
    se = np.sqrt((spread**2).sum(axis=(1, 2)) / (pixels - 1) / pixels)
    return pd.DataFrame({"b": mean, "b_se": se, "pixels": pixels}, index=stack.table.index)
