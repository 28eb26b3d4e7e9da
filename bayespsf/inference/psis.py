"""Pareto-smoothed importance sampling over a batch of weight vectors, in NumPy or JAX.

``psis`` is ``arviz_stats.base.array_stats.psislw`` (Vehtari, Simpson, Gelman, Yao & Gabry,
JMLR 25 (2024)) with ``r_eff = 1``, applied to the last axis of an array of log ratios with any
leading batch shape: the same tail length (``3 sqrt(k)`` draws above 225 draws, else ``k / 5``),
the same generalised Pareto fit (Zhang & Stephens, Technometrics 51 (2009), with the weakly
informative prior on the shape), the same smoothing of the tail by the fitted quantiles,
truncated at the largest raw weight (``tests/inference/test_psis.py`` holds the two to 1e-9).

One implementation serves both array libraries: it uses only operations that NumPy and
``jax.numpy`` share with the same meaning (no in-place assignment; the tail is smoothed in sorted
order and put back with the inverse permutation), so ``psis(x, xp=jax.numpy)`` compiles with
``jax.jit`` and maps with ``jax.vmap``. This module imports NumPy only.

Non-finite values follow ``arviz_stats``: a draw with log ratio -inf (outside the posterior's
support) has log weight -inf and enters the tail fit as a zero weight; k-hat is NaN where the
tail's exceedances have their first quartile at their minimum (no generalised Pareto fit), inf
where the shape estimate is NaN, and the tail is smoothed only where k-hat is finite; a row with
a NaN or +inf ratio, or with every ratio -inf, has NaN weights and a k-hat of NaN or inf. One
case differs: where the tail's largest and smallest log ratios differ by less than the smallest
normal double, ``arviz_stats`` raises ``ValueError`` for the whole call, ``psis`` returns k-hat
NaN and the unsmoothed normalised weights for that row only.

Tied ratios in the tail (in practice: more than ``k - tail`` draws outside the support) get
the smoothed values in their sort's order. NumPy's sort is ``arviz_stats``', so NumPy matches it
draw by draw; JAX's sort is stable, so with JAX the tied draws get the same values in another
order.
"""

from __future__ import annotations

import math

import numpy as np

PRIOR_BS = 3  # the fit's grid of b over the first quartile, as arviz_stats
PRIOR_K = 10  # weight (in draws) of the weakly informative prior k ~ 0.5
MIN_TAIL = 5  # the fewest tail draws arviz_stats fits
BLOCK_BYTES = 2**22  # NumPy's working set per block of rows (``psis``)


def tail_length(draws: int) -> int:
    """Draws in the smoothed tail of ``draws`` log ratios (``r_eff = 1``).

    Parameters
    ----------
    draws : int
        Number of draws ``k``.

    Returns
    -------
    int
        ``floor(3 sqrt(k))`` above 225 draws, else ``floor(k / 5)``.
    """
    return math.floor(3 * draws**0.5) if draws > 225 else draws // 5


def _logsumexp(a, xp):
    """``scipy.special.logsumexp`` over the last axis: -inf where every entry is -inf, inf
    where one is inf, NaN where one is NaN."""
    top = xp.max(a, axis=-1, keepdims=True)
    top = xp.where(xp.isfinite(top), top, 0.0)
    return top[..., 0] + xp.log(xp.sum(xp.exp(a - top), axis=-1))


def _gpdfit(x, xp):
    """``arviz_stats``' generalised Pareto fit of sorted exceedances ``x`` (..., n): k-hat and
    sigma (...); (NaN, NaN) where the first quartile is not above the minimum, (inf, NaN)
    where the shape estimate is NaN."""
    n = x.shape[-1]
    m_est = 30 + int(n**0.5)
    xstar = x[..., int(n / 4 + 0.5) - 1]
    grid = 1 - xp.sqrt(m_est / (xp.arange(1, m_est + 1, dtype=x.dtype) - 0.5))
    b = grid / (PRIOR_BS * xstar[..., None]) + 1 / x[..., -1:]  # (..., m_est)
    k = xp.mean(xp.log1p(-b[..., :, None] * x[..., None, :]), axis=-1)
    scale = n * (xp.log(-b / k) - k - 1)
    w = xp.exp(scale - _logsumexp(scale, xp)[..., None])
    w = xp.where(w >= 10 * xp.finfo(x.dtype).eps, w, 0.0)  # negligible (or NaN) weights out
    total = xp.sum(w, axis=-1)
    kept = total > 0
    # every weight out: arviz_stats' posterior mean of b is the sum of an empty array, 0
    b_post = xp.where(kept, xp.sum(b * w, axis=-1) / xp.where(kept, total, 1.0), 0.0)
    kappa = xp.mean(xp.log1p(-b_post[..., None] * x), axis=-1)
    sigma = -kappa / b_post
    kappa = (n * kappa + PRIOR_K * 0.5) / (n + PRIOR_K)
    undefined = xp.isnan(kappa)
    kappa = xp.where(undefined, xp.inf, kappa)
    sigma = xp.where(undefined, xp.nan, sigma)
    no_fit = xstar <= x[..., 0]
    return xp.where(no_fit, xp.nan, kappa), xp.where(no_fit, xp.nan, sigma)


def _inverse(order, xp):
    """The inverse of the permutations ``order`` along the last axis. A stable sort of 16-bit
    indices is a radix sort in NumPy, a few times faster than its sort of 64-bit ones."""
    if order.shape[-1] <= np.iinfo(np.int16).max:
        return xp.argsort(order.astype(xp.int16), axis=-1, stable=True)
    return xp.argsort(order, axis=-1)


def psis(log_ratio, xp=np):
    """Pareto-smoothed normalised log weights and k-hat of each row of ``log_ratio``, as
    ``arviz_stats.base.array_stats.psislw(-log_ratio)`` computes them (``r_eff = 1``).

    Parameters
    ----------
    log_ratio : array_like, shape (..., k)
        ``log pi(z) - log g(z)`` of the draws along the last axis, -inf where the posterior is
        0; any leading batch shape.
    xp : module, optional
        The array library: ``numpy`` (default) or ``jax.numpy`` (then the function can be
        traced by ``jax.jit`` and ``jax.vmap``; float64 needs JAX's x64 mode).

    Returns
    -------
    log_weights : array, shape (..., k)
        Normalised log weights (``logsumexp`` 0 along the last axis).
    khat : array, shape (...)
        The Pareto shape estimate of each row: NaN where the tail admits no generalised Pareto
        fit, inf where the fit is undefined (module docstring).

    Raises
    ------
    ValueError
        If ``k`` gives a tail of fewer than 5 draws (``k < 25``), as ``arviz_stats``.
    """
    x = xp.asarray(log_ratio, dtype=float)
    k = x.shape[-1]
    tail = tail_length(k)
    if tail < MIN_TAIL:
        raise ValueError(f"{k} draws give a tail of {tail}; PSIS needs at least {MIN_TAIL}")
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # NumPy: blocks of rows, so that the tail fit's (rows, grid, tail) array stays a few
        # MB (one large array costs more in page faults and cache misses than the loop)
        block = max(1, BLOCK_BYTES // (8 * tail * (30 + int(tail**0.5))))
        if xp is not np or x.size <= block * k:
            return _smooth(x, tail, xp)
        rows = x.reshape(-1, k)
        parts = [_smooth(rows[i : i + block], tail, np) for i in range(0, len(rows), block)]
        log_w = np.concatenate([part[0] for part in parts]).reshape(x.shape)
        return log_w, np.concatenate([part[1] for part in parts]).reshape(x.shape[:-1])


def _smooth(x, tail: int, xp):
    """``psis`` of ``x`` (..., k) with a tail of ``tail`` draws, under ``np.errstate``."""
    k = x.shape[-1]
    x = x - xp.max(x, axis=-1, keepdims=True)
    order = xp.argsort(x, axis=-1)
    ordered = xp.take_along_axis(x, order, axis=-1)
    top = ordered[..., k - tail :]
    largest = top[..., -1:]  # the tail's maximum (NaN where a ratio is NaN)
    cutoff = xp.exp(ordered[..., k - tail - 1 : k - tail])
    khat, sigma = _gpdfit(xp.exp(top) - cutoff, xp)
    flat = xp.abs(largest[..., 0] - top[..., 0]) < xp.finfo(x.dtype).tiny
    khat = xp.where(flat, xp.nan, khat)  # arviz_stats raises ValueError

    probs = (xp.arange(tail, dtype=x.dtype) + 0.5) / tail
    kappa, sigma = khat[..., None], sigma[..., None]
    nonzero = xp.where(kappa == 0, 1.0, kappa)
    quantile = xp.where(
        kappa == 0,
        cutoff - sigma * xp.log1p(-probs),
        cutoff + sigma * xp.expm1(-nonzero * xp.log1p(-probs)) / nonzero,
    )
    smoothed = xp.log(xp.where(sigma <= 0, xp.nan, quantile))
    smoothed = xp.where(smoothed > largest, largest, smoothed)
    top = xp.where(xp.isfinite(kappa), smoothed, top)
    ordered = xp.concatenate([ordered[..., : k - tail], top], axis=-1)
    # the sorted row's last entry is its maximum (the smoothed tail is increasing and above
    # the cutoff), the shift ``_logsumexp`` takes; a row with a NaN is NaN either way
    shift = xp.where(xp.isfinite(top[..., -1:]), top[..., -1:], 0.0)
    norm = shift + xp.log(xp.sum(xp.exp(ordered - shift), axis=-1, keepdims=True))
    return xp.take_along_axis(ordered - norm, _inverse(order, xp), axis=-1), khat


__all__ = ["MIN_TAIL", "psis", "tail_length"]
