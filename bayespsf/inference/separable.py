"""The stack fit's pixel loops, written for the separable spot.

A pixel-integrated (or sampled) Gaussian is separable: its mass in pixel ``(i, j)`` is
``N Py[i] Px[j]``, and each row of its Jacobian by ``(x0, y0, s_x, s_y, N, b)`` is an outer
product ``A_k[i] B_k[j]`` of 1-D factors (``psf.gaussian.axis_factors``): ``B_k`` is one of
``Px``, ``dPx/dx0``, ``dPx/ds_x`` and the constant 1. So the sums that a Fisher-scoring step
needs, ``J' score`` and ``J' diag(F) J``, are taken a pixel row at a time: along the row, the
score against the four ``B`` and the information against the ten products ``B_k B_q``
(fourteen multiply-adds per pixel, with independent accumulators); then each row's sums times
the ``A`` factors. The Laplace's Hessian (``hessian_sums``) is taken the same way: the law's
curvature against the ten products, the score against six x factors. ``solver`` calls these;
their test references are the full Jacobian's contraction and central differences of the
gradient (``tests/inference/test_solver_factors.py``).
"""

from __future__ import annotations

import numba
import numpy as np

# the x factor of each Jacobian row (0: Px, 1: dPx/dx0, 2: dPx/ds_x, 3: the constant 1) and
# the index of each unordered pair of x factors in a row's ten information sums
COLUMN = np.array([1, 0, 2, 0, 0, 3])
PAIR = np.array([[0, 1, 2, 3], [1, 4, 5, 6], [2, 5, 7, 8], [3, 6, 8, 9]])


@numba.njit(cache=True, nogil=True)
def expected_counts(px, py, photons, background, scale, offset, out):
    """``(N Py[i] Px[j] + b) scale + offset`` into ``out`` (n, roi, roi), the same arithmetic
    as ``Model.expected`` of the separable spot (``Model._detected``: ``scale`` photoelectrons
    per photon, ``offset`` the clock-induced charge), so the same numbers bit for bit.

    ``px``, ``py`` (n, roi): the spot's 1-D masses; ``photons``, ``background`` (n,).
    Returns ``out``."""
    for r in range(out.shape[0]):
        n, b = photons[r], background[r]
        for i in range(out.shape[1]):
            row = n * py[r, i]
            for j in range(out.shape[2]):
                out[r, i, j] = (row * px[r, j] + b) * scale + offset
    return out


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def jacobian_sums(x, y, photons, scale, score, fisher, need, grad, metric):
    """``J' score`` into ``grad`` (n, 6) and ``J' diag(fisher) J`` into ``metric`` (n, 6, 6).

    ``x``, ``y`` (n, 3, roi): the 1-D factors along x and y (mass, derivative by the centre,
    by the width); ``photons`` (n,); ``scale``: photoelectrons per photon; ``score`` and
    ``fisher`` (n, roi, roi), per pixel. The Jacobian's rows at pixel ``(i, j)`` are
    ``c N Py dPx``, ``c N dPy Px``, ``c N Py dPx/ds``, ``c N dPy/ds Px``, ``c Py Px`` and
    ``c`` (``c = scale``). ``metric`` of length 0 gives the gradient alone; a ROI that
    ``need`` (n,) bool leaves out gets a NaN metric, and its ``fisher`` is not read. Fused
    multiply-adds only (``docs/decisions.md``): no reassociation, so the sums keep the order
    written here."""
    roi = x.shape[2]
    products, a, t, m = _scratch(roi)
    for r in range(x.shape[0]):
        with_metric = metric.shape[0] > 0 and need[r]
        spot = scale * photons[r]
        if with_metric:
            _products(x[r], products)
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        m[:] = 0.0
        for i in range(roi):
            s0 = s1 = s2 = s3 = 0.0
            for j in range(roi):
                s = score[r, i, j]
                s0 += x[r, 0, j] * s
                s1 += x[r, 1, j] * s
                s2 += x[r, 2, j] * s
                s3 += s
            _row_factors(y[r, :, i], spot, scale, a)
            g0 += a[0] * s1
            g1 += a[1] * s0
            g2 += a[2] * s2
            g3 += a[3] * s0
            g4 += a[4] * s0
            g5 += a[5] * s3
            if not with_metric:
                continue
            _pair_sums(fisher[r, i], products, t)
            for k in range(6):
                for q in range(k + 1):
                    m[k, q] += a[k] * a[q] * t[PAIR[COLUMN[k], COLUMN[q]]]
        grad[r, 0], grad[r, 1], grad[r, 2] = g0, g1, g2
        grad[r, 3], grad[r, 4], grad[r, 5] = g3, g4, g5
        if with_metric:
            for k in range(6):
                for q in range(k + 1):
                    metric[r, k, q] = metric[r, q, k] = m[k, q]
        elif metric.shape[0] > 0:
            metric[r] = np.nan


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def hessian_sums(x, y, xc, yc, photons, scale, score, curvature, hessian):
    """``sum_pixels -curvature J J' - score K`` into ``hessian`` (n, 6, 6): the Hessian of
    ``-log L`` in the parameters, ``curvature`` and ``score`` (n, roi, roi) the law's second
    and first derivatives by the expected count, ``K`` the expected count's second derivatives.

    ``xc``, ``yc`` (n, 3, roi): the factors' second derivatives (by the centre twice, by the
    centre and the width, by the width twice; ``psf.gaussian.axis_curvature``). ``K`` is
    ``c N`` times two factors' derivatives (``c N Py Px''`` for x0 twice, ``c N Py' Px'`` for
    x0 and y0, ...), ``c`` times one factor's derivative times the other factor for N and a
    position or width, and 0 for N twice and for b; each of its entries is an outer product
    too, so a pixel row takes the score against six x factors and the curvature against the
    ten products of ``jacobian_sums``."""
    roi = x.shape[2]
    products, a, t, h = _scratch(roi)
    for r in range(x.shape[0]):
        spot = scale * photons[r]
        _products(x[r], products)
        h[:] = 0.0
        for i in range(roi):
            # the score against Px, dPx, dPx/ds and their curvatures
            s0 = s1 = s2 = c0 = c1 = c2 = 0.0
            for j in range(roi):
                s = score[r, i, j]
                s0 += x[r, 0, j] * s
                s1 += x[r, 1, j] * s
                s2 += x[r, 2, j] * s
                c0 += xc[r, 0, j] * s
                c1 += xc[r, 1, j] * s
                c2 += xc[r, 2, j] * s
            _pair_sums(curvature[r, i], products, t)
            _row_factors(y[r, :, i], spot, scale, a)
            y0, y1, y2 = y[r, 0, i], y[r, 1, i], y[r, 2, i]
            for k in range(6):
                for q in range(k + 1):
                    h[q, k] -= a[k] * a[q] * t[PAIR[COLUMN[k], COLUMN[q]]]
            h[0, 0] -= spot * y0 * c0
            h[0, 2] -= spot * y0 * c1
            h[2, 2] -= spot * y0 * c2
            h[1, 1] -= spot * yc[r, 0, i] * s0
            h[1, 3] -= spot * yc[r, 1, i] * s0
            h[3, 3] -= spot * yc[r, 2, i] * s0
            h[0, 1] -= spot * y1 * s1
            h[0, 3] -= spot * y2 * s1
            h[1, 2] -= spot * y1 * s2
            h[2, 3] -= spot * y2 * s2
            h[0, 4] -= scale * y0 * s1
            h[2, 4] -= scale * y0 * s2
            h[1, 4] -= scale * y1 * s0
            h[3, 4] -= scale * y2 * s0
        for k in range(6):
            for q in range(k, 6):
                hessian[r, k, q] = hessian[r, q, k] = h[k, q]


@numba.njit(cache=True, nogil=True, inline="always")
def _scratch(roi):
    """Working arrays of the two sums: the ten x-factor products per pixel of a row, a row's
    six y factors, its ten weighted sums, and the 6 x 6 accumulator."""
    return np.empty((10, roi)), np.empty(6), np.empty(10), np.empty((6, 6))


@numba.njit(cache=True, nogil=True, inline="always")
def _row_factors(y, spot, scale, a):
    """The y factor ``A_k[i]`` of each Jacobian row at pixel row ``i``, from that row's ``Py``,
    ``dPy/dy0``, ``dPy/ds_y`` (``y``, length 3): ``c N Py``, ``c N dPy``, ``c N Py``,
    ``c N dPy/ds``, ``c Py``, ``c`` (``spot = c N``, ``scale = c``)."""
    a[0] = a[2] = spot * y[0]
    a[1], a[3] = spot * y[1], spot * y[2]
    a[4], a[5] = scale * y[0], scale


@numba.njit(cache=True, nogil=True)
def _products(x, products):
    """The ten products of a ROI's x factors ``x`` (3, roi) and the constant 1, by ``PAIR``."""
    for j in range(x.shape[1]):
        b0, b1, b2 = x[0, j], x[1, j], x[2, j]
        products[0, j], products[1, j], products[2, j] = b0 * b0, b0 * b1, b0 * b2
        products[3, j], products[4, j], products[5, j] = b0, b1 * b1, b1 * b2
        products[6, j], products[7, j], products[8, j] = b1, b2 * b2, b2
        products[9, j] = 1.0


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, inline="always")
def _pair_sums(weights, products, t):
    """``t[p] = sum_j products[p, j] weights[j]``, one pass over a pixel row with ten
    accumulators (independent chains, not one)."""
    t0 = t1 = t2 = t3 = t4 = t5 = t6 = t7 = t8 = t9 = 0.0
    for j in range(weights.shape[0]):
        f = weights[j]
        t0 += products[0, j] * f
        t1 += products[1, j] * f
        t2 += products[2, j] * f
        t3 += products[3, j] * f
        t4 += products[4, j] * f
        t5 += products[5, j] * f
        t6 += products[6, j] * f
        t7 += products[7, j] * f
        t8 += products[8, j] * f
        t9 += f
    t[0], t[1], t[2], t[3], t[4] = t0, t1, t2, t3, t4
    t[5], t[6], t[7], t[8], t[9] = t5, t6, t7, t8, t9
