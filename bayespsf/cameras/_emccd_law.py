"""The EMCCD pixel law in gain units: closed form without readout, quadrature with readout.

Everything here works in *gain units*: ``t = electrons / gain`` and ``r = readout_sd / gain``.
The law of ``t`` depends on ``(lam, r)`` only, so one implementation serves every gain.

Model (Basden, Haniff & Mackay, MNRAS 345 (2003); Ulbrich & Isacoff, Nat. Methods 4 (2007)):
photoelectrons ``n ~ Poisson(lam)``; the EM register turns ``n >= 1`` into ``Gamma(n, 1)``
(``n = 0`` stays 0); readout adds ``Normal(0, r)``. Without readout the law is an atom
``exp(-lam)`` at 0 plus the density

    f(t) = exp(-lam - t) * lam * 0F1(; 2; lam t),   0F1(; 2; w) = I1(2 sqrt(w)) / sqrt(w),

(the sum over n >= 1 of Poisson-weighted Gamma densities). With readout the density is
``exp(-lam) phi_r(t) + J(t)`` with ``J(t) = integral_0^inf f(u) phi_r(t - u) du``, which has no
closed form; ``log_convolved`` computes it by Gauss-Legendre quadrature on windows placed
around the integrand's mode (the integrand is log-concave in u, so it has one mode and the
windows carry all but ``exp(-_DROP)`` of its mass).
"""

from __future__ import annotations

import numpy as np
from scipy import special

_DROP = 40.0  # each window ends where the log-integrand has dropped this far below its mode
_NODES = 24  # Gauss-Legendre nodes per window: 1e-10 in log p against 128 nodes, lam <= 1e4
_GL_X, _GL_W = np.polynomial.legendre.leggauss(_NODES)
_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def log_0f1_2(w):
    """``log 0F1(; 2; w) = log(I1(2 sqrt w) / sqrt w)`` for ``w >= 0``, via the scaled Bessel
    function ``i1e`` (Cephes: equal to the general ``ive`` within 2e-15, and 7x faster).

    Series ``w/2 - w**2/24 + w**3/144`` below 1e-8 (where the Bessel form is 0/0 at w = 0).
    """
    w = np.asarray(w, dtype=np.float64)
    small = w < 1e-8
    ws = np.where(small, 1.0, w)
    z = 2.0 * np.sqrt(ws)
    big = np.log(special.i1e(z)) + z - 0.5 * np.log(ws)
    return np.where(small, w * (0.5 - w / 24.0), big)


def dlog_0f1_2(w, *, second: bool = False):
    """First derivative of ``log_0f1_2``, ``R(w) = I0(z) / (sqrt(w) I1(z)) - 1/w`` with
    ``z = 2 sqrt w``; with ``second``, also ``R'(w) = (1 - (I0/I1)^2) / w + 1 / w^2`` (negative:
    ``log_0f1_2`` is concave). Taylor series near 0, where the Bessel forms cancel.
    """
    w = np.asarray(w, dtype=np.float64)
    ws = np.where(w < 1e-4, 1.0, w)
    z = 2.0 * np.sqrt(ws)
    ratio = special.i0e(z) / special.i1e(z)
    first = np.where(w < 1e-4, 0.5 - w / 12.0 + w * w / 48.0, ratio / np.sqrt(ws) - 1.0 / ws)
    if not second:
        return first
    curvature = np.where(w < 1e-2, -1.0 / 12.0 + w / 24.0, (1.0 - ratio * ratio) / ws + 1.0 / ws**2)
    return first, curvature


def log_amplified(t, lam):
    """``log f(t)``: log density of the amplified (n >= 1) part at ``t > 0``, for ``lam > 0``."""
    return -lam - t + np.log(lam) + log_0f1_2(lam * t)


def log_normal_pdf(t, r):
    return -0.5 * (t / r) ** 2 - np.log(r) - _LOG_SQRT_2PI


def log_high_gain(t, lam):
    """Log density of the readout-free law (closed form), ``lam >= 0``.

    The atom ``exp(-lam)`` at ``t == 0`` is returned as its probability mass: the law is a
    density with respect to Lebesgue measure plus a unit point mass at zero. ``t < 0`` is
    outside the support (``-inf``).
    """
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    positive = (t > 0) & (lam > 0)
    ts = np.where(positive, t, 1.0)
    ls = np.where(positive, lam, 1.0)
    continuous = np.where(positive, log_amplified(ts, ls), -np.inf)
    return np.where(t == 0, -lam, continuous)


def _gradient(u, t0, lam, r):
    """First and second derivatives in u of ``log f(u) + log phi_r(t0 - u)``."""
    first, second = dlog_0f1_2(lam * u, second=True)
    d1 = -1.0 + lam * first + (t0 - u) / (r * r)
    d2 = lam * lam * second - 1.0 / (r * r)
    return d1, d2


def _mode(t0, lam, r, max_iter: int = 200):
    """Mode of the concave log-integrand on [0, inf): safeguarded Newton, vectorised.

    Only a loose mode is needed (1e-3 of the local width): the windows extend ~9 widths.
    """
    slope0, _ = _gradient(np.zeros_like(t0), t0, lam, r)
    interior = slope0 > 0
    idx = np.flatnonzero(interior)
    x, lm = t0[idx], lam[idx]
    lo = np.zeros_like(x)
    hi = np.maximum(x, 0.0) + 0.5 * r * r * lm + r
    # start from the product of the Gaussian approximations of f (mean lam, var 2 lam) and phi
    u = np.clip((2.0 * lm * x + lm * r * r) / (2.0 * lm + r * r), 0.0, hi)
    mode = np.zeros_like(t0)
    for _ in range(max_iter):
        if idx.size == 0:
            break
        d1, d2 = _gradient(u, x, lm, r)
        lo = np.where(d1 > 0, u, lo)
        hi = np.where(d1 <= 0, u, hi)
        newton = u - d1 / d2
        step = np.where((newton > lo) & (newton < hi), newton, 0.5 * (lo + hi))
        done = (np.abs(step - u) * np.sqrt(-d2) <= 1e-3) | (hi - lo <= 1e-12 * np.maximum(hi, 1.0))
        mode[idx[done]] = step[done]
        keep = ~done
        idx, x, lm, lo, hi, u = idx[keep], x[keep], lm[keep], lo[keep], hi[keep], step[keep]
    mode[idx] = u
    return mode, interior


def _windows(t0, lam, r):
    """Integration windows (left, right) of shape (..., 4) covering the integrand's mass."""
    m, interior = _mode(t0, lam, r)
    slope_m, curv_m = _gradient(m, t0, lam, r)
    quad_half = np.sqrt(2.0 * _DROP / -curv_m)
    # At a boundary mode (m = 0, slope < 0) the tangent bound may end the window sooner.
    tangent = np.where(slope_m < 0, _DROP / np.maximum(-slope_m, 1e-300), np.inf)
    right1 = m + np.where(interior, quad_half, np.minimum(quad_half, tangent))
    slope_r, _ = _gradient(right1, t0, lam, r)
    right2 = right1 + _DROP / np.maximum(-slope_r, 1e-300)
    left1 = np.where(interior, np.maximum(m - quad_half, 0.0), m)
    slope_l, _ = _gradient(left1, t0, lam, r)
    left2 = np.where(left1 > 0, np.maximum(left1 - _DROP / np.maximum(slope_l, 1e-300), 0.0), 0.0)
    lower = np.stack([left2, left1, m, right1], axis=-1)
    upper = np.stack([left1, m, right1, right2], axis=-1)
    return m, lower, upper


def log_convolved(t0, lam, r, *, with_score: bool = False):
    """``log J(t0)``, the readout-convolved amplified part, for ``lam > 0`` and ``r > 0``.

    With ``with_score``, also returns ``dJ/dlam / J``, using
    ``d log f(u) / d lam = -1 + 1/lam + u * dlog_0f1_2(lam u)``.
    """
    m, lower, upper = _windows(t0, lam, r)
    half = 0.5 * (upper - lower)
    # node offsets from the mode, formed from small differences to keep precision at large t
    offset = (0.5 * (upper + lower) - m[..., None])[..., None] + half[..., None] * _GL_X
    weights = half[..., None] * _GL_W
    lam_e = lam[..., None, None]
    m_e = m[..., None, None]
    gap = (t0 - m)[..., None, None]
    u = m_e + offset
    # log integrand at u minus its value at the mode m, written without large cancelling terms
    rel_log = (
        -offset
        + log_0f1_2(lam_e * u)
        - log_0f1_2(lam_e * m_e)
        + offset * (gap - 0.5 * offset) / (r * r)
    )
    rel = np.exp(rel_log) * weights
    total = rel.sum(axis=(-2, -1))
    peak = log_amplified(m, lam) - 0.5 * ((t0 - m) / r) ** 2
    log_j = peak + np.log(total) - np.log(r) - _LOG_SQRT_2PI
    if not with_score:
        return log_j
    dlogf = -1.0 + 1.0 / lam_e + u * dlog_0f1_2(lam_e * u)
    return log_j, (rel * dlogf).sum(axis=(-2, -1)) / total


def log_exact(t, lam, r):
    """Log density of the EMCCD law with readout ``r > 0`` (gain units), ``lam >= 0``."""
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    atom = -lam + log_normal_pdf(t, r)
    some = lam > 0
    log_j = np.full(t.shape, -np.inf)
    if some.any():
        log_j[some] = log_convolved(t[some], lam[some], r)
    return np.logaddexp(atom, log_j)


def log_small_lam(t, lam, r):
    """Log density of the law with readout ``r > 0`` for ``lam`` below ~1e-6, in closed form.

    Expanding the Poisson sum to second order in ``lam``,
    ``p(t) = exp(-lam) [phi_r(t) + lam g1(t) + lam**2 / 2 g2(t)] + O(lam**3)``, with ``g_n`` the
    Gamma(n, 1) density convolved with the readout Gaussian (exponentially modified Gaussians):
    ``g1(t) = exp(r**2/2 - t) Phi(m / r)`` and
    ``g2(t) = exp(r**2/2 - t) r [phi(m / r) + (m / r) Phi(m / r)]``, ``m = t - r**2``
    (Grushka, Anal. Chem. 44 (1972) for the first). The neglected third-order term is about
    ``lam**2 (t + r)**2 / 12`` of the first-order one: < 1e-7 in log p at ``lam = 1e-6`` up to
    ``t`` = 1000 gain units (tests/test_emccd_table.py checks it against ``log_exact``).
    Where ``m / r < -5`` the
    second-order term is below ``1e-6 lam`` of the first and is dropped.
    """
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    x = (t - r * r) / r
    shift = 0.5 * r * r - t
    atom = log_normal_pdf(t, r)
    first = np.log(lam) + shift + special.log_ndtr(x)
    xs = np.where(x > -5.0, x, 0.0)
    second = np.where(
        x > -5.0,
        2.0 * np.log(lam) - np.log(2.0) + shift + np.log(r)
        + np.log(np.exp(-0.5 * xs * xs) / np.sqrt(2.0 * np.pi) + xs * special.ndtr(xs)),
        -np.inf,
    )  # fmt: skip
    return -lam + np.logaddexp(np.logaddexp(atom, first), second)


def log_and_score_exact(t, lam, r):
    """``log p`` and ``d log p / d lam`` of the law with readout ``r > 0``, for ``lam > 0``."""
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    shape = t.shape
    t, lam = t.ravel(), lam.ravel()  # the quadrature works on flat arrays
    log_atom = -lam + log_normal_pdf(t, r)
    log_j, ratio = log_convolved(t, lam, r, with_score=True)
    log_p = np.logaddexp(log_atom, log_j)
    score = np.exp(log_j - log_p) * ratio - np.exp(log_atom - log_p)
    return log_p.reshape(shape), score.reshape(shape)


def score_high_gain(t, lam):
    """``d log p / d lam`` of the readout-free law at ``t >= 0``, ``lam > 0``."""
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    positive = t > 0
    ts = np.where(positive, t, 1.0)
    continuous = -1.0 + 1.0 / lam + ts * dlog_0f1_2(lam * ts)
    return np.where(positive, continuous, -1.0)
