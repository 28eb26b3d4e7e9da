"""Pareto-smoothed importance sampling in JAX, as ``arviz_stats`` computes it.

``psis`` is ``arviz_stats.base.array_stats.psislw`` (Vehtari, Simpson, Gelman, Yao & Gabry,
JMLR 25 (2024)) for one vector of log ratios with ``r_eff = 1``, written for ``jax.vmap``: the
same tail length (``3 sqrt(k)`` draws above 225 draws, else ``k / 5``), the same generalised
Pareto fit (Zhang & Stephens, Technometrics 51 (2009), with the weakly informative prior on the
shape), the same smoothing of the tail by the fitted quantiles, truncated at the largest raw
weight (``tests/inference/test_jax_backend.py`` holds the two to 1e-9).
"""

from __future__ import annotations

import math


def _jax():
    import jax
    import jax.numpy as jnp

    return jax, jnp


def _gpdfit(x):
    """``arviz_stats``' generalised-Pareto fit of sorted exceedances ``x`` (m,): (k, sigma);
    k is NaN where the first quartile is not above the minimum, inf where it is undefined."""
    _, jnp = _jax()
    n = x.shape[0]
    m_est = 30 + int(n**0.5)
    xstar = x[int(n / 4 + 0.5) - 1]
    b = 1 - jnp.sqrt(m_est / (jnp.arange(1, m_est + 1, dtype=float) - 0.5))
    b = b / (3 * xstar) + 1 / x[-1]
    k = jnp.mean(jnp.log1p(-b[:, None] * x[None, :]), axis=1)
    scale = n * (jnp.log(-b / k) - k - 1)
    w = jnp.exp(scale - _logsumexp(scale))
    w = jnp.where(w >= 10 * jnp.finfo(float).eps, w, 0.0)
    b_post = jnp.sum(b * w) / jnp.sum(w)
    kappa = jnp.mean(jnp.log1p(-b_post * x))
    sigma = -kappa / b_post
    kappa = (n * kappa + 10 * 0.5) / (n + 10)
    kappa = jnp.where(jnp.isnan(kappa), jnp.inf, kappa)
    return jnp.where(xstar <= x[0], jnp.nan, kappa), sigma


def _logsumexp(x):
    _, jnp = _jax()
    top = jnp.max(x)
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    return top + jnp.log(jnp.sum(jnp.exp(x - top)))


def psis(log_ratio):
    """Pareto-smoothed normalised log weights and k-hat of one ROI's ``log_ratio`` (k,), as
    ``arviz_stats.base.array_stats.psislw`` computes them (``r_eff = 1``).

    Parameters
    ----------
    log_ratio : jax.Array, shape (k,)
        ``log pi(z) - log g(z)`` of the draws, -inf where the posterior is 0.

    Returns
    -------
    log_weights : jax.Array, shape (k,)
        Normalised log weights.
    khat : jax.Array
        The Pareto shape estimate (NaN or inf where the fit fails).
    """
    _, jnp = _jax()
    k = log_ratio.shape[0]
    tail = math.floor(3 * k**0.5) if k > 225 else k // 5
    x = log_ratio - jnp.max(log_ratio)
    order = jnp.argsort(x)
    ordered = x[order]
    top, cutoff = ordered[k - tail :], ordered[k - tail - 1]
    khat, sigma = _gpdfit(jnp.exp(top) - jnp.exp(cutoff))
    probs = (jnp.arange(tail) + 0.5) / tail
    mu = jnp.exp(cutoff)
    safe_k = jnp.where(jnp.isfinite(khat) & (khat != 0), khat, 1.0)
    quantile = jnp.where(
        khat == 0,
        mu - sigma * jnp.log1p(-probs),
        mu + sigma * jnp.expm1(-safe_k * jnp.log1p(-probs)) / safe_k,
    )
    quantile = jnp.where(sigma > 0, quantile, jnp.nan)
    smoothed = jnp.minimum(jnp.log(quantile), top[-1])
    smooth = jnp.isfinite(khat)
    x = x.at[order[k - tail :]].set(jnp.where(smooth, smoothed, top))
    return x - _logsumexp(x), khat


__all__ = ["psis"]
