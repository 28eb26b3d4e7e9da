"""The spot's 1-D factors for many draws of many ROIs: ``Px`` (or ``Py``) per pixel and draw.

The integrated Gaussian's mass in a pixel is a difference of the upper tails
``Q(|z|) = erfc(|z| / sqrt(2)) / 2`` at its two edges (``z``: edge minus centre, over the
width), as ``bayespsf.psf.expected_counts`` takes it, so that a pixel far from the spot keeps
its relative precision. That is one ``erfc`` per edge and draw, ~19 ns each in compiled code
(the C library's, not vectorised), 32 per draw of a 15 x 15 ROI: the largest cost of scoring
a draw. Over one ROI's batch of draws an edge's ``z`` moves over a narrow range, so, as
``bayespsf.inference.fused`` does for the camera law, ``log Q`` of each edge is interpolated
there: Chebyshev nodes (``bayespsf.inference.chebyshev``) on the edge's range, the tail of the
side its range lies on (``log_ndtr(-z)``, or ``log_ndtr(z)`` on the left; an edge within one
width of the centre takes ``1 - Q`` of the other side near ``z = 0``, where it is exact enough),
checked at its check points to ``TOLERANCE`` in ``log Q``. The draws then cost a vectorised
polynomial and NumPy's vectorised ``exp`` per edge. A ROI with an edge whose interpolant misses
the check, or whose range spans both sides beyond one width, takes the ``erfc`` per draw.
``TOLERANCE`` (1e-9 in ``log Q``, so relative in ``Q``) moves a pixel's mass by at most 2e-9
relative (measured: 2e-10), and its log-likelihood by ~1e-7 at a count 50 from its
expectation, within ``fused``'s 1e-6 per pixel.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy import special

from bayespsf.inference.chebyshev import AT_CHECKS, DEGREE, POINTS, TO_COEFFICIENTS, clenshaw, terms
from bayespsf.psf.gaussian import pixel_mass

TOLERANCE = 1e-9  # the largest |interpolant - log Q| at the check points
NEAR = 1.0  # an edge's range may reach this many widths across the centre
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def factors(centre, width, roi: int, a: float, starts, sampled: bool) -> np.ndarray:
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
    z = mid[..., None] + half[..., None] * POINTS
    values = special.log_ndtr(np.where(upper[..., None], -z, z))
    coef = np.einsum("kn,men->mek", TO_COEFFICIENTS, values[..., : DEGREE + 1])
    error = np.einsum("mek,kc->mec", coef, AT_CHECKS) - values[..., DEGREE + 1 :]
    usable &= np.all(np.abs(error) <= TOLERANCE, axis=(1, 2))
    log_tail = np.zeros((roi + 1, len(centre)))  # 0 where not interpolated: read nowhere
    _log_tails(centre, scale, roi, a, starts, usable, mid, 1.0 / half, coef, log_tail)
    tail = np.exp(log_tail, out=log_tail)  # NumPy's exp is vectorised; the C library's is not
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
            out[j, d] = pixel_mass(near, far, near_tail, far_tail)
            near, near_tail = far, far_tail


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
    """The interpolated ``log Q`` of each usable ROI's edges, ``out[k, d]``
    (``chebyshev.clenshaw``)."""
    for r in range(starts.size - 1):
        if not usable[r]:
            continue
        first, last = starts[r], starts[r + 1]
        centres, scales = centre[first:last], scale[first:last]
        for k in range(roi + 1):
            edge = (k - 0.5 * roi) * a
            m, h, c = mid[r, k], inv_half[r, k], terms(coef[r, k])
            row = out[k, first:last]
            for d in range(last - first):
                row[d] = clenshaw(c, ((edge - centres[d]) * scales[d] - m) * h)


@numba.njit(cache=True, nogil=True)
def _masses(centre, scale, roi, a, starts, usable, upper, tail, out):
    """Each usable ROI's pixel masses from its edges' tails: ``tail`` is ``Q`` of the side an
    edge's interpolant took (``upper``: the right), ``1 - tail`` the other side's; it is
    turned into ``Q(|z|)`` in place, then each pixel's mass is read from its two edges. Both
    passes run over draws innermost, where the compiler vectorises them."""
    for r in range(starts.size - 1):
        if not usable[r]:
            continue
        first, last = starts[r], starts[r + 1]
        c, v = centre[first:last], scale[first:last]
        for k in range(roi + 1):
            edge, up, row = (k - 0.5 * roi) * a, upper[r, k], tail[k, first:last]
            for d in range(last - first):
                row[d] = row[d] if ((edge - c[d]) * v[d] >= 0.0) == up else 1.0 - row[d]
        for j in range(roi):
            near_edge, far_edge = (j - 0.5 * roi) * a, (j + 1.0 - 0.5 * roi) * a
            near_tail, far_tail, mass = tail[j, first:last], tail[j + 1, first:last], out[j]
            for d in range(last - first):
                near, far = (near_edge - c[d]) * v[d], (far_edge - c[d]) * v[d]
                mass[first + d] = pixel_mass(near, far, near_tail[d], far_tail[d])


__all__ = ["NEAR", "TOLERANCE", "factors"]
