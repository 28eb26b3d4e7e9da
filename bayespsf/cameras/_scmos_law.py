"""The exact sCMOS pixel law in electron units: its log density, score and curvature.

Model (Huang et al., "Video-rate nanoscopy using sCMOS camera-specific single-molecule
localization algorithms", Nat. Methods 10, 653-658 (2013)): every pixel has its own gain ``g``
(ADU per photoelectron, > 0), offset ``o`` (ADU) and readout variance ``v`` (ADU^2, >= 0).
Given ``lam`` expected photoelectrons,

    n ~ Poisson(lam),    counts = o + g n + Normal(0, sqrt(v))    (ADU).

Everything here works in electrons, ``y = (c - o) / g`` and ``s = sqrt(v) / g`` (readout sd in
electrons): the law of ``y`` depends on ``(lam, s)`` only, so one implementation serves every
pixel (``bayespsf.cameras.scmos.SCMOS`` converts, and the density of the counts in ADU is
``p(c) = q(y) / g``), with

    q(y) = sum_{n >= 0} Pois(n; lam) phi_s(y - n),    phi_s = Normal(0, s) density.

The ``"exact"`` likelihood tier
    ``log q(y)`` by a log-space sum over a window of ``n`` (see ``log_mixture``). The
    summand is log-concave in ``n`` (its second difference is ``-log((n+1)/n) - 1/s^2 < 0``), so
    it has one mode; the sum starts at the mode and walks outward in both directions, stopping
    once the geometric bound on the remaining terms (valid by log-concavity) is below ``1e-17``
    of the running total, and in any case after ``12 min(sqrt(n_c + 1), s) + 12`` terms from
    the integer ``n_c`` nearest the mode, where the summand has provably dropped below
    ``exp(-46)`` of its peak. One compiled loop over pixels, each with its own walk, which
    gives the score and curvature by ``lam`` from the same terms (``log_mixture_and_score``).
    Measured absolute error in ``log p``: <= 4e-11 (a few ulp of ``log p``) against a 30-digit
    mpmath sum, for ``lam`` in [0, 1e5], readout sd in [0.1, 20] e- and counts in
    ``o + g [-50, lam + 50 sqrt(lam) + 50]``.

The Fisher information about ``lam``: ``bayespsf.cameras._scmos_fisher``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_LOG_2 = np.log(2.0)

# exact likelihood: window walk
_TAIL_TOL = 1e-17  # stop when the bound on the remaining terms is below this share of the sum
_WINDOW_SCALE = 12.0  # hard cap of the walk: 12 min(sqrt(m + 1), s) + 12 terms each side
_WINDOW_PAD = 12.0
_NEWTON_MAX_ITER = 100
_DARK_STEP = 1e-8  # photoelectrons: the score's forward difference at lam = 0
_DARK_SECANT = 1e-4  # ... and the curvature's secant there
_RATIO_REACH = 700.0  # the walk's ratios by recurrence where their first logs are below this


# --------------------------------------------------------------------------------------------
# The exact law in electron units
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _stirlerr(n):
    """``log n! - (n + 1/2) log n + n - log sqrt(2 pi)`` for ``n >= 1`` (series above 15)."""
    if n > 15.0:
        inv = 1.0 / n
        inv2 = inv * inv
        return inv * (
            1.0 / 12 - inv2 * (1.0 / 360 - inv2 * (1.0 / 1260 - inv2 * (1.0 / 1680 - inv2 / 1188)))
        )
    return math.lgamma(n + 1.0) - (n + 0.5) * math.log(n) + n - _LOG_SQRT_2PI


@numba.njit(cache=True, nogil=True)
def _log_poisson(n, lam, log_lam):
    """``log Pois(n; lam)`` at integer ``n >= 0`` for ``lam > 0``, accurate for large n and lam.

    Loader's saddle-point form ``-stirlerr(n) - log sqrt(2 pi n) - bd0(n, lam)`` with
    ``bd0 = n log(n / lam) + lam - n`` through ``log1p`` near ``n = lam``: the naive
    ``n log lam - lam - gammaln(n + 1)`` loses ~1e-10 to cancellation at ``n ~ 1e5``.
    """
    if n < 1.0:
        return -lam
    diff = n - lam
    if abs(diff) < 0.5 * n:
        bd0 = n * math.log1p(diff / lam) - diff
    else:
        bd0 = n * (math.log(n) - log_lam) - diff
    return -_stirlerr(n) - 0.5 * math.log(n) - _LOG_SQRT_2PI - bd0


@numba.njit(cache=True, nogil=True)
def _log_poisson_lattice(n, lam, log_lam):
    """``_log_poisson`` element by element (arrays of one shape, ``lam > 0``)."""
    out = np.empty(n.shape)
    flat_n, flat_lam, flat_log = n.ravel(), lam.ravel(), log_lam.ravel()
    flat = out.ravel()
    for k in range(flat.size):
        flat[k] = _log_poisson(flat_n[k], flat_lam[k], flat_log[k])
    return out


@numba.njit(cache=True, nogil=True)
def _mixture_mode(y, lam, log_lam, s2):
    """Mode over real ``n >= 0`` of ``n log lam - gammaln(n + 1) - (y - n)^2 / (2 s^2)``.

    The root of its derivative with ``digamma(n + 1)`` replaced by ``log(n + 1/2)`` (within
    0.12 of it, so the mode moves by less than 0.06): ``g(n) = log lam - log(n + 1/2) + (y - n)
    / s^2`` is convex and decreasing, so Newton's iterates, clamped at 0, reach it from any
    start (after the first step from the right they rise to it monotonically). Where ``g(0) <=
    0`` the mode is 0. The start is the root of ``g`` with ``log(n + 1/2)`` linear about ``lam``,
    the precision-weighted mean ``(y / s^2 + 1 - 1 / (2 lam)) / (1 / s^2 + 1 / lam)``: one or two
    steps from the root where the readout is narrow or the light bright. The sum only needs
    the mode to within ~1; iteration stops when a step is below 1e-3.
    """
    if log_lam + _LOG_2 + y / s2 <= 0.0:
        return 0.0  # the mode is at the boundary
    m = (y / s2 + 1.0 - 0.5 / lam) / (1.0 / s2 + 1.0 / lam)
    if not m > 0.0:  # also NaN, where 1 / lam overflows (lam below 1e-308)
        m = 0.0
    for _ in range(_NEWTON_MAX_ITER):
        slope = log_lam - math.log(m + 0.5) + (y - m) / s2
        step = slope / (1.0 / (m + 0.5) + 1.0 / s2)
        m = max(m + step, 0.0)
        if abs(step) < 1e-3:
            break
    return m


@numba.njit(cache=True, nogil=True, error_model="numpy")  # x / 0: inf, not an exception
def _walk(y, lam, s, moments):
    """``(log q(y), E[n | y] / lam, E[n (n - 1) | y] / lam^2)`` for ``lam > 0`` (the two
    moments only with ``moments``; else 0): the window walk of ``log_mixture``'s Notes for one
    pixel.

    A term is the last times its ratio to it, ``lam / n`` times the Gaussian's ratio
    ``exp(-(2 j - 1 +- 2 d0) c)``, which itself shrinks by ``exp(-2 c)`` per term: one ``exp``
    per direction, none per term. Where a first ratio could overflow (``(1 + 2 |d0|) c + |log
    lam - log(n_c + 1)| > 700``, ``_RATIO_REACH``: a count far from the light, or light far
    below a photoelectron at a count of many), each ratio is one ``exp`` of its logarithm
    instead.

    The moments are summed already divided by ``lam`` and ``lam^2``: above the centre the
    term of ``n`` times ``n / lam`` is the previous term times the Gaussian ratio, and times
    ``n (n - 1) / lam^2`` it is the previous such term times it, so no ``lam^n`` underflows
    first (with little light, ``E[n (n - 1)]`` lives in terms ``lam^2`` below the sum). The
    walk stops once each of the three series' tails is below ``_TAIL_TOL`` of its sum, and
    above the centre not before ``n = 2``.
    """
    log_lam = math.log(lam)
    s2 = s * s
    nc = float(round(_mixture_mode(y, lam, log_lam, s2)))
    d0 = nc - y
    c = 0.5 / s2
    log_centre = _log_poisson(nc, lam, log_lam) - d0 * d0 * c - math.log(s) - _LOG_SQRT_2PI
    cap = math.ceil(_WINDOW_SCALE * min(math.sqrt(nc + 1.0), s) + _WINDOW_PAD)
    by_ratio = (1.0 + 2.0 * abs(d0)) * c + abs(log_lam - math.log(nc + 1.0)) <= _RATIO_REACH
    shrink = math.exp(-2.0 * c)
    centre_first = nc / lam if moments else 0.0
    centre_second = centre_first * ((nc - 1.0) / lam) if moments and nc > 1.0 else 0.0
    total, first, second = 1.0, centre_first, centre_second
    for direction in (1.0, -1.0):
        up = direction > 0.0
        term, term_first = 1.0, centre_first  # the last term, and it times n / lam
        gauss = math.exp(-(1.0 + direction * 2.0 * d0) * c) if by_ratio else 0.0
        for j in range(1, cap + 1):
            n = nc + direction * j
            if n < 0.0:
                break
            # above the centre the moments' terms come from the previous terms, without lam^n
            if by_ratio:
                if moments and up:
                    new_first, new_second = term * gauss, term_first * gauss
                ratio = (lam / n if up else (n + 1.0) / lam) * gauss
                gauss *= shrink
            else:
                log_gauss = -(2.0 * j - 1.0 + direction * 2.0 * d0) * c
                if moments and up:
                    new_first = math.exp(math.log(term) + log_gauss) if term > 0.0 else 0.0
                    new_second = (
                        math.exp(math.log(term_first) + log_gauss) if term_first > 0.0 else 0.0
                    )
                log_poisson = log_lam - math.log(n) if up else math.log(n + 1.0) - log_lam
                ratio = math.exp(log_poisson + log_gauss)
            term *= ratio
            total += term
            if moments:
                if not up:
                    new_first = term * (n / lam) if term > 0.0 else 0.0
                    new_second = new_first * ((n - 1.0) / lam) if n > 1.0 else 0.0
                first += new_first
                second += new_second
                term_first = new_first
            # the ratios only fall (log-concave): once below 1, the rest of each series is
            # below the geometric series of its last ratio
            if not (ratio < 1.0 and term * ratio <= _TAIL_TOL * total * (1.0 - ratio)):
                continue
            if moments:
                if up and n < 2.0:
                    continue
                grow_first = ratio * (n + 1.0) / n if up else ratio
                grow_second = ratio * (n + 1.0) / (n - 1.0) if up else ratio
                if not (
                    grow_first < 1.0
                    and grow_second < 1.0
                    and new_first * grow_first <= _TAIL_TOL * first * (1.0 - grow_first)
                    and new_second * grow_second <= _TAIL_TOL * second * (1.0 - grow_second)
                ):
                    continue
            break
    return log_centre + math.log(total), first / total, second / total


@numba.njit(cache=True, nogil=True, error_model="numpy")  # x / 0: inf, not an exception
def _log_mixture(y, lam, s, out, score, curvature):
    """``log_mixture`` of flat arrays into ``out``; where ``score`` has their size, also
    ``d log q / d lam = E[n | y] / lam - 1`` and, where ``curvature`` has it,
    ``d^2 log q / d lam^2 = E[n (n - 1) | y] / lam^2 - (E[n | y] / lam)^2``, from the same
    walk (NaN at ``lam == 0``, where only one side of the derivative exists). NaN for all
    three where an input is outside the law's domain."""
    moments = score.size > 0
    for k in range(y.size):
        if not (
            math.isfinite(y[k]) and 0.0 <= lam[k] < math.inf and 0.0 < s[k] < math.inf
        ):  # unchecked input outside the domain: no value, rather than a walk from nowhere
            out[k] = np.nan
            if moments:
                score[k] = np.nan
                if curvature.size > 0:
                    curvature[k] = np.nan
            continue
        if lam[k] == 0.0:  # no light: only n = 0
            d = y[k] / s[k]
            out[k] = -0.5 * d * d - math.log(s[k]) - _LOG_SQRT_2PI
            if moments:
                score[k] = np.nan
                if curvature.size > 0:
                    curvature[k] = np.nan
            continue
        out[k], mean, pairs = _walk(y[k], lam[k], s[k], moments)
        if moments:
            score[k] = mean - 1.0
            if curvature.size > 0:
                curvature[k] = pairs - mean * mean


def log_mixture(y: ArrayLike, lam: ArrayLike, s: ArrayLike) -> np.ndarray:
    """``log sum_n Pois(n; lam) phi_s(y - n)``: the exact sCMOS law in electron units.

    Parameters
    ----------
    y : array_like
        Counts in photoelectrons, ``(c - o) / g``.
    lam : array_like
        Expected photoelectrons, ``>= 0``.
    s : array_like
        Readout sd in photoelectrons, ``sqrt(v) / g``, ``> 0``.

    Returns
    -------
    numpy.ndarray
        The log density of ``y`` (per photoelectron), broadcast shape. Unchecked input.

    Notes
    -----
    The summand ``f(n) = log Pois(n; lam) - (y - n)^2 / (2 s^2)`` is log-concave in ``n``. The
    sum is centred on the integer ``n_c`` nearest the mode (``_mixture_mode``); terms
    ``exp(f(n) - f(n_c))`` are built outward, each the last times its ratio to it (``lam /
    (n + 1)`` times the Gaussian's ratio: no cancellation between large ``gammaln`` values,
    and nothing overflows; ``_walk``). Each direction stops once ``t_j r_j / (1 - r_j)``
    (``t_j`` the last term, ``r_j`` its ratio to the previous one; ratios only shrink, by
    log-concavity) is below ``1e-17`` of the sum, or after ``12 min(sqrt(n_c + 1), s) + 12``
    terms, where the summand has dropped below ``exp(-46)`` of its peak (its curvature is at
    least ``1/(n + 1) + 1/s^2``). One pixel at a time in a compiled loop (``_log_mixture``),
    each with its own walk. A pixel whose ``y``, ``lam`` or ``s`` is not finite, or whose
    ``lam < 0`` or ``s <= 0``, gets NaN.
    """
    return _mixture(y, lam, s, False, False)[0]


def log_mixture_and_score(y: ArrayLike, lam: ArrayLike, s: ArrayLike, curvature: bool = False):
    """``log_mixture`` and its derivatives by ``lam``, from the same walk.

    Parameters
    ----------
    y, lam, s : array_like
        As ``log_mixture``.
    curvature : bool, optional
        Also the second derivative.

    Returns
    -------
    log_q, score : numpy.ndarray
        ``log q`` and ``d log q / d lam = E[n | y] / lam - 1`` (``d q / d lam = q(y - 1) -
        q(y)``), broadcast shape. At ``lam == 0``, where the law has only a one-sided
        derivative, the forward difference over ``1e-8`` photoelectrons
        (``Camera.score_unchecked``'s step there).
    curvature : numpy.ndarray
        With ``curvature`` only: ``E[n (n - 1) | y] / lam^2 - (E[n | y] / lam)^2``; at ``lam
        == 0`` the secant of the score over ``1e-4`` photoelectrons
        (``Camera.score_and_curvature_unchecked``'s there).
    """
    out = _mixture(y, lam, s, True, curvature)
    dark = np.flatnonzero(np.broadcast_to(np.asarray(lam, dtype=np.float64) == 0, out[0].shape))
    if dark.size:  # lam == 0: one-sided, as Camera.score_unchecked and its curvature
        y0, s0 = (np.broadcast_to(a, out[0].shape).ravel()[dark] for a in (y, s))
        flat = [a.reshape(-1) for a in out]  # views of the outputs
        flat[1][dark] = (log_mixture(y0, _DARK_STEP, s0) - flat[0][dark]) / _DARK_STEP
        if curvature:
            above = _mixture(y0, _DARK_SECANT, s0, True, False)[1]
            flat[2][dark] = (above - flat[1][dark]) / _DARK_SECANT
    return out


def _mixture(y, lam, s, score: bool, curvature: bool):
    arrays = [np.asarray(a, dtype=np.float64) for a in (y, lam, s)]
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    flat = []
    for a in arrays:  # flat and writeable for the compiled loop, copied only where they are not
        a = np.ascontiguousarray(np.broadcast_to(a, shape) if a.shape != shape else a)
        flat.append(a.reshape(-1) if a.flags.writeable else a.reshape(-1).copy())
    y, lam, s = flat
    out = [np.empty(y.size), np.empty(y.size if score else 0)]
    out.append(np.empty(y.size if curvature else 0))
    _log_mixture(y, lam, s, *out)
    return tuple(a.reshape(shape) for a in out[: 1 + score + curvature])
