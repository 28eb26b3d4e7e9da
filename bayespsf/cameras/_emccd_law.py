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
windows carry all but ``exp(-_DROP)`` of its mass), except where the readout is too narrow to
change ``log J`` at double precision: there ``J = f`` (``readout_negligible``, with its bound).

Numerical domain (``EMCCD`` refuses anything else; tests/cameras/test_camera_domain.py):
``r = 0`` or ``RATIO_MIN <= r <= RATIO_MAX``, ``lam`` in ``[0, 1e10]`` and ``|t| <= T_MAX``.
There every function here is finite (``-inf`` only outside the support) and warning-free:
``(t / r)**2`` stays below 1e55 and ``r * r`` above 1e-24.
"""

from __future__ import annotations

import numpy as np
from scipy import special

_DROP = 40.0  # each window ends where the log-integrand has dropped this far below its mode
_NODES = 24  # Gauss-Legendre nodes per window: 1e-10 in log p against 128 nodes, lam <= 1e4
_GL_X, _GL_W = np.polynomial.legendre.leggauss(_NODES)
_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
RATIO_MIN, RATIO_MAX = 1e-12, 1e6  # readout/gain r > 0; physical cameras have 1e-4 to 300
T_MAX = 1e15  # largest |t| in gain units, 1e5 times the law's bulk at lam = 1e10
_NEGLIGIBLE_ABS = 1e-13  # readout ignored where it moves log J by less than this ...
_NEGLIGIBLE_REL = 2.0**-53  # ... or by less than half an ulp of log J
_REACH = 40.0  # readout SDs: beyond them the Gaussian weight is below exp(-800)
_BLOCK = 2048  # points per quadrature pass: its (points, 4, _NODES) arrays are 1.5 MB each


def log_0f1_2(w):
    """``log 0F1(; 2; w) = log(I1(2 sqrt w) / sqrt w)`` for ``w >= 0``, via the scaled Bessel
    function ``i1e`` (Cephes: equal to the general ``ive`` within 2e-15, and 7x faster).

    Series ``w/2 - w**2/24 + w**3/144`` below 1e-8 (where the Bessel form is 0/0 at w = 0).
    """
    w = np.asarray(w, dtype=np.float64)
    small = w < 1e-8
    ws = np.where(small, 1.0, w)
    wt = np.where(small, w, 0.0)  # the series only where it is used: w * w overflows at 1e154
    z = 2.0 * np.sqrt(ws)
    big = np.log(special.i1e(z)) + z - 0.5 * np.log(ws)
    return np.where(small, wt * (0.5 - wt / 24.0), big)


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


def _gradient(u, gap, lam, r):
    """First and second derivatives in u of ``log f(u) + log phi_r(t0 - u)``, ``gap = t0 - u``.

    The gap is passed separately so that callers can form it from exact small differences: at
    large ``t0`` and small ``r`` the readout term ``gap / r**2`` would otherwise be dominated by
    the rounding of ``u``.
    """
    first, second = dlog_0f1_2(lam * u, second=True)
    d1 = -1.0 + lam * first + gap / (r * r)
    d2 = lam * lam * second - 1.0 / (r * r)
    return d1, d2


def _mode(t0, lam, r, max_iter: int = 200):
    """Mode of the concave log-integrand on [0, inf): safeguarded Newton, vectorised.

    Only a loose mode is needed (1e-3 of the local width ``1 / sqrt(-d2)``): the windows extend
    ~9 widths. Iteration also stops once the bracket is that narrow or a few ulp wide (the
    mode is then resolved as well as a double can hold it).
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
        d1, d2 = _gradient(u, x - u, lm, r)
        lo = np.where(d1 > 0, u, lo)
        hi = np.where(d1 <= 0, u, hi)
        newton = u - d1 / d2
        step = np.where((newton > lo) & (newton < hi), newton, 0.5 * (lo + hi))
        width = 1e-3 / np.sqrt(-d2)
        done = (np.abs(step - u) <= width) | (hi - lo <= np.maximum(width, 4.0 * np.spacing(hi)))
        mode[idx[done]] = step[done]
        keep = ~done
        idx, x, lm, lo, hi, u = idx[keep], x[keep], lm[keep], lo[keep], hi[keep], step[keep]
    mode[idx] = u
    return mode, interior


def _windows(t0, lam, r):
    """Integration windows as offsets from the mode ``m``: ``(m, lower, upper)``, the last two
    of shape (..., 4), covering all but ``exp(-_DROP)`` of the integrand's mass.

    Slopes at the window ends are evaluated from the exact offsets. The log-integrand's
    curvature is at most ``-1 / r**2`` (``log f`` is concave), so its slope ``delta`` away from
    the mode exceeds ``|delta| / r**2`` in magnitude; half of that floors the computed slope,
    so no rounding can open a window without end.
    """
    m, interior = _mode(t0, lam, r)
    gap = t0 - m
    r2 = r * r

    def slope(delta):
        return _gradient(m + delta, gap - delta, lam, r)[0]

    slope_m, curv_m = _gradient(m, gap, lam, r)
    quad_half = np.sqrt(2.0 * _DROP / -curv_m)
    # At a boundary mode (m = 0, slope < 0) the tangent bound may end the window sooner.
    tangent = np.where(slope_m < 0, _DROP / np.maximum(-slope_m, 1e-300), np.inf)
    right1 = np.where(interior, quad_half, np.minimum(quad_half, tangent))
    right2 = right1 + _DROP / np.maximum(-slope(right1), 0.5 * right1 / r2)
    inner = interior & (m > quad_half)  # a left tail window fits above u = 0
    left1 = np.where(inner, -quad_half, -m)
    left2 = np.where(
        inner, np.maximum(left1 - _DROP / np.maximum(slope(left1), 0.5 * quad_half / r2), -m), -m
    )
    zero = np.zeros_like(m)
    lower = np.stack([left2, left1, zero, right1], axis=-1)
    upper = np.stack([left1, zero, right1, right2], axis=-1)
    return m, lower, upper


def readout_negligible(t0, lam, r):
    """Where the readout cannot change ``log J`` at double precision, and ``log f(t0)``.

    With ``g = log f``, concave on ``u > 0`` with curvature ``lam**2 R'(lam u)`` shrinking in
    magnitude as ``u`` grows (``R = dlog_0f1_2``, ``-1/12 <= R' < 0``), and ``Z ~ Normal(0, 1)``,
    ``J(t) / f(t) = E[exp(g(t + r Z) - g(t)); t + r Z > 0]``. For ``t > 40 r``:

    * concavity, ``g(t + rZ) <= g(t) + g'(t) r Z``, gives ``log J - g(t) <= r**2 g'(t)**2 / 2``;
    * on ``|Z| <= 40``, ``g(t + rZ) >= g(t) + g'(t) r Z - c r**2 Z**2 / 2`` with
      ``c = |g''(t - 40 r)|``, and the Gaussian integral gives
      ``log J - g(t) >= -c r**2 / 2 - exp(-200)`` (while ``|g'| r <= 20``).

    So ``|log J - g(t)| <= B = r**2 max(g'(t)**2, c) / 2``. Where ``B`` is below 1e-13 (a
    hundredth of the quadrature's error) or below half an ulp of ``g(t)`` (``2**-53 |g|``),
    ``J = f(t)`` exactly in double precision; the score's error, to leading order
    ``r**2 g' dg'/dlam``, is smaller still. This is where the quadrature's windows (a few ``r``
    wide) would fall below the spacing of doubles near ``t``: the regime of
    ``r <= 1e-5`` far in the upper tail. Returns the mask and ``log f(t0)`` (``-inf`` off it).
    """
    far = t0 > _REACH * r
    ts = np.where(far, t0, 1.0)
    g1 = -1.0 + lam * dlog_0f1_2(lam * ts)
    _, curvature = dlog_0f1_2(lam * np.where(far, t0 - _REACH * r, 1.0), second=True)
    bound = 0.5 * r * r * np.maximum(g1 * g1, -lam * lam * curvature)
    log_f = log_amplified(ts, lam)
    negligible = far & (bound <= np.maximum(_NEGLIGIBLE_ABS, _NEGLIGIBLE_REL * np.abs(log_f)))
    return negligible, np.where(negligible, log_f, -np.inf)


def log_convolved(t0, lam, r, *, with_score: bool = False):
    """``log J(t0)``, the readout-convolved amplified part, for ``lam > 0`` and ``r > 0``.

    The closed form ``log f(t0)`` where ``readout_negligible``, quadrature elsewhere. With
    ``with_score``, also returns ``dJ/dlam / J``, using
    ``d log f(u) / d lam = -1 + 1/lam + u * dlog_0f1_2(lam u)``. The quadrature runs over
    blocks of ``_BLOCK`` points, each point's value the same as in one pass over all of them,
    so its memory does not grow with the input (in one pass, the 285 000 points of the
    ``table`` tier's grids took a process to 1.6 GB: benchmarks/README.md, first use).
    """
    t0, lam = np.broadcast_arrays(np.asarray(t0, float), np.asarray(lam, float))
    shape = t0.shape
    t0, lam = t0.ravel(), lam.ravel()
    negligible, log_j = readout_negligible(t0, lam, r)
    score = _score_amplified(np.where(negligible, t0, 1.0), lam)
    hard = np.flatnonzero(~negligible)
    for start in range(0, hard.size, _BLOCK):
        k = hard[start : start + _BLOCK]
        quad = _log_convolved_quadrature(t0[k], lam[k], r, with_score=with_score)
        log_j[k], score[k] = quad if with_score else (quad, 0.0)
    log_j, score = log_j.reshape(shape), score.reshape(shape)
    return (log_j, score) if with_score else log_j


def _log_convolved_quadrature(t0, lam, r, *, with_score: bool):
    """``log J(t0)`` (and its score) by Gauss-Legendre quadrature on ``_windows``; 1-D input."""
    m, lower, upper = _windows(t0, lam, r)
    half = 0.5 * (upper - lower)
    # node offsets from the mode, formed from small differences to keep precision at large t
    offset = (0.5 * (upper + lower))[..., None] + half[..., None] * _GL_X
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


def _score_amplified(t, lam):
    """``d log f(t) / d lam = -1 + 1/lam + t R(lam t)`` at ``t > 0``, ``lam > 0``."""
    return -1.0 + 1.0 / lam + t * dlog_0f1_2(lam * t)


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
    ``t`` = 1000 gain units (tests/cameras/test_emccd_table.py checks it against ``log_exact``).
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
        2.0 * np.log(lam)
        - np.log(2.0)
        + shift
        + np.log(r)
        + np.log(np.exp(-0.5 * xs * xs) / np.sqrt(2.0 * np.pi) + xs * special.ndtr(xs)),
        -np.inf,
    )
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
    continuous = _score_amplified(np.where(positive, t, 1.0), lam)
    return np.where(positive, continuous, -1.0)


def readout_free_score(t, lam):
    """Score of the closed form without readout; at ``lam == 0``, ``-1`` at the offset and
    ``+inf`` above it (the one-sided derivative of ``log(lam) + ...``)."""
    positive = lam > 0
    score = score_high_gain(t, np.where(positive, lam, 1.0))
    return np.where(positive, score, np.where(t > 0, np.inf, -1.0))


def gaussian_score(t, lam, r):
    """``d/dlam`` of ``log Normal(t; lam, 2 lam + r^2)``:
    ``(t - lam) / v + (t - lam)^2 / v^2 - 1 / v`` with ``v = 2 lam + r^2``; NaN at the
    degenerate ``v = 0`` (``lam = r = 0``), where the law is an atom at 0 with no derivative.

    Without readout and below ``lam ~ 1e-150`` the true value can exceed the double range: it
    is then ``+inf`` or ``-inf`` by the sign of ``z^2 - 1``, ``z^2 = (t - lam)^2 / v``.
    """
    v = 2.0 * lam + r * r
    degenerate = v == 0
    vs = np.where(degenerate, 1.0, v)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        d = (t - lam) / vs
        score = d + d * d - 1.0 / vs
        z2 = (t - lam) * d
    score = np.where(np.isnan(score), np.where(z2 > 1.0, np.inf, -np.inf), score)
    return np.where(degenerate, np.nan, score)


def gaussian_log_pdf(t, lam, r):
    """Normal(lam, 2 lam + r^2) in gain units; the degenerate ``lam = r = 0`` is the atom at 0.

    Without readout and at ``lam`` below ~1e-278 the log density of a count far from ``lam`` is
    below -1.8e308: it is ``-inf``, the nearest double (the overflow is expected, not warned).
    """
    var = 2.0 * lam + r * r
    degenerate = var == 0
    v = np.where(degenerate, 1.0, var)
    with np.errstate(over="ignore"):
        log_pdf = -0.5 * (t - lam) ** 2 / v - 0.5 * np.log(2.0 * np.pi * v)
    return np.where(degenerate, np.where(t == 0, 0.0, -np.inf), log_pdf)
