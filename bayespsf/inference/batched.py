"""Posteriors of many ROIs at once, without a Markov chain where a diagnostic allows it.

Every ROI of a stack starts from its maximum-likelihood fit and Laplace approximation
(``fit_mle``'s stack engine: the fit and the inverse observed information ``C``), in the
sampling coordinates ``z = (x0, y0, log s_x, log s_y, log N, b)`` of ``Model.log_posterior``.
Three methods use it, cheapest first:

``laplace``
    Draws from the Gaussian ``N(z_hat, C_z)``. No likelihood evaluation beyond the fit.
``importance``
    Pareto-smoothed importance sampling from the Laplace Student-t
    (``bayespsf.inference.importance``): exact where its k-hat is <= 0.7 and the ESS target is
    reached within ``50 * ess`` draws.
``auto``
    Per ROI, the cheapest whose diagnostic passes. A pilot of ``PILOT`` draws from the Laplace
    Gaussian is scored; with ``w = pi / g`` the importance weights normalised to mean 1, the
    Laplace is used when their standard deviation is at most ``LAPLACE_WEIGHT_SD``. That bound
    is what makes the Laplace's error small for every summary at once: by Cauchy-Schwarz,
    ``|E_pi[f] - E_g[f]| = |Cov_g(w, f)| <= sd(w) sd_g(f)``, so with sd(w) <= 0.05 every
    posterior probability is within ``0.05 sqrt(p (1 - p))`` of the Laplace's (0.8 percentage
    points at a 2.5% tail), every mean within 0.05 SD, every variance within
    ``0.05 sqrt(2)`` relative (the Gaussian's ``sd((z - mu)^2) = sqrt(2) var``). The pilot's
    sd(w) is itself an estimate (relative error ~ ``1 / sqrt(2 PILOT)``, 9%). Otherwise, where
    the pilot's weight SD is at most ``GAUSSIAN_WEIGHT_SD``, importance sampling from that
    Gaussian, continuing its pilot: near the Laplace its ESS per draw, ``1 / (1 + sd(w)**2)``,
    beats the Student-t's (~0.97 against ~0.77 on emccd-typical at N = 1 000, where every
    ROI's pilot SD is 0.12-0.2), and a posterior with heavier tails than the Gaussian shows as
    k-hat above 0.7. Where the pilot SD is larger (the Gaussian's ESS per draw below 0.5) or
    the Gaussian run fails, importance sampling from the Student-t, as ``importance``; where
    that fails too, the chain (``bayespsf.sample_posterior``'s emcee run), which the callers
    run one ROI at a time.

Where importance sampling from the Laplace Student-t fails (``importance`` and ``auto``), up to
``ADAPT_ROUNDS`` further runs each draw from a mixture of a Student-t fitted to the previous
run's weighted draws (its share ``ADAPT_SHARE``) and the Laplace Student-t (the rest, which
keeps the weights bounded where the fitted part is too narrow), with their own random streams;
each is judged like the first (k-hat, ESS), and only its own draws make the posterior, so it is
ordinary importance sampling from a proposal that earlier draws chose (``importance.
DefensiveMixture``). A faint spot's posterior is skewed in its widths and photons, which the
Laplace misses: on emccd-typical at N = 250 they took 15 of the 16 ROIs in 2 000 that the
Student-t left to the chain, each in about 600-1 200 draws where its chain took ~2 s.

Draws of all the ROIs being worked on are scored together (``bayespsf.inference.fused``: the
camera law interpolated per pixel over each ROI's batch, checked, within 1e-6 in log p per
pixel of ``Model.log_posterior``): the cost of a stack is a few compiled passes, not a Python
loop of small calls. Each ROI keeps its own random
streams, spawned from its seed exactly as ``sample_posterior`` spawns them, so a ROI's
posterior is the same whether it is sampled alone or in any stack
(``tests/inference/test_stack_posterior.py``).
"""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np

from bayespsf.inference import fused
from bayespsf.inference.gof import pearson_fit
from bayespsf.inference.importance import (
    CHAINS,
    KHAT_MAX,
    DefensiveMixture,
    GaussianProposal,
    ImportanceRun,
    IndependenceMove,
    fitted_t,
    psis,
    systematic_resample,
)
from bayespsf.inference.result_file import molecule_attributes
from bayespsf.psf import PARAMETER_NAMES

PILOT = 64  # Laplace draws scored to judge the Laplace (auto)
LAPLACE_WEIGHT_SD = 0.05  # the largest pilot weight SD at which auto uses the Laplace
GAUSSIAN_WEIGHT_SD = 1.0  # ... and at which it goes on with the Laplace Gaussian as proposal
GAUSSIAN_MARGIN = 1.05  # its pilot predicts its ESS per draw, 1 / (1 + sd(w)**2), closely
MAX_DRAWS_PER_ESS = 50  # an importance run scores at most this many draws per unit of ESS
ADAPT_ROUNDS = 3  # runs from proposals fitted to the last run's draws, where the t fails
ADAPT_SHARE = 0.7  # the fitted t's share of their mixture; the Laplace t has the rest


def laplace_in_z(fits, model) -> tuple[np.ndarray, np.ndarray]:
    """Centres ``(n, 6)`` and covariances ``(n, 6, 6)`` of the Laplace approximations of
    ``fits`` (``fit_mle`` rows with ``sd_<p>`` and ``corr_<p>_<q>``) in sampling coordinates.

    A centre outside the prior's support (an informative prior that excludes the MLE) is moved
    to its edge; the covariance maps by the Jacobian of the log of s_x, s_y and N.
    """
    from bayespsf.inference.estimators import covariance

    low, high = model.prior_bounds()  # the support includes its ends
    centre = np.clip(fits[list(PARAMETER_NAMES)].to_numpy(float), low, high)
    to_z = np.ones_like(centre)
    to_z[:, 2:5] = 1.0 / centre[:, 2:5]
    cov = covariance(fits) * to_z[:, :, None] * to_z[:, None, :]
    return model.to_unconstrained(centre), cov


STREAMS = {"start": (0,), "chain": (1,), "draws": (1, 0), "resample": (1, 1), "laplace": (1, 2)}
STREAMS["adapt"] = (1, 3)


def random_stream(seed: int, name: str, *child: int) -> np.random.SeedSequence:
    """One seed sequence of a ROI's sampling, as ``sample_posterior`` spawns them from its
    seed: ``start`` (the walkers' start) and ``chain`` are the seed's two children, ``draws``
    (importance draws), ``resample``, ``laplace`` and ``adapt`` the chain's four
    (``STREAMS``: each one's spawn key); ``child``: a descendant of that one (``adapt``'s
    round). Made directly from its key, the same sequence as by spawning, without making the
    others a ROI does not use."""
    return np.random.SeedSequence(int(seed), spawn_key=(*STREAMS[name], *child))


def random_streams(seed: int) -> dict:
    """Every seed sequence of a ROI's sampling by name (``random_stream``)."""
    return {name: random_stream(seed, name) for name in STREAMS}


def cheap_posteriors(stack, model, fits, seeds, settings) -> list[dict]:
    """Posteriors of the ROIs of ``stack`` (n, roi, roi; validated counts) by
    ``settings.method`` (``laplace``, ``importance`` or ``auto``; module docstring).

    ``fits`` are their ``fit_mle`` rows (Laplace included), ``seeds`` their seeds. Returns one
    dict per ROI: ``draws`` (k, 6) equally weighted parameter draws, or None where the chain
    is needed, and ``info`` (what ran and why: ``method``, ``why``, ``ess``, ``khat``,
    ``weight_sd``, ``draws_scored``, the settings; with draws, the goodness of fit at the MLE,
    ``bayespsf.inference.gof.pearson_fit``).
    """
    n = len(stack)
    ok = fits["converged"].to_numpy(bool)
    given = asdict(settings)  # once: asdict copies field by field
    out = [
        {
            "draws": None,
            "info": _info(
                given,
                int(seeds[i]),
                bool(ok[i]),
                "chain: the "
                "maximum-likelihood fit did not converge, so there is no "
                "Laplace proposal",
            ),
        }
        for i in range(n)
    ]
    if ok.any():
        todo = np.flatnonzero(ok)
        laplace = np.full((n, 6), np.nan), np.full((n, 6, 6), np.nan)
        laplace[0][todo], laplace[1][todo] = laplace_in_z(fits[ok], model)
        pilots = {}
        if settings.method in ("laplace", "auto"):
            todo, pilots = _laplace(stack, model, todo, laplace, seeds, settings, out)
        if settings.method in ("importance", "auto") and todo.size:
            _importance(stack, model, todo, laplace, seeds, settings, out, pilots)
    made = [i for i in range(n) if out[i]["draws"] is not None]  # all at a converged MLE
    if made:
        theta = fits[list(PARAMETER_NAMES)].to_numpy(float)[made]
        for i, fit in zip(made, pearson_fit(model, stack[made], theta, "mle"), strict=True):
            out[i]["info"].update(fit)
    return out


def as_posterior(outcome: dict, counts, model, truth=None, scene=None):
    """A ``cheap_posteriors`` outcome with draws as a ``Posterior`` (its draws split into
    ``CHAINS`` chains; no autocorrelation time, as the draws are independent)."""
    from bayespsf.inference.posterior import Posterior

    return Posterior.from_draws(
        as_chains(outcome["draws"]),
        tau=np.ones(6),
        info=outcome["info"],
        counts=counts,
        model=model,
        truth=truth,
        scene=scene,
    )


def as_stored(outcome: dict, truth=None, row: dict | None = None) -> tuple[np.ndarray, dict]:
    """A ``cheap_posteriors`` outcome as a store writes it (``Store.write``): its draws in
    ``CHAINS`` chains and its attributes as JSON, those of ``as_posterior`` and the summary
    ``row``."""
    attrs = molecule_attributes(np.ones(6), outcome["info"], truth)
    if row is not None:
        attrs["summary_row"] = json.dumps(row)
    return as_chains(outcome["draws"]), attrs


def as_chains(draws: np.ndarray) -> np.ndarray:
    """Independent draws (n, 6) as ``CHAINS`` chains (CHAINS, n / CHAINS, 6)."""
    return draws.reshape(CHAINS, -1, len(PARAMETER_NAMES))


def _info(given: dict, seed: int, mle_ok: bool, why: str, **facts) -> dict:
    """A ROI's first outcome: the chain, for ``why``; ``given``: the settings as a dict."""
    return {
        **given,
        "seed": seed,
        "method": "mcmc",
        "requested": given["method"],
        "why": why,
        "converged": mle_ok,
        "mle_converged": mle_ok,
        "stuck_walkers": 0,
        **facts,
    }


def _choleskys(cov: np.ndarray) -> np.ndarray:
    """Cholesky factors of the covariances ``cov`` (m, 6, 6), NaN where one is not positive
    definite (LAPACK runs matrix by matrix either way, so a factor does not depend on the
    others)."""
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        out = np.full_like(cov, np.nan)
        for k, one in enumerate(cov):
            try:
                out[k] = np.linalg.cholesky(one)
            except np.linalg.LinAlgError:
                pass
        return out


def _laplace(stack, model, todo, laplace, seeds, settings, out) -> tuple[np.ndarray, dict]:
    """Laplace draws where accepted (``laplace``: centres and covariances in z, per ROI of
    the stack); returns the ROIs still to do and, for those whose pilot weight SD is at most
    ``GAUSSIAN_WEIGHT_SD``, the pilot (draws, log proposal density, log posterior, the
    random stream it came from, its interpolants and the covariance's Cholesky factor) to go
    on with."""
    centres, covariances = laplace
    factors = _choleskys(covariances[todo])
    positive = ~np.isnan(factors).any(axis=(1, 2))
    usable, factors = todo[positive], factors[positive]
    left = [int(i) for i in todo[~positive]]
    for i in left:
        out[i]["info"]["why"] = "chain: the Laplace covariance is not positive definite"
    if not usable.size:
        return np.array(left, dtype=int), {}
    rngs = [np.random.default_rng(random_stream(seeds[i], "laplace")) for i in usable]
    u = np.stack([rng.standard_normal((PILOT, 6)) for rng in rngs])
    pilots_z = centres[usable, None, :] + u @ np.swapaxes(factors, 1, 2)
    log_g = -0.5 * np.einsum("mkj,mkj->mk", u, u)
    kept = [None] * len(usable)  # the pilot's interpolants, for the runs that continue it
    scored = np.stack(fused.score(model, stack[usable], list(pilots_z), kept))
    weight_sds = _weight_sds(scored - log_g)
    wanted = CHAINS * int(np.ceil(settings.ess / CHAINS))
    pilots = {}
    for k, i in enumerate(usable.tolist()):
        weight_sd = float(weight_sds[k])
        passed = weight_sd <= LAPLACE_WEIGHT_SD
        if settings.method == "auto" and not passed:
            out[i]["info"]["weight_sd"] = weight_sd
            out[i]["info"]["why"] = (
                f"Laplace rejected (pilot weight SD {weight_sd:.3g} > {LAPLACE_WEIGHT_SD})"
            )
            left.append(i)
            if weight_sd <= GAUSSIAN_WEIGHT_SD:
                pilots[i] = (pilots_z[k], log_g[k], scored[k], rngs[k], kept[k], factors[k])
            continue
        z = centres[i] + rngs[k].standard_normal((2 * wanted, 6)) @ factors[k].T
        params = model.from_unconstrained(z)
        params = params[np.isfinite(model.log_prior(params))][:wanted]  # within the prior
        params = params[: CHAINS * (len(params) // CHAINS)]
        relation = "<=" if passed else ">"
        out[i]["draws"] = params
        out[i]["info"].update(
            method="laplace",
            why=f"Laplace (pilot weight SD {weight_sd:.3g} {relation} {LAPLACE_WEIGHT_SD})",
            weight_sd=weight_sd,
            ess=float(len(params)),
            draws_scored=PILOT,
            converged=bool(out[i]["info"]["mle_converged"] and passed),
        )
    return np.array(sorted(left), dtype=int), pilots


def _weight_sds(log_ratio: np.ndarray) -> np.ndarray:
    """Per row of ``log_ratio`` (m, k), the standard deviation of its importance weights
    normalised to mean 1 (inf if any is 0 or undefined: a draw outside the posterior's
    support)."""
    finite = np.isfinite(log_ratio).all(axis=1)
    safe = np.where(finite[:, None], log_ratio, 0.0)
    w = np.exp(safe - safe.max(axis=1, keepdims=True))
    return np.where(finite, np.std(w / w.mean(axis=1, keepdims=True), axis=1, ddof=1), np.inf)


def _importance(stack, model, todo, laplace, seeds, settings, out, pilots) -> None:
    """Importance sampling of the ROIs ``todo``: those with a pilot (``auto``) first from the
    Laplace Gaussian, continuing its pilot; then the rest, and those whose Gaussian run
    failed, from the Laplace Student-t."""
    max_draws = int(MAX_DRAWS_PER_ESS * settings.ess)
    centres, covariances = laplace
    runs, kept = {}, {}
    for i, (z, log_g, lp, rng, interpolants, cholesky) in pilots.items():
        proposal = GaussianProposal(centres[i], covariances[i], cholesky=cholesky)
        runs[i] = ImportanceRun(
            proposal, settings.ess, max_draws, rng, first=(z, log_g, lp), margin=GAUSSIAN_MARGIN
        )
        kept[i] = interpolants
    _advance(stack, model, runs, kept)
    failed = _accepted(runs, "the Laplace Gaussian", model, seeds, settings, out)
    runs = {}
    for i in sorted(set(todo.tolist()) - set(pilots) | set(failed)):
        random = np.random.RandomState(np.random.MT19937(random_stream(seeds[i], "draws")))
        try:
            proposal = IndependenceMove(centres[i], covariances[i])
        except np.linalg.LinAlgError:
            out[i]["info"]["why"] = "chain: the Laplace covariance is not positive definite"
            continue
        runs[i] = ImportanceRun(proposal, settings.ess, max_draws, random)
    _advance(stack, model, runs, {})
    failed = _accepted(runs, "the Laplace Student-t", model, seeds, settings, out)
    _adapt(stack, model, {i: runs[i] for i in failed}, laplace, seeds, settings, out)


def _adapt(stack, model, failed: dict, laplace, seeds, settings, out) -> None:
    """Up to ``ADAPT_ROUNDS`` runs for the ROIs of ``failed`` (their failed Student-t runs),
    each from a ``DefensiveMixture`` of a t fitted to the previous run's weighted draws and
    the Laplace Student-t (module docstring); a ROI whose weights cannot be fitted, or whose
    last round fails, is left to the chain."""
    max_draws = int(MAX_DRAWS_PER_ESS * settings.ess)
    centres, covariances = laplace
    before = {i: out[i]["info"]["why"] + "; " for i in failed}  # the t's outcome, kept
    for round_ in range(ADAPT_ROUNDS):
        runs = {}
        for i, previous in failed.items():
            if previous.weights is None or not np.all(np.isfinite(previous.weights)):
                continue  # overflowed: nothing to fit
            try:
                parts = (
                    fitted_t(previous.draws, previous.weights),
                    IndependenceMove(centres[i], covariances[i]),  # the Laplace t
                )
            except np.linalg.LinAlgError:
                continue
            proposal = DefensiveMixture(parts, (ADAPT_SHARE, 1.0 - ADAPT_SHARE))
            stream = random_stream(seeds[i], "adapt", round_)
            runs[i] = ImportanceRun(
                proposal, settings.ess, max_draws, np.random.RandomState(np.random.MT19937(stream))
            )
        _advance(stack, model, runs, {})
        source = f"a t fitted to the weighted draws, round {round_ + 1}"
        failed = {}
        for i, run in runs.items():
            z = _accept(i, run, source, seeds, settings, out, before=before[i])
            if z is None:
                failed[i] = run
            else:
                out[i]["draws"] = model.from_unconstrained(z)
        if not failed:
            return


def _advance(stack, model, runs: dict, kept: dict) -> None:
    """Run importance runs to the end together: each round scores every active run's batch
    in one call (``kept``: each ROI's interpolants, reused while they span its draws), and
    smooths the weights of the runs with equally many draws together."""
    active = [i for i, run in runs.items() if not run.done]
    while active:
        batches = [runs[i].propose() for i in active]
        interpolants = [kept.get(i) for i in active]
        scored = fused.score(model, stack[active], batches, interpolants)
        kept.update(zip(active, interpolants, strict=True))
        _judge(runs, {i: runs[i].add(lp) for i, lp in zip(active, scored, strict=True)})
        active = [i for i in active if not runs[i].done]


def _judge(runs: dict, ratios: dict) -> None:
    """``ImportanceRun.judge`` of each run in ``ratios`` (its log ratios so far), with one
    smoothing call per number of draws."""
    for size in {len(r) for r in ratios.values()}:
        same = [i for i in ratios if len(ratios[i]) == size]
        weights, khat = psis(np.stack([ratios[i] for i in same]))
        for i, w, k in zip(same, weights, np.atleast_1d(khat), strict=True):
            runs[i].judge(w, float(k))


def _accepted(runs: dict, source: str, model, seeds, settings, out) -> list[int]:
    """Record each run's outcome in ``out`` (``_accept``); returns the ROIs whose run
    failed."""
    failed = []
    for i, run in runs.items():
        z = _accept(i, run, source, seeds, settings, out)
        if z is None:
            failed.append(i)
        else:  # one ROI's draws at a time: the chunk's together fall out of the cache
            out[i]["draws"] = model.from_unconstrained(z)
    return failed


def _accept(i, run, source: str, seeds, settings, out, before=None) -> np.ndarray | None:
    """Record run ``i``'s outcome in ``out[i]["info"]``; its resampled draws (sampling
    coordinates) where k-hat and the ESS pass, else None (and why). ``before``: what was
    tried before, as the start of ``why`` (default: what ``auto`` tried)."""
    info = out[i]["info"]
    if before is None:
        before = info["why"] + "; " if "weight_sd" in info else ""
    facts = f"k-hat {run.khat:.2f}, ESS {run.achieved:.0f} of {len(run.weights)} draws"
    info.update(khat=run.khat, draws_scored=info.get("draws_scored", 0) + len(run.weights))
    if run.khat > KHAT_MAX or run.achieved < settings.ess:
        info["why"] = f"{before}chain: importance sampling from {source} failed ({facts})"
        return None
    n = CHAINS * int(run.achieved // CHAINS)
    rng = np.random.default_rng(random_stream(seeds[i], "resample"))
    info.update(
        method="importance",
        ess=float(run.achieved),
        why=f"{before}importance sampling from {source} ({facts})",
    )
    return run.draws[systematic_resample(run.weights, n, rng)]


__all__ = [
    "LAPLACE_WEIGHT_SD",
    "PILOT",
    "cheap_posteriors",
    "laplace_in_z",
    "random_stream",
    "random_streams",
]
