"""The log posterior of many draws of many ROIs, without a draws x pixels array of the law.

Within one ROI's batch of draws each pixel's count is fixed and only its expected value
``lam = N Py[i] Px[j] + b`` moves, over the narrow range that the draws span. The camera's
log-likelihood of that count is a smooth function of ``lam`` there, so for each pixel it is
evaluated at ``DEGREE + 1`` Chebyshev nodes (first kind) in ``sqrt(lam)`` spanning the batch's
range, and every draw reads the pixel's interpolating polynomial (Clenshaw's recurrence, in a
compiled loop over draws that the compiler vectorises): ~20 arithmetic operations and a square
root per pixel and draw, where the EMCCD ``table`` tier costs ~40 operations, a logarithm and
two square roots and the ``exact`` tiers a quadrature. The law itself is called only at the
nodes (``Model.pixel_log_likelihood``, so every camera, tier and pixel map works unchanged);
the spot's 1-D factors ``Px``, ``Py`` (``roi`` values per axis and draw, not ``roi**2``) come
from ``bayespsf.inference.spot_factors``. Groups of at most ``GROUP_DRAWS`` draws keep the
working arrays in cache. A caller that scores a ROI batch by batch can keep its interpolants
(``kept``): they are built over ``WIDEN`` times the first batch's range and reused while they
span the next batch (checked as always).

Every interpolant is checked against the law at ``chebyshev.CHECKS``: the two ends of its range
and two midpoints between nodes (``x = +-1/2``), where a Chebyshev interpolant's error peaks. A
ROI with a pixel whose interpolant misses the law there by more than ``TOLERANCE`` in log p, or
whose law is not finite at a node, or whose range reaches ``lam <= 0``, is scored by
``Model.log_posterior`` itself. ``TOLERANCE`` (1e-6) is 40x below the ``table`` tier's own error
against the exact law (4e-5, ``benchmarks/README.md``). Measured against ``Model.log_posterior``
on Laplace draws of 100 ROIs (``tests/inference/test_fused.py`` holds the bound): a draw's log
posterior within 2e-7 (median 2e-8) for the EMCCD table, 5e-9 for the
photon-counting camera, 3e-9 for the sCMOS exact tier; the wider Student-t draws of
``method="importance"`` within 2.3e-6, with a few ROIs in a hundred sent to the law itself.
The interpolants are a ROI's own, so a ROI scores the same in any stack; a draw's value
depends on the other draws of its batch (the range) within that tolerance.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from bayespsf.inference import spot_factors
from bayespsf.inference.chebyshev import (
    AT_CHECKS,
    DEGREE,
    POINTS,
    TO_COEFFICIENTS,
    clenshaw,
    terms,
)
from bayespsf.model import LOG_PARAMETERS

TOLERANCE = 1e-6  # the largest |interpolant - law| in log p at the check points
GROUP_PIXELS = 2**22  # law evaluations per call at the nodes and check points (32 MB arrays)
GROUP_DRAWS = 2**14  # draws per group: the spot's factors, (roi, draws), in a few MB
WIDEN = 2.5  # a kept interpolant spans this many times its first batch's range
EXACT_DRAWS = 4096  # draws per Model.log_posterior call where the law is needed itself
EXACT_PIXELS = 2**22  # ... and pixels per call (401 x 401: 26 draws, not 4096 in 5.3 GB)
_FLAGS = {"contract", "reassoc", "nsz", "arcp"}  # vectorise the loops; keep inf and NaN exact


def score(
    model, stack: np.ndarray, draws: list[np.ndarray], kept: list | None = None
) -> list[np.ndarray]:
    """``Model.log_posterior`` of ``draws[i]`` (k_i, 6) in sampling coordinates given ROI
    ``stack[i]`` (validated counts, ``check_counts``), for every ROI at once.

    Parameters
    ----------
    model : Model
        The model of the ROIs.
    stack : ndarray, shape (m, roi, roi)
        Counts of the ROIs, already validated.
    draws : list of ndarray
        ``m`` arrays ``(k_i, 6)``: draws of ``z = (x0, y0, log s_x, log s_y, log N, b)``.
    kept : list, optional
        For callers that score a ROI's draws batch by batch: ``m`` entries, each None or the
        interpolants a previous call left for that ROI, updated in place. A ROI whose draws
        all lie within its kept interpolants' ranges reuses them; new ones span ``WIDEN``
        times the draws' range (checked as always), so that the next batch of draws from the
        same proposal likely falls inside.

    Returns
    -------
    list of ndarray
        ``m`` arrays ``(k_i,)``: the log posterior up to the constant of
        ``Model.log_posterior``, ``-inf`` outside the prior's support; within ``TOLERANCE``
        per pixel of it (module docstring).
    """
    sizes = np.array([len(z) for z in draws], dtype=np.int64)
    out = [np.empty(0) for _ in draws]
    for rois in _groups(sizes, POINTS.size * model.roi**2):
        rois = rois[sizes[rois] > 0]
        if rois.size:
            previous = None if kept is None else [kept[i] for i in rois]
            scored = _score_group(model, stack[rois], [draws[i] for i in rois], previous)
            for k, i in enumerate(rois):
                out[i] = scored[k]
                if kept is not None:
                    kept[i] = previous[k]
    return out


def _groups(sizes: np.ndarray, per_roi: int) -> list[np.ndarray]:
    """Consecutive ROIs in groups of at most ``GROUP_PIXELS`` law evaluations at their nodes
    and ``GROUP_DRAWS`` draws (one ROI at least): working arrays that stay in cache, instead
    of page faults and misses on arrays of tens of MB."""
    groups, first, draws = [], 0, 0
    most = max(1, GROUP_PIXELS // per_roi)
    for i, size in enumerate(sizes):
        if i > first and (i - first >= most or draws + size > GROUP_DRAWS):
            groups.append(np.arange(first, i))
            first, draws = i, 0
        draws += size
    groups.append(np.arange(first, len(sizes)))
    return groups


def _score_group(model, stack, draws, kept):
    sizes = np.array([len(z) for z in draws], dtype=np.int64)
    z = np.concatenate(draws)
    which = np.repeat(np.arange(len(draws)), sizes)
    with np.errstate(over="ignore"):  # exp overflow -> inf -> outside the prior's support
        p = model.from_unconstrained(z)
    total = model.log_prior(p) + z[:, LOG_PARAMETERS].sum(axis=1)
    inside = np.isfinite(total)
    total[~inside] = -np.inf
    p = p[inside]
    per_roi = np.bincount(which[inside], minlength=len(draws))
    starts = np.concatenate([[0], np.cumsum(per_roi)])
    roi, a = model.roi, float(model.pixel_size)
    sampled = model.pixel_model == "sampled"
    px = spot_factors.factors(p[:, 0], p[:, 2], roi, a, starts, sampled)
    py = spot_factors.factors(p[:, 1], p[:, 3], roi, a, starts, sampled)
    n = p[:, 4] * model.photoelectrons_per_photon
    b = p[:, 5] * model.photoelectrons_per_photon + model.clock_induced_charge
    low = np.full((len(draws), roi, roi), np.inf)
    high = np.full((len(draws), roi, roi), -np.inf)
    _ranges(px, py, n, b, starts, low, high)
    mid, half, coef, usable = _reused_or_built(model, stack, low, high, starts, kept)
    likelihood = np.zeros(len(p))
    _evaluate(px, py, n, b, starts, mid, 1.0 / half, coef, usable, likelihood)
    total[inside] += likelihood
    exact = np.flatnonzero(~usable & (np.diff(starts) > 0))
    if exact.size:  # ROIs whose interpolants missed the check: the law itself
        again = np.flatnonzero(np.isin(which, exact) & inside)
        step = min(EXACT_DRAWS, max(1, EXACT_PIXELS // model.roi**2))
        for first in range(0, again.size, step):
            part = again[first : first + step]
            total[part] = model.log_posterior(z[part], stack, which=which[part])
    return np.split(total, np.cumsum(sizes)[:-1])


def _reused_or_built(model, stack, low, high, starts, kept):
    """The interpolants of each ROI: its kept ones where they span its draws' range, else new
    ones (``WIDEN`` times that range where ``kept`` is given, which is then updated; the
    draws' range itself where the wider one misses the check)."""
    if kept is None:
        return _interpolants(model, stack, low, high, starts, 1.0)
    m, roi = low.shape[0], low.shape[1]
    mid, half = np.ones((m, roi, roi)), np.ones((m, roi, roi))
    coef, usable = np.zeros((m, roi, roi, DEGREE + 1)), np.zeros(m, dtype=np.bool_)
    have = np.array([r for r, old in enumerate(kept) if old is not None], dtype=np.int64)
    if have.size:
        mid[have] = np.stack([kept[r][0] for r in have])
        half[have] = np.stack([kept[r][1] for r in have])
        spanned = _spans(mid[have], half[have], low[have], high[have])
        usable[have] = spanned
        coef[have[spanned]] = np.stack([kept[r][2] for r in have[spanned]]) if spanned.any() else 0
    for widen in (WIDEN, 1.0):  # a wide range can miss the check where the draws' own pass
        build = np.flatnonzero(~usable & (np.diff(starts) > 0))
        if build.size:
            rows = np.concatenate([[0], np.cumsum(np.diff(starts)[build])])
            made = _interpolants(model, stack[build], low[build], high[build], rows, widen)
            mid[build], half[build], coef[build], usable[build] = made
    for r in range(m):
        kept[r] = (mid[r], half[r], coef[r]) if usable[r] else None
    return mid, half, coef, usable


def _spans(mid, half, low, high) -> np.ndarray:
    """Per ROI, whether its intervals ``mid +- half`` in ``sqrt(lam)`` (m, roi, roi) hold
    every pixel's ``[low, high]``."""
    slack = 1e-9 * half
    inside = (np.sqrt(low) >= mid - half - slack) & (np.sqrt(high) <= mid + half + slack)
    return np.all(inside, axis=(1, 2))


def _interpolants(model, stack, low, high, starts, widen):
    """Per ROI and pixel the interval ``mid +- half`` in ``sqrt(lam)``, the Chebyshev
    coefficients ``(m, roi, roi, DEGREE + 1)`` of the law there and, per ROI, whether every
    pixel's interpolant passed the check (module docstring)."""
    m, roi = low.shape[0], low.shape[1]
    mid, half = np.empty((m, roi, roi)), np.empty((m, roi, roi))
    positive = np.empty(m, dtype=np.bool_)
    lam = np.empty((m, POINTS.size, roi, roi))  # (m, points, roi, roi): camera maps broadcast
    _points(low, high, np.diff(starts) == 0, POINTS, widen, mid, half, positive, lam)
    values = model.pixel_log_likelihood(stack[:, None], lam)
    coef = np.empty((m, roi, roi, DEGREE + 1))
    usable = np.empty(m, dtype=np.bool_)
    _fit(values, TO_COEFFICIENTS, AT_CHECKS, TOLERANCE, positive, coef, usable)
    return mid, half, coef, usable


@numba.njit(cache=True, nogil=True)
def _points(low, high, empty, points, widen, mid, half, positive, lam):
    """Each pixel's interval in ``sqrt(lam)`` (``widen`` times the draws' range about its
    middle, its lower end no lower than half the draws' lowest) and the expected values at
    its nodes and check points; ``positive[r]`` is False where a range reaches ``lam <= 0``
    (a ROI without draws gets a valid interval that is never read)."""
    for r in range(low.shape[0]):
        positive[r] = True
        for i in range(low.shape[1]):
            for j in range(low.shape[2]):
                lo, hi = (1.0, 1.0) if empty[r] else (low[r, i, j], high[r, i, j])
                if not lo > 0.0:
                    positive[r], lo, hi = False, 1.0, 1.0
                a, b = math.sqrt(lo), math.sqrt(hi)
                spread = 0.5 * widen * (b - a)
                lower = max(0.5 * (a + b) - spread, 0.5 * a)
                upper = 0.5 * (a + b) + spread
                mid[r, i, j], half[r, i, j] = (
                    0.5 * (upper + lower),
                    max(0.5 * (upper - lower), 1e-300),
                )
                for k in range(points.size):
                    root = mid[r, i, j] + half[r, i, j] * points[k]
                    lam[r, k, i, j] = root * root


@numba.njit(cache=True, nogil=True)
def _fit(values, to_coefficients, at_checks, tolerance, positive, coef, usable):
    """Chebyshev coefficients from the law at the nodes (``values[:, :DEGREE + 1]``); a ROI
    is usable where every pixel's interpolant is within ``tolerance`` of the law at the check
    points and the law is finite at its nodes."""
    nodes = to_coefficients.shape[0]
    for r in range(values.shape[0]):
        usable[r] = positive[r]
        for i in range(values.shape[2]):
            for j in range(values.shape[3]):
                for k in range(nodes):
                    total = 0.0
                    for n in range(nodes):
                        total += to_coefficients[k, n] * values[r, n, i, j]
                    coef[r, i, j, k] = total
                for c in range(at_checks.shape[1]):
                    approx = 0.0
                    for k in range(nodes):
                        approx += coef[r, i, j, k] * at_checks[k, c]
                    if not abs(approx - values[r, nodes + c, i, j]) <= tolerance:
                        usable[r] = False  # also NaN: a law not finite at a node or check


@numba.njit(cache=True, nogil=True, fastmath=True)  # finite inputs: min/max vectorise
def _ranges(px, py, n, b, starts, low, high):
    """The smallest and largest expected value of each ROI's pixels over its draws."""
    roi = px.shape[0]
    for r in range(starts.size - 1):
        first, last = starts[r], starts[r + 1]
        photons, background = n[first:last], b[first:last]
        for i in range(roi):
            row = py[i, first:last]
            for j in range(roi):
                column = px[j, first:last]
                # four running extremes: one waits on the latency of each min and max
                s0 = s1 = s2 = s3 = np.inf
                l0 = l1 = l2 = l3 = -np.inf
                d = 0
                while d + 4 <= last - first:
                    a0 = photons[d] * row[d] * column[d] + background[d]
                    a1 = photons[d + 1] * row[d + 1] * column[d + 1] + background[d + 1]
                    a2 = photons[d + 2] * row[d + 2] * column[d + 2] + background[d + 2]
                    a3 = photons[d + 3] * row[d + 3] * column[d + 3] + background[d + 3]
                    s0, s1, s2, s3 = min(s0, a0), min(s1, a1), min(s2, a2), min(s3, a3)
                    l0, l1, l2, l3 = max(l0, a0), max(l1, a1), max(l2, a2), max(l3, a3)
                    d += 4
                for e in range(d, last - first):
                    lam = photons[e] * row[e] * column[e] + background[e]
                    s0, l0 = min(s0, lam), max(l0, lam)
                low[r, i, j] = min(min(s0, s1), min(s2, s3))
                high[r, i, j] = max(max(l0, l1), max(l2, l3))


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def _evaluate(px, py, n, b, starts, mid, inv_half, coef, usable, out):
    """Add each pixel's interpolated log-likelihood to ``out[d]`` (``chebyshev.clenshaw``)."""
    roi = px.shape[0]
    for r in range(starts.size - 1):
        if not usable[r]:
            continue
        first, last = starts[r], starts[r + 1]
        total, photons, background = out[first:last], n[first:last], b[first:last]
        for i in range(roi):
            row = py[i, first:last]
            for j in range(roi):
                column = px[j, first:last]
                c = terms(coef[r, i, j])
                m, h = mid[r, i, j], inv_half[r, i, j]
                for d in range(last - first):
                    x = (math.sqrt(photons[d] * row[d] * column[d] + background[d]) - m) * h
                    total[d] += clenshaw(c, x)


__all__ = ["GROUP_DRAWS", "TOLERANCE", "WIDEN", "score"]
