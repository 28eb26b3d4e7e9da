"""The chain-free posteriors in JAX: ``sample_many(..., backend="jax")``.

The same methods as ``bayespsf.inference.batched`` (the Laplace where its pilot's weight SD
passes, Pareto-smoothed importance sampling from the Laplace Student-t where its k-hat passes,
else the emcee chain on the CPU), written as functions of one ROI, mapped over chunks of ROIs
with ``jax.vmap`` and compiled once per draw count, so that a whole dataset runs on one device:

* **Laplace** (``auto``, ``laplace``): ``PILOT`` Gaussian draws scored; the Laplace is taken
  where the normalised weights' SD is at most ``LAPLACE_WEIGHT_SD``; its draws are the first
  ``ess`` (rounded up to a multiple of ``CHAINS``) of ``2 ess`` Gaussian draws inside the
  prior's support.
* **Importance** (``auto``, ``importance``): rounds of Student-t draws (5 degrees of freedom,
  scaled by the Laplace covariance). The first round has ``first_batch(ess)`` draws; a ROI whose
  smoothed weights reach the ESS target is done. A ROI short of it gets a fresh round of twice the
  draws (fixed sizes, so that the programs a dataset needs compile once), up to ``MAX_ROUNDS``
  rounds and ``50 ess`` draws; the
  weights of a round are those of its own draws (a round is independent of the decision to
  run it, so each round's estimate is valid on its own). This replaces the NumPy engine's
  growing batches, which a fixed-shape program cannot hold; the diagnostics and thresholds are
  the same. PSIS is ``arviz_stats``' (Vehtari et al., JMLR 25 (2024)) written in JAX:
  the same tail length, generalised-Pareto fit (Zhang & Stephens, Technometrics 51 (2009),
  with the weakly informative prior on k) and truncation, tested against ``arviz_stats``.
* Draws are resampled systematically to ``CHAINS * floor(ESS / CHAINS)`` equally weighted
  draws, and the summary row (mean, SD, quantiles, SBC rank) is computed on the device.

Random numbers come from JAX's counter-based generator keyed by each ROI's seed
(``sample_many``'s ``molecule_seed``), so a ROI's posterior does not depend on the chunk, the
chunk size or the device; it differs from the NumPy backend's draws by Monte Carlo error only.
"""

from __future__ import annotations

import functools

import numpy as np

from bayespsf.inference.backends import start_jax
from bayespsf.inference.batched import LAPLACE_WEIGHT_SD, MAX_DRAWS_PER_ESS, PILOT, laplace_in_z
from bayespsf.inference.importance import CHAINS, KHAT_MAX, first_batch
from bayespsf.inference.jax_mle import bucket
from bayespsf.inference.jax_model import JaxModel
from bayespsf.inference.psis import psis
from bayespsf.inference.summary import QUANTILES, RANK_DRAWS
from bayespsf.model import LOG_PARAMETERS

MAX_ROUNDS = 3  # importance rounds per ROI before it goes to the chain
DOF = 5.0  # the Student-t proposal's degrees of freedom (``IndependenceMove``'s)
DRAW_PIXELS = {"cpu": 2**23, "gpu": 2**26}  # draws x pixels per device call


def _jax():
    import jax
    import jax.numpy as jnp

    return jax, jnp


def keys(seeds) -> object:
    """One JAX PRNG key per ROI from its 64-bit seed (both halves folded in).

    Parameters
    ----------
    seeds : sequence of int
        Seeds in [0, 2**64).

    Returns
    -------
    jax.Array
        Keys, shape (n,).
    """
    jax, jnp = _jax()
    seeds = np.asarray([int(s) for s in seeds], dtype=np.uint64)
    low = jnp.asarray((seeds & np.uint64(0xFFFFFFFF)).astype(np.uint32))
    high = jnp.asarray((seeds >> np.uint64(32)).astype(np.uint32))

    def one(lo, hi):
        return jax.random.fold_in(jax.random.fold_in(jax.random.key(0), lo), hi)

    return jax.vmap(one)(low, high)


def log_posterior(jm: JaxModel, counts, z, fallback):
    """``Model.log_posterior`` of draws ``z`` (n, k, 6) of ``n`` ROIs ``counts`` (n, roi,
    roi), scored as one array (so that the camera law's rare costly branches run only where
    they are needed: ``jax_laws.log_table``); ``fallback`` (n, 6) is a point inside each ROI's
    prior support, scored in place of draws outside it (whose value is -inf)."""
    _, jnp = _jax()
    logs = jnp.asarray(LOG_PARAMETERS)
    p = z.at[..., logs].set(jnp.exp(z[..., logs]))
    prior = jm.log_prior(p) + z[..., logs].sum(axis=-1)
    inside = jnp.isfinite(prior)
    safe = jnp.where(inside[..., None], p, fallback[:, None, :])
    total = prior + jm.log_likelihood(counts[:, None], safe)
    return jnp.where(inside & jnp.isfinite(total), total, -jnp.inf)


def _resample(key, log_w, n_keep, size: int):
    """Systematic resampling of ``n_keep`` indices (in a random order) into a ``size`` array;
    entries from ``n_keep`` on are -1."""
    jax, jnp = _jax()
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
    jax, jnp = _jax()
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


def _pilot(jm, counts, centre, chol, key, fallback):
    """The Laplace pilot's weight SD (``batched``'s ``_weight_sd``) of each ROI of a chunk."""
    jax, jnp = _jax()
    u = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(k, 1), (PILOT, 6)))(key)
    z = centre[:, None, :] + jnp.einsum("nkj,nij->nki", u, chol)
    ratio = log_posterior(jm, counts, z, fallback) + 0.5 * jnp.sum(u * u, axis=-1)
    finite = jnp.all(jnp.isfinite(ratio), axis=1)
    top = jnp.max(jnp.where(finite[:, None], ratio, 0.0), axis=1, keepdims=True)
    w = jnp.exp(ratio - top)
    sd = jnp.std(w / jnp.mean(w, axis=1, keepdims=True), axis=1, ddof=1)
    return jnp.where(finite, sd, jnp.inf)


def _laplace_draws(jm, centre, chol, key, truth, *, wanted: int):
    """The Laplace's draws inside the prior's support and their summary, for one ROI."""
    jax, jnp = _jax()
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


def _proposal(centre, chol, key, round_, *, size: int):
    """One ROI's ``size`` Student-t draws of an importance round, their log density and the
    keys of the round's resampling and ranks."""
    jax, jnp = _jax()
    key = jax.random.fold_in(key, 10 + round_)
    k_radius, k_normal, k_resample, k_rank = jax.random.split(key, 4)
    radius = jnp.sqrt(DOF / (2.0 * jax.random.gamma(k_radius, DOF / 2.0, (size,))))
    u = radius[:, None] * jax.random.normal(k_normal, (size, 6))
    log_g = -0.5 * (DOF + 6) * jnp.log1p(jnp.sum(u * u, axis=1) / DOF)
    return centre + u @ chol.T, log_g, k_resample, k_rank


def _weighted(z, log_ratio, k_resample, k_rank, truth):
    """One ROI's round from its draws' log ratios: the summary of its resampled draws, k-hat,
    ESS, the number kept and the draws (index -1: not kept)."""
    _, jnp = _jax()
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


def _importance(jm, counts, centre, chol, key, fallback, truth, round_, *, size: int):
    """One importance round of ``size`` Student-t draws for each ROI of a chunk (module
    docstring): per ROI the summary, k-hat, ESS, the number kept and the draws."""
    jax, _ = _jax()
    proposal = functools.partial(_proposal, size=size)
    z, log_g, k_resample, k_rank = jax.vmap(proposal, in_axes=(0, 0, 0, None))(
        centre, chol, key, round_
    )
    log_ratio = log_posterior(jm, counts, z, fallback) - log_g
    return jax.vmap(_weighted)(z, log_ratio, k_resample, k_rank, truth)


def _pearson(jm, counts, theta, law):
    """Pearson's statistic of one ROI at ``theta`` (``bayespsf.inference.gof.pearson``) for a
    camera whose count variance is affine in ``lam``: ``law = (offset, photons_per_adu, v0,
    v1)``, variance ``v0 + v1 lam``."""
    _, jnp = _jax()
    offset, per_adu, v0, v1 = law[0], law[1], law[2], law[3]
    lam = jm.expected(theta)
    square = (counts - (offset + lam / per_adu)) ** 2
    variance = v0 + v1 * lam
    safe = jnp.where(variance > 0, variance, 1.0)
    terms = jnp.where(variance > 0, square / safe, jnp.where(square > 0, jnp.inf, 0.0))
    return jnp.sum(terms)


def pearson(model, counts: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``bayespsf.inference.gof.pearson`` on JAX's device, for the cameras whose count
    variance is affine in the expected photons (Photon, EMCCD); others on the host.

    Parameters
    ----------
    model : Model
        The inference model.
    counts : ndarray, shape (n, roi, roi)
        Validated ROIs in ADU.
    theta : ndarray, shape (n, 6)
        Where each ROI is judged (its maximum-likelihood fit).

    Returns
    -------
    ndarray, shape (n,)
        Pearson's statistic per ROI.
    """
    from bayespsf.inference import gof

    _, jnp = _jax()
    per_adu, offset = model.camera.photons_per_adu()
    v0 = float(model.camera.variance(0.0))
    v1 = float(model.camera.variance(1.0)) - v0
    affine = np.isclose(float(model.camera.variance(100.0)), v0 + 100 * v1, rtol=1e-12)
    if not (affine and np.ndim(per_adu) == 0 and np.ndim(offset) == 0) or len(counts) == 0:
        return gof.pearson(model, counts, theta)
    start_jax()
    law = jnp.asarray([float(offset), float(per_adu), v0, v1])
    (out,) = _chunked(
        _program("pearson"),
        JaxModel.from_model(model),
        [jnp.asarray(counts), jnp.asarray(theta)],
        max(1, 2**22 // model.roi**2),
        law,
    )
    return out


@functools.cache
def _program(kind: str, keep: bool = True, **static):
    """The jitted program ``kind`` over a chunk of ROIs, for the static sizes ``static``;
    without ``keep`` the draws (the last output of ``laplace`` and ``importance``) are not
    returned, so the device never writes them out."""
    jax, _ = _jax()
    if kind in ("pilot", "importance"):  # chunk-level: their likelihood is one array
        function = functools.partial({"pilot": _pilot, "importance": _importance}[kind], **static)
    else:
        function, axes = {
            "laplace": (_laplace_draws, (None, 0, 0, 0, 0)),
            "pearson": (_pearson, (None, 0, 0, None)),
        }[kind]
        function = jax.vmap(functools.partial(function, **static), in_axes=axes)
    if keep:
        return jax.jit(function)
    return jax.jit(lambda *args: (*function(*args)[:-1], None))


def _chunked(program, jm, arrays: list, size: int, *shared) -> list[np.ndarray]:
    """``program(jm, *arrays)`` over the ROIs (the arrays' first axis) in chunks of ``size``
    (the last padded with its first ROI), outputs gathered on the host."""
    _, jnp = _jax()
    n = len(arrays[0])
    size = bucket(n, size)
    parts = []
    for first in range(0, n, size):
        k = min(size, n - first)
        chunk = [a[first : first + k] for a in arrays]
        if k < size:
            chunk = [jnp.concatenate([a, jnp.repeat(a[:1], size - k, axis=0)]) for a in chunk]
        out = program(jm, *chunk, *shared)
        out = out if isinstance(out, tuple) else (out,)
        parts.append([None if o is None else np.asarray(o)[:k] for o in out])
    return [
        None if column[0] is None else np.concatenate(column) for column in zip(*parts, strict=True)
    ]


def posteriors(stack, model, fits, seeds, settings, truths=None, keep_draws: bool = False):
    """The chain-free posteriors of a stack on JAX's device (module docstring).

    Parameters
    ----------
    stack : ndarray, shape (n, roi, roi)
        Validated ROIs in ADU.
    model : Model
        The inference model.
    fits : pandas.DataFrame
        ``fit_mle``'s rows of the stack (with the Laplace columns).
    seeds : sequence of int
        Each ROI's seed.
    settings : Settings
        ``method`` (``auto``, ``laplace`` or ``importance``) and ``ess``.
    truths : ndarray, shape (n, 6), optional
        True parameters: SBC ranks.
    keep_draws : bool
        Also return each ROI's equally weighted draws (to store them).

    Returns
    -------
    dict
        Arrays over the ROIs: ``made`` (bool: a posterior was made; else the chain is needed),
        ``method``, ``why``, ``converged``, ``ess``, ``khat``, ``weight_sd``, ``draws_scored``,
        ``draws`` (the count), ``mean``, ``sd`` (n, 6), ``quantiles`` (n, 9, 6), ``rank``
        (n, 6; -1 where none), and with ``keep_draws`` ``samples``: a list of (k, 6) arrays
        (None where none was made).
    """
    jax, jnp = _jax()
    start_jax()
    jm = JaxModel.from_model(model)
    n, roi = len(stack), model.roi
    platform = jax.devices()[0].platform
    budget = DRAW_PIXELS["cpu" if platform == "cpu" else "gpu"]
    ok = fits["converged"].to_numpy(bool)
    out = _empty(n, keep_draws)
    out["why"][:] = (
        "chain: the maximum-likelihood fit did not converge, so there is no Laplace proposal"
    )
    todo = np.flatnonzero(ok)
    if todo.size == 0:
        return out
    centre, cov = laplace_in_z(fits.iloc[todo], model)
    chol = np.asarray(jnp.linalg.cholesky(jnp.asarray(cov)))
    usable = np.all(np.isfinite(chol), axis=(1, 2))
    out["why"][todo[~usable]] = "chain: the Laplace covariance is not positive definite"
    todo, centre, chol = todo[usable], centre[usable], chol[usable]
    theta = fits[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy(float)[todo]
    fallback = np.clip(theta, *model.prior_bounds())  # inside the prior: scored in its place
    truth = np.full((n, 6), np.nan) if truths is None else np.asarray(truths, float)
    key = keys(np.asarray(seeds)[todo])
    data = [jnp.asarray(stack[todo]), jnp.asarray(centre), jnp.asarray(chol), key]
    left = np.ones(len(todo), bool)
    if settings.method in ("auto", "laplace"):
        size = max(1, budget // (PILOT * roi * roi))
        (weight_sd,) = _chunked(_program("pilot"), jm, [*data, jnp.asarray(fallback)], size)
        out["weight_sd"][todo] = weight_sd
        passed = weight_sd <= LAPLACE_WEIGHT_SD
        take = passed if settings.method == "auto" else np.ones(len(todo), bool)
        rejected = todo[~take]
        out["why"][rejected] = [
            f"Laplace rejected (pilot weight SD {v:.3g} > {LAPLACE_WEIGHT_SD})"
            for v in weight_sd[~take]
        ]
        wanted = CHAINS * int(np.ceil(settings.ess / CHAINS))
        if take.any():
            pick = np.flatnonzero(take)
            results = _chunked(
                _program("laplace", keep_draws, wanted=wanted),
                jm,
                [data[1][pick], data[2][pick], data[3][pick], jnp.asarray(truth[todo[pick]])],
                max(1, budget // (2 * wanted * 6)),
            )
            rows = todo[pick]
            _store(out, rows, results, keep_draws)
            out["method"][rows] = "laplace"
            out["draws_scored"][rows] = PILOT
            out["ess"][rows] = results[-2]
            out["converged"][rows] = passed[pick]
            out["why"][rows] = [
                f"Laplace (pilot weight SD {v:.3g} {'<=' if p else '>'} {LAPLACE_WEIGHT_SD})"
                for v, p in zip(weight_sd[pick], passed[pick], strict=True)
            ]
        left = ~take
    if settings.method in ("auto", "importance"):
        _importance_rounds(
            jm, out, todo, left, data, fallback, truth, settings, budget, roi, keep_draws
        )
    return out


def _importance_rounds(jm, out, todo, left, data, fallback, truth, settings, budget, roi, keep):
    """Importance rounds for the ROIs ``todo[left]`` (module docstring), filling ``out``."""
    _, jnp = _jax()
    size = first_batch(settings.ess)
    limit = int(MAX_DRAWS_PER_ESS * settings.ess)
    pending = np.flatnonzero(left)
    scored = np.zeros(len(todo), int)
    for round_ in range(MAX_ROUNDS):
        if pending.size == 0:
            break
        results = _chunked(
            _program("importance", keep, size=size),
            jm,
            [data[0][pending], data[1][pending], data[2][pending], data[3][pending],
             jnp.asarray(fallback[pending]), jnp.asarray(truth[todo[pending]])],
            max(1, budget // (size * roi * roi)),
            jnp.asarray(round_),
        )  # fmt: skip
        khat, ess = results[-4], results[-3]
        scored[pending] += size
        done = (ess >= settings.ess) & (khat <= KHAT_MAX)
        rows = todo[pending]
        before = [w + "; " if np.isfinite(s) else "" for w, s in
                  zip(out["why"][rows], out["weight_sd"][rows], strict=True)]  # fmt: skip
        facts = [
            f"k-hat {k:.2f}, ESS {e:.0f} of {size} draws" for k, e in zip(khat, ess, strict=True)
        ]
        out["khat"][rows], out["draws_scored"][rows] = khat, scored[pending]
        good = np.flatnonzero(done)
        _store(
            out,
            rows[good],
            [r[good] for r in results[:4]]
            + [results[-2][good], None if results[-1] is None else results[-1][good]],
            keep,
        )
        out["method"][rows[good]] = "importance"
        out["ess"][rows[good]] = ess[good]
        out["converged"][rows[good]] = True
        out["why"][rows[good]] = [f"{before[i]}importance sampling ({facts[i]})" for i in good]
        failed = ~done & ((khat > KHAT_MAX) | ~np.isfinite(khat) | (round_ == MAX_ROUNDS - 1))
        out["why"][rows[failed]] = [
            f"{before[i]}chain: importance sampling failed ({facts[i]})"
            for i in np.flatnonzero(failed)
        ]
        again = ~done & ~failed
        if not again.any():
            break
        size = min(limit, 2 * size)  # fixed sizes: the programs a dataset needs compile once
        pending = pending[again]


def _store(out, rows, results, keep_draws) -> None:
    """Copy a method's per-ROI summary (mean, sd, quantiles, rank, ..., count, draws)."""
    mean, sd, quantiles, rank = results[:4]
    count, draws = results[-2], results[-1]
    out["made"][rows] = True
    out["mean"][rows], out["sd"][rows] = mean, sd
    out["quantiles"][rows], out["rank"][rows] = quantiles, rank
    out["draws"][rows] = count
    if keep_draws:
        for r, d, c in zip(rows, draws, count, strict=True):
            out["samples"][r] = d[: int(c)]


def _empty(n: int, keep_draws: bool) -> dict:
    out = {
        "made": np.zeros(n, bool),
        "method": np.full(n, "mcmc", dtype=object),
        "why": np.full(n, "", dtype=object),
        "converged": np.zeros(n, bool),
        "ess": np.full(n, np.nan),
        "khat": np.full(n, np.nan),
        "weight_sd": np.full(n, np.nan),
        "draws_scored": np.zeros(n, int),
        "draws": np.zeros(n, int),
        "mean": np.full((n, 6), np.nan),
        "sd": np.full((n, 6), np.nan),
        "quantiles": np.full((n, len(QUANTILES), 6), np.nan),
        "rank": np.full((n, 6), -1),
    }
    if keep_draws:
        out["samples"] = [None] * n
    return out


__all__ = ["DOF", "MAX_ROUNDS", "keys", "log_posterior", "pearson", "posteriors"]
