"""The device programs of the JAX backend's posteriors (``bayespsf.inference.jax_sampling``).

Pure ``jax.numpy`` functions of a chunk of ROIs (``pilot``, ``gaussian``, ``importance``) or of
one ROI (``laplace``, ``pearson``, mapped with ``jax.vmap``), which ``jax_sampling`` compiles and
runs chunk by chunk. The scoring programs take ``exact`` (static): without it a draw's
log-likelihood is the camera law interpolated per pixel (``bayespsf.inference.jax_fused``), and
the program's first output says per ROI whether every interpolant passed its check; with it, the
law itself at every pixel and draw (every ROI usable), for the ROIs that failed.

Random numbers: each ROI's key is folded in with a fixed number per use (1 the pilot, 2 and 3
the Laplace's draws and ranks, 4 the Gaussian round, ``10 + round`` the Student-t rounds), so a
program regenerates the draws of an earlier one (the Gaussian round resamples the pilot's draws
with its own) and a ROI's draws do not depend on the chunk or the device.
"""

from __future__ import annotations

import functools

from bayespsf.inference import jax_fused
from bayespsf.inference.backends import jax_modules
from bayespsf.inference.batched import PILOT
from bayespsf.inference.importance import CHAINS
from bayespsf.inference.psis import psis
from bayespsf.inference.summary import QUANTILES, RANK_DRAWS
from bayespsf.model import LOG_PARAMETERS

DOF = 5.0  # the Student-t proposal's degrees of freedom (``IndependenceMove``'s)


def log_posterior(jm, counts, z, fallback, exact: bool = False):
    """``Model.log_posterior`` of draws ``z`` (n, k, 6) of ``n`` ROIs ``counts`` (n, roi, roi),
    scored as one array.

    Parameters
    ----------
    jm : JaxModel
        The model.
    counts : jax.Array, shape (n, roi, roi)
        Each ROI's counts.
    z : jax.Array, shape (n, k, 6)
        Draws in sampling coordinates.
    fallback : jax.Array, shape (n, 6)
        A point inside each ROI's prior support, scored in place of draws outside it (whose
        value is -inf).
    exact : bool
        Score with the law itself at every pixel and draw; else interpolated
        (``jax_fused``).

    Returns
    -------
    log_posterior : jax.Array, shape (n, k)
        Up to the constant of ``Model.log_posterior``; -inf outside the prior's support.
    usable : jax.Array of bool, shape (n,)
        Per ROI, whether ``log_posterior`` may be used (always with ``exact``).
    """
    _, jnp = jax_modules()
    logs = jnp.asarray(LOG_PARAMETERS)
    p = z.at[..., logs].set(jnp.exp(z[..., logs]))
    prior = jm.log_prior(p) + z[..., logs].sum(axis=-1)
    inside = jnp.isfinite(prior)
    safe = jnp.where(inside[..., None], p, fallback[:, None, :])
    if exact:
        likelihood, usable = jm.log_likelihood(counts[:, None], safe), jnp.ones(len(z), bool)
    else:
        likelihood, usable = jax_fused.log_likelihood(jm, counts, safe)
    total = prior + likelihood
    return jnp.where(inside & jnp.isfinite(total), total, -jnp.inf), usable


def _resample(key, log_w, n_keep, size: int):
    """Systematic resampling of ``n_keep`` indices (in a random order) into a ``size`` array;
    entries from ``n_keep`` on are -1."""
    jax, jnp = jax_modules()
    k_offset, k_order = jax.random.split(key)
    w = jnp.exp(log_w)
    j = jnp.arange(size)
    positions = (jax.random.uniform(k_offset) + j) / jnp.maximum(n_keep, 1)
    index = jnp.minimum(jnp.searchsorted(jnp.cumsum(w), positions), log_w.shape[0] - 1)
    valid = j < n_keep
    shuffle = jnp.argsort(jnp.where(valid, jax.random.uniform(k_order, (size,)), jnp.inf))
    return jnp.where(valid, index[shuffle], -1)


def _summary(key, draws, valid, truth):
    """Mean, SD (ddof 1), ``QUANTILES`` (NumPy's linear interpolation) and the SBC rank over
    ``RANK_DRAWS`` random valid draws, of one ROI's draws (size, 6) where ``valid``."""
    jax, jnp = jax_modules()
    n = jnp.sum(valid)
    x = jnp.where(valid[:, None], draws, 0.0)
    mean = x.sum(axis=0) / n
    sd = jnp.sqrt(jnp.sum(jnp.where(valid[:, None], (draws - mean) ** 2, 0.0), axis=0) / (n - 1))
    ordered = jnp.sort(jnp.where(valid[:, None], draws, jnp.inf), axis=0)
    h = (n - 1) * jnp.asarray(QUANTILES)
    low = jnp.floor(h).astype(int)
    high = jnp.minimum(low + 1, n - 1)
    frac = (h - low)[:, None]
    quantiles = ordered[low] * (1 - frac) + ordered[high] * frac
    pick = jnp.argsort(jnp.where(valid, jax.random.uniform(key, valid.shape), jnp.inf))
    rank = jnp.sum(draws[pick[:RANK_DRAWS]] < truth, axis=0)
    return mean, sd, quantiles, jnp.where(n >= RANK_DRAWS, rank, -1)


def _gaussian_draws(centre, chol, key, fold: int, size: int):
    """``size`` draws of each ROI's Laplace Gaussian (key folded with ``fold``) and their log
    density up to a constant."""
    jax, jnp = jax_modules()
    u = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(k, fold), (size, 6)))(key)
    return centre[:, None, :] + jnp.einsum("nkj,nij->nki", u, chol), -0.5 * jnp.sum(u * u, -1)


def pilot(jm, counts, centre, chol, key, fallback, *, exact: bool):
    """The Laplace pilot of each ROI of a chunk: ``PILOT`` draws of its Gaussian scored.

    Returns
    -------
    usable : jax.Array of bool, shape (n,)
        As ``log_posterior``'s.
    weight_sd : jax.Array, shape (n,)
        The SD of the weights normalised to mean 1 (``batched``'s); inf where a weight is 0.
    log_ratio : jax.Array, shape (n, PILOT)
        Log posterior minus log proposal density per draw (continued by ``gaussian``).
    """
    _, jnp = jax_modules()
    z, log_g = _gaussian_draws(centre, chol, key, 1, PILOT)
    scored, usable = log_posterior(jm, counts, z, fallback, exact)
    ratio = scored - log_g
    finite = jnp.all(jnp.isfinite(ratio), axis=1)
    top = jnp.max(jnp.where(finite[:, None], ratio, 0.0), axis=1, keepdims=True)
    w = jnp.exp(ratio - top)
    sd = jnp.std(w / jnp.mean(w, axis=1, keepdims=True), axis=1, ddof=1)
    return usable, jnp.where(finite, sd, jnp.inf), ratio


def laplace(jm, centre, chol, key, truth, *, wanted: int):
    """The Laplace's draws inside the prior's support and their summary, for one ROI."""
    jax, jnp = jax_modules()
    u = jax.random.normal(jax.random.fold_in(key, 2), (2 * wanted, 6))
    z = centre + u @ chol.T
    logs = jnp.asarray(LOG_PARAMETERS)
    p = z.at[:, logs].set(jnp.exp(z[:, logs]))
    inside = jnp.isfinite(jm.log_prior(p))
    first = jnp.argsort(~inside, stable=True)[:wanted]
    count = CHAINS * (jnp.minimum(jnp.sum(inside), wanted) // CHAINS)
    valid = jnp.arange(wanted) < count
    draws = p[first]
    return (*_summary(jax.random.fold_in(key, 3), draws, valid, truth), count, draws)


def _weighted(z, log_ratio, k_resample, k_rank, truth):
    """One ROI's draws from their log ratios: the summary of its resampled draws, k-hat,
    ESS, the number kept and the draws (index -1: not kept)."""
    _, jnp = jax_modules()
    size = z.shape[0]
    log_w, khat = psis(log_ratio, xp=jnp)
    w = jnp.exp(log_w)
    ess = 1.0 / jnp.sum(w * w)
    ess = jnp.where(jnp.isfinite(khat) & jnp.isfinite(ess), ess, 0.0)
    keep = CHAINS * jnp.floor(ess / CHAINS).astype(int)
    index = _resample(k_resample, log_w, keep, size)
    logs = jnp.asarray(LOG_PARAMETERS)
    chosen = z[jnp.maximum(index, 0)]
    draws = chosen.at[:, logs].set(jnp.exp(chosen[:, logs]))
    return (*_summary(k_rank, draws, index >= 0, truth), khat, ess, keep, draws)


def gaussian(jm, counts, centre, chol, key, fallback, truth, pilot_ratio, *, size, exact):
    """Importance sampling from each ROI's Laplace Gaussian, continuing its pilot: ``size``
    more draws, weighted with the pilot's (``pilot_ratio``, regenerated draws).

    Returns
    -------
    tuple
        ``usable``, then per ROI the summary (mean, SD, quantiles, ranks), k-hat, ESS, the
        number of draws kept and the draws (index -1: not kept).
    """
    jax, jnp = jax_modules()
    z_pilot, _ = _gaussian_draws(centre, chol, key, 1, PILOT)
    z, log_g = _gaussian_draws(centre, chol, key, 4, size)
    scored, usable = log_posterior(jm, counts, z, fallback, exact)
    ratio = jnp.concatenate([pilot_ratio, scored - log_g], axis=1)
    split = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, 5)))(key)
    k_resample, k_rank = split[:, 0], split[:, 1]
    z = jnp.concatenate([z_pilot, z], axis=1)
    return usable, *jax.vmap(_weighted)(z, ratio, k_resample, k_rank, truth)


def _student_t(centre, chol, key, round_, *, size: int):
    """One ROI's ``size`` Student-t draws of an importance round, their log density and the
    keys of the round's resampling and ranks."""
    jax, jnp = jax_modules()
    key = jax.random.fold_in(key, 10 + round_)
    k_radius, k_normal, k_resample, k_rank = jax.random.split(key, 4)
    radius = jnp.sqrt(DOF / (2.0 * jax.random.gamma(k_radius, DOF / 2.0, (size,))))
    u = radius[:, None] * jax.random.normal(k_normal, (size, 6))
    log_g = -0.5 * (DOF + 6) * jnp.log1p(jnp.sum(u * u, axis=1) / DOF)
    return centre + u @ chol.T, log_g, k_resample, k_rank


def importance(jm, counts, centre, chol, key, fallback, truth, round_, *, size, exact):
    """One importance round of ``size`` Student-t draws for each ROI of a chunk.

    Returns
    -------
    tuple
        As ``gaussian``'s.
    """
    jax, _ = jax_modules()
    proposal = functools.partial(_student_t, size=size)
    z, log_g, k_resample, k_rank = jax.vmap(proposal, in_axes=(0, 0, 0, None))(
        centre, chol, key, round_
    )
    scored, usable = log_posterior(jm, counts, z, fallback, exact)
    return usable, *jax.vmap(_weighted)(z, scored - log_g, k_resample, k_rank, truth)


def pearson(jm, counts, theta, law):
    """Pearson's statistic of one ROI at ``theta`` (``bayespsf.inference.gof.pearson``) for a
    camera whose count variance is affine in ``lam``: ``law = (offset, photons_per_adu, v0,
    v1)``, variance ``v0 + v1 lam``."""
    _, jnp = jax_modules()
    offset, per_adu, v0, v1 = law[0], law[1], law[2], law[3]
    lam = jm.expected(theta)
    square = (counts - (offset + lam / per_adu)) ** 2
    variance = v0 + v1 * lam
    safe = jnp.where(variance > 0, variance, 1.0)
    terms = jnp.where(variance > 0, square / safe, jnp.where(square > 0, jnp.inf, 0.0))
    return jnp.sum(terms)


__all__ = ["DOF", "gaussian", "importance", "laplace", "log_posterior", "pearson", "pilot"]
