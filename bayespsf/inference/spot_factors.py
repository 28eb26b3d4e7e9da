"""The spot's 1-D factors for many draws of many ROIs: ``Px`` (or ``Py``) per pixel and draw.

The integrated Gaussian's mass in a pixel is a difference of the upper tails
``Q(|z|) = erfc(|z| / sqrt(2)) / 2`` at its two edges (``z``: edge minus centre, over the
width), as ``bayespsf.psf.expected_counts`` takes it, so that a pixel far from the spot keeps
its relative precision. That is one ``erfc`` per edge and draw, ~19 ns each in compiled code
(the C library's, not vectorised), 32 per draw of a 15 x 15 ROI: the largest cost of scoring
a draw. Over one ROI's batch of draws an edge's ``z`` moves over a narrow range, so, as
``bayespsf.inference.fused`` does for the camera law, ``log Q`` of each edge is interpolated
there: Chebyshev nodes (``fused.NODES``) on the edge's range, the tail of the side its range
lies on (``log_ndtr(-z)``, or ``log_ndtr(z)`` on the left; an edge within one width of the
centre takes ``1 - Q`` of the other side near ``z = 0``, where it is exact enough), checked at
``fused.CHECKS`` to ``TOLERANCE`` in ``log Q``. The draws then cost a vectorised polynomial
and NumPy's vectorised ``exp`` per edge. A ROI with an edge whose interpolant misses the
check, or whose range spans both sides beyond one width, takes the ``erfc`` per draw.
``TOLERANCE`` (1e-11, relative in ``Q``) moves a pixel's expected count by at most 2e-11
relative, its log-likelihood by ~1e-9 at a count 50 from its expectation.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy import special

TOLERANCE = 1e-9  # the largest |interpolant - log Q| at the check points
NEAR = 1.0  # an edge's range may reach this many widths across the centre
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def factors(centre, width, roi: int, a: float, starts, sampled: bool, nodes) -> np.ndarray:
    """The spot's 1-D factor ``(roi, n)`` along one axis for draws ``centre``, ``width`` (n,)
    grouped by ROI (``starts``: each ROI's first draw, then n).

    Parameters
    ----------
    centre, width : ndarray, shape (n,)
        The spot's centre (nm) and SD (nm, > 0) along the axis, per draw.
    roi : int
        Side of the ROI in pixels.
    a : float
        Pixel side in nm.
    starts : ndarray of int
        Where each ROI's draws begin, and their number at the end (``m + 1`` values).
    sampled : bool
        The density at the pixel centre times ``a`` (``sampled_gaussian``) instead of the
        mass in the pixel.
    nodes : tuple
        ``(points, to_coefficients, at_checks)`` of ``bayespsf.inference.fused``: the
        Chebyshev nodes then check points on [-1, 1], and the matrices that give the
        coefficients from the node values and the interpolant at the check points.

    Returns
    -------
    ndarray, shape (roi, n)
        ``Px[j]`` for each draw: the fraction of the spot's photons in pixel ``j``.
    """
    out = np.empty((roi, len(centre)))
    if sampled or len(centre) == 0:
        _direct(centre, width, roi, a, sampled, out)
        return out
    m = len(starts) - 1
    low, high = np.empty((m, roi + 1)), np.empty((m, roi + 1))
    scale = 1.0 / width  # one division per draw, not one per edge
    _edge_ranges(centre, scale, roi, a, starts, low, high)
    empty = np.diff(starts) == 0
    low[empty], high[empty] = 0.0, 0.0  # no draws: an interval that is never read
    upper = low >= -NEAR  # log Q of the right side; else of the left
    usable = np.all(upper | (high <= NEAR), axis=1) & ~empty
    mid, half = 0.5 * (high + low), np.maximum(0.5 * (high - low), 1e-300)
    points, to_coefficients, at_checks = nodes
    z = mid[..., None] + half[..., None] * points
    values = special.log_ndtr(np.where(upper[..., None], -z, z))
    degree = to_coefficients.shape[0]
    coef = np.einsum("kn,men->mek", to_coefficients, values[..., :degree])
    error = np.einsum("mek,kc->mec", coef, at_checks) - values[..., degree:]
    usable &= np.all(np.abs(error) <= TOLERANCE, axis=(1, 2))
    log_tail = np.zeros((roi + 1, len(centre)))  # 0 where not interpolated: read nowhere
    _log_tails(centre, scale, roi, a, starts, usable, mid, 1.0 / half, coef, log_tail)
    tail = np.exp(log_tail)  # NumPy's exp is vectorised; the compiled C library's is not
    _masses(centre, scale, roi, a, starts, usable, upper, tail, out)
    for r in np.flatnonzero(~usable):
        part = slice(starts[r], starts[r + 1])
        _direct(centre[part], width[part], roi, a, False, out[:, part])
    return out


@numba.njit(cache=True, nogil=True)
def _direct(centre, width, roi, a, sampled, out):
    """The factor ``out[j, d]`` draw by draw: the Gaussian's mass in pixel ``j`` from ``erfc``
    at each edge (a pixel wholly on one side of the centre as a difference of upper tails), or
    with ``sampled`` its density at the pixel centre times ``a``."""
    for d in range(centre.shape[0]):
        c, w = centre[d], width[d]
        if sampled:
            for j in range(roi):
                u = ((j - 0.5 * (roi - 1)) * a - c) / w
                out[j, d] = a * _INV_SQRT_2PI * math.exp(-0.5 * u * u) / w
            continue
        near = ((0.0 - 0.5 * roi) * a - c) / w
        near_tail = 0.5 * math.erfc(abs(near) * _INV_SQRT2)
        for j in range(roi):
            far = ((j + 1.0 - 0.5 * roi) * a - c) / w
            far_tail = 0.5 * math.erfc(abs(far) * _INV_SQRT2)
            out[j, d] = _mass(near, far, near_tail, far_tail)
            near, near_tail = far, far_tail


@numba.njit(cache=True, nogil=True, inline="always")
def _mass(near, far, near_tail, far_tail):
    """A pixel's mass from its edges ``near < far`` and the tails beyond them, ``Q(|z|)``."""
    if near >= 0.0:
        return near_tail - far_tail
    if far <= 0.0:
        return far_tail - near_tail
    return 1.0 - near_tail - far_tail


@numba.njit(cache=True, nogil=True, fastmath=True)
def _edge_ranges(centre, scale, roi, a, starts, low, high):
    """The smallest and largest standardised position ``z`` of each ROI's edges (``scale``:
    one over the width)."""
    for r in range(starts.size - 1):
        for k in range(roi + 1):
            edge = (k - 0.5 * roi) * a
            smallest, largest = np.inf, -np.inf
            for d in range(starts[r], starts[r + 1]):
                z = (edge - centre[d]) * scale[d]
                smallest, largest = min(smallest, z), max(largest, z)
            low[r, k], high[r, k] = smallest, largest


@numba.njit(cache=True, nogil=True, fastmath={"contract", "reassoc", "nsz", "arcp"})
def _log_tails(centre, scale, roi, a, starts, usable, mid, inv_half, coef, out):
    """The interpolated ``log Q`` of each usable ROI's edges, ``out[k, d]`` (Clenshaw, degree
    8, unrolled so that the loop over draws vectorises)."""
    for r in range(starts.size - 1):
        if not usable[r]:
            continue
        first, last = starts[r], starts[r + 1]
        centres, scales = centre[first:last], scale[first:last]
        for k in range(roi + 1):
            edge = (k - 0.5 * roi) * a
            m, h, c = mid[r, k], inv_half[r, k], coef[r, k]
            c0, c1, c2, c3, c4, c5, c6, c7, c8 = (
                c[0],
                c[1],
                c[2],
                c[3],
                c[4],
                c[5],
                c[6],
                c[7],
                c[8],
            )
            row = out[k, first:last]
            for d in range(last - first):
                x = ((edge - centres[d]) * scales[d] - m) * h
                x2 = 2.0 * x
                b7 = c7 + x2 * c8
                b6 = c6 + x2 * b7 - c8
                b5 = c5 + x2 * b6 - b7
                b4 = c4 + x2 * b5 - b6
                b3 = c3 + x2 * b4 - b5
                b2 = c2 + x2 * b3 - b4
                b1 = c1 + x2 * b2 - b3
                row[d] = c0 + x * b1 - b2


@numba.njit(cache=True, nogil=True)
def _masses(centre, scale, roi, a, starts, usable, upper, tail, out):
    """Each usable ROI's pixel masses from its edges' tails: ``tail`` is ``Q`` of the side an
    edge's interpolant took (``upper``: the right), ``1 - tail`` the other side's."""
    for r in range(starts.size - 1):
        if not usable[r]:
            continue
        for d in range(starts[r], starts[r + 1]):
            c, v = centre[d], scale[d]
            near = ((0.0 - 0.5 * roi) * a - c) * v
            near_tail = tail[0, d] if (near >= 0.0) == upper[r, 0] else 1.0 - tail[0, d]
            for j in range(roi):
                far = ((j + 1.0 - 0.5 * roi) * a - c) * v
                t = tail[j + 1, d]
                far_tail = t if (far >= 0.0) == upper[r, j + 1] else 1.0 - t
                out[j, d] = _mass(near, far, near_tail, far_tail)
                near, near_tail = far, far_tail


__all__ = ["NEAR", "TOLERANCE", "factors"]
