"""Input validation shared by every public function: one place that turns bad input into an
error naming the argument."""

from __future__ import annotations

import functools
import numbers

import numpy as np

from bayespsf.errors import BayespsfInputError


def real_array(name: str, value) -> np.ndarray:
    """``value`` as a float64 array; complex, boolean or non-numeric values (which NumPy would
    cast silently: the imaginary part dropped, True read as 1) raise an error naming ``name``.
    NaN and infinity pass (``finite_array`` refuses them)."""
    try:
        raw = np.asarray(value)
    except ValueError as exc:  # ragged nested sequences
        raise BayespsfInputError(f"{name} must be a rectangular numeric array ({exc})") from exc
    if raw.dtype.kind == "O":  # e.g. a row of a mixed-type DataFrame: numbers held as objects
        try:
            raw = raw.astype(np.float64)
        except (TypeError, ValueError) as exc:
            raise BayespsfInputError(f"{name} must be real numbers, got {exc}") from exc
    if raw.dtype.kind not in "iuf":
        what = {"c": "complex", "b": "boolean", "U": "text", "S": "bytes"}
        raise BayespsfInputError(
            f"{name} must be real numbers (integer or float), got "
            f"{what.get(raw.dtype.kind, raw.dtype.name)} values"
        )
    return raw.astype(np.float64, copy=False)


def finite_array(name: str, value) -> np.ndarray:
    """``real_array`` whose entries are all finite (NaN or infinity raise naming ``name``)."""
    arr = real_array(name, value)
    if not np.all(np.isfinite(arr)):
        bad = np.count_nonzero(~np.isfinite(arr))
        raise BayespsfInputError(f"{name} must be finite; {bad} entries are NaN or infinite")
    return arr


def nonnegative_array(name: str, value) -> np.ndarray:
    """A finite float64 array with every entry >= 0."""
    arr = finite_array(name, value)
    if np.any(arr < 0):
        raise BayespsfInputError(
            f"{name} must be >= 0 (expected photons per pixel); min is {arr.min():.6g}"
        )
    return arr


def scalar_in_range(
    name: str, value, low: float, high: float = np.inf, *, low_inclusive: bool = True
) -> float:
    """``value`` as a float in [low, high] (or (low, high] when ``low_inclusive`` is False)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise BayespsfInputError(f"{name} must be a number, got {value!r}") from exc
    ok_low = v >= low if low_inclusive else v > low
    if not (np.isfinite(v) and ok_low and v <= high):
        bracket = "[" if low_inclusive else "("
        raise BayespsfInputError(f"{name} must be in {bracket}{low:g}, {high:g}], got {value!r}")
    return v


def probability(name: str, value) -> float:
    """``value`` as a float strictly between 0 and 1 (a credible or confidence level)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0 < value < 1:
        raise BayespsfInputError(f"{name} must be in (0, 1), got {value!r}")
    return float(value)


def broadcast_pair(name_a: str, a: np.ndarray, name_b: str, b: np.ndarray):
    """Broadcast two arrays, raising an error that names both when their shapes do not fit."""
    try:
        return np.broadcast_arrays(a, b)
    except ValueError as exc:
        raise BayespsfInputError(
            f"{name_a} with shape {a.shape} does not broadcast against {name_b} "
            f"with shape {b.shape}"
        ) from exc


def as_generator(rng) -> np.random.Generator:
    """A numpy Generator from a Generator, an integer seed or a SeedSequence."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        raise BayespsfInputError("rng must be a numpy Generator or an integer seed, got None")
    return np.random.default_rng(rng)


PLATEAU_SPREAD = 1000  # a plateau counts where the ROI spans this many count quanta


def suspect_rois(flat, low, floor, fraction, saturation) -> np.ndarray:
    """Which ROIs may have a problem, in one compiled pass over each ROI's pixels (a screen:
    the ROIs it flags are judged one by one; ``Model.roi_problems``).

    Parameters
    ----------
    flat : ndarray, shape (n, m)
        The ROIs' counts, one ROI per row.
    low : ndarray, shape (m,)
        A count below ``low[j]`` in pixel ``j`` is implausible for the camera.
    floor : float
        Any count below it flags the ROI (``-inf``: none).
    fraction : float
        More than this fraction of a ROI's pixels below ``low`` flags it.
    saturation : float
        A count at or above it flags the ROI; where it is 0 (none declared), two or more
        pixels at the ROI's maximum do.

    Returns
    -------
    ndarray of bool, shape (n,)
        True for a ROI with a NaN or infinite pixel, every pixel equal, or any of the above.
    """
    return _compiled_screen()(flat, low, floor, fraction, saturation)


@functools.cache
def _compiled_screen():
    """``_screen`` compiled (numba, imported here: the modules that validate input need not
    load it)."""
    import numba

    return numba.njit(cache=True, nogil=True)(_screen)


def _screen(flat, low, floor, fraction, saturation):
    n, m = flat.shape
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        row = flat[i]
        top, bottom = row[0], row[0]
        nonfinite, below = 0, 0
        for j in range(m):  # counts and extremes, no branch: the loop vectorises
            v = row[j]
            nonfinite += (v - v) != 0.0  # NaN for NaN and +-inf; the extremes then unused
            below += v < low[j]
            top, bottom = max(top, v), min(bottom, v)
        if saturation > 0:
            capped = top >= saturation
        else:
            ties = 0
            for j in range(m):
                ties += row[j] == top
            capped = ties >= 2
        equal = top == bottom  # every pixel equal
        out[i] = nonfinite > 0 or equal or bottom < floor or below / m > fraction or capped
    return out


def saturation_plateau(roi: np.ndarray) -> int:
    """The number of pixels of a saturation plateau in one ROI (flat counts), else 0.

    A plateau is two or more pixels at the ROI's maximum where that maximum is an ADC's full
    scale (``2**k - 1`` or ``2**k`` ADU, ``k`` = 8 to 20), or three or more where the ROI spans
    at least ``PLATEAU_SPREAD`` quanta (the smallest step between its distinct counts) between
    its median and its maximum: there, by chance, three pixels share the maximum with a
    probability of order ``PLATEAU_SPREAD**-2`` or less (the counts near the peak are spread
    over hundreds of quanta), while a clipped spot has several.

    Parameters
    ----------
    roi : ndarray
        One ROI's counts (any shape).

    Returns
    -------
    int
        The plateau's pixels, or 0.
    """
    top = roi.max()
    at_top = int(np.count_nonzero(roi == top))
    if at_top < 2:
        return 0
    full_scale = any(top in (2.0**k - 1, 2.0**k) for k in range(8, 21))
    if full_scale:
        return at_top
    steps = np.diff(np.unique(roi))
    spread = (top - np.median(roi)) / steps.min()
    return at_top if at_top >= 3 and spread >= PLATEAU_SPREAD else 0
