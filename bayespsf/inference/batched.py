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

Draws of all the ROIs being worked on are scored together (``bayespsf.inference.fused``: the
camera law interpolated per pixel over each ROI's batch, checked, within 1e-6 in log p per
pixel of ``Model.log_posterior``): the cost of a stack is a few compiled passes, not a Python
loop of small calls. Each ROI keeps its own random
streams, spawned from its seed exactly as ``sample_posterior`` spawns them, so a ROI's
posterior is the same whether it is sampled alone or in any stack
(``tests/inference/test_stack_posterior.py``).
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from bayespsf.inference import fused
from bayespsf.inference.gof import pearson_fit
from bayespsf.inference.importance import (
    CHAINS,
    KHAT_MAX,
    GaussianProposal,
    ImportanceRun,
    IndependenceMove,
    psis,
    systematic_resample,
)
from bayespsf.psf import PARAMETER_NAMES

PILOT = 64  # Laplace draws scored to judge the Laplace (auto)
LAPLACE_WEIGHT_SD = 0.05  # the largest pilot weight SD at which auto uses the Laplace
GAUSSIAN_WEIGHT_SD = 1.0  # ... and at which it goes on with the Laplace Gaussian as proposal
GAUSSIAN_MARGIN = 1.05  # its pilot predicts its ESS per draw, 1 / (1 + sd(w)**2), closely
MAX_DRAWS_PER_ESS = 50  # an importance run scores at most this many draws per unit of ESS


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


def random_streams(seed: int):
    """The seed sequences of a ROI's sampling, spawned as ``sample_posterior`` does: the
    walkers' start, then (from the second) importance draws, resampling and the Laplace."""
    start, rest = np.random.SeedSequence(int(seed)).spawn(2)
    draws, resample, laplace = rest.spawn(3)
    return {"start": start, "chain": rest, "draws": draws, "resample": resample, "laplace": laplace}


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
    out = [
        {
            "draws": None,
            "info": _info(
                settings,
                int(seeds[i]),
                bool(ok[i]),
                "chain: the "
                "maximum-likelihood fit did not converge, so there is no "
                "Laplace proposal",
            ),
        }
        for i in range(n)
    ]
    streams = [random_streams(s) for s in seeds]
    if ok.any():
        centre, cov = laplace_in_z(fits[ok], model)
        todo = np.flatnonzero(ok)
        laplace = {i: (centre[k], cov[k]) for k, i in enumerate(todo)}
        pilots = {}
        if settings.method in ("laplace", "auto"):
            todo, pilots = _laplace(stack, model, todo, laplace, streams, settings, out)
        if settings.method in ("importance", "auto") and todo.size:
            _importance(stack, model, todo, laplace, streams, settings, out, pilots)
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
        outcome["draws"].reshape(CHAINS, -1, len(PARAMETER_NAMES)),
        tau=np.ones(6),
        info=outcome["info"],
        counts=counts,
        model=model,
        truth=truth,
        scene=scene,
    )


def _info(settings, seed: int, mle_ok: bool, why: str, **facts) -> dict:
    return {
        **asdict(settings),
        "seed": seed,
        "method": "mcmc",
        "requested": settings.method,
        "why": why,
        "converged": mle_ok,
        "mle_converged": mle_ok,
        "stuck_walkers": 0,
        **facts,
    }


def _cholesky(cov):
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None


def _laplace(stack, model, todo, laplace, streams, settings, out) -> tuple[np.ndarray, dict]:
    """Laplace draws where accepted (``laplace``: ROI -> centre and covariance in z); returns
    the ROIs still to do and, for those whose pilot weight SD is at most
    ``GAUSSIAN_WEIGHT_SD``, the pilot (draws, log proposal density, log posterior, the
    random stream it came from, its interpolants and the covariance's Cholesky factor) to go
    on with."""
    factors = {i: _cholesky(laplace[i][1]) for i in todo}
    usable = [i for i in todo if factors[i] is not None]
    rngs = {i: np.random.default_rng(streams[i]["laplace"]) for i in usable}
    pilots_z, log_g = [], []
    for i in usable:
        u = rngs[i].standard_normal((PILOT, 6))
        pilots_z.append(laplace[i][0] + u @ factors[i].T)
        log_g.append(-0.5 * np.sum(u * u, axis=1))
    kept = [None] * len(usable)  # the pilot's interpolants, for the runs that continue it
    scored = fused.score(model, stack[usable], pilots_z, kept) if usable else []
    left = [i for i in todo if factors[i] is None]
    for i in left:
        out[i]["info"]["why"] = "chain: the Laplace covariance is not positive definite"
    wanted = CHAINS * int(np.ceil(settings.ess / CHAINS))
    pilots = {}
    for i, z, lp, lg, interpolants in zip(usable, pilots_z, scored, log_g, kept, strict=True):
        weight_sd = _weight_sd(lp - lg)
        passed = weight_sd <= LAPLACE_WEIGHT_SD
        if settings.method == "auto" and not passed:
            out[i]["info"]["weight_sd"] = weight_sd
            out[i]["info"]["why"] = (
                f"Laplace rejected (pilot weight SD {weight_sd:.3g} > {LAPLACE_WEIGHT_SD})"
            )
            left.append(i)
            if weight_sd <= GAUSSIAN_WEIGHT_SD:
                pilots[i] = (z, lg, lp, rngs[i], interpolants, factors[i])
            continue
        u = rngs[i].standard_normal((2 * wanted, 6))
        z = laplace[i][0] + u @ factors[i].T
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


def _weight_sd(log_ratio: np.ndarray) -> float:
    """Standard deviation of importance weights normalised to mean 1 (inf if any is 0 or
    undefined: a draw outside the posterior's support)."""
    if not np.all(np.isfinite(log_ratio)):
        return float("inf")
    w = np.exp(log_ratio - log_ratio.max())
    return float(np.std(w / w.mean(), ddof=1))


def _importance(stack, model, todo, laplace, streams, settings, out, pilots) -> None:
    """Importance sampling of the ROIs ``todo``: those with a pilot (``auto``) first from the
    Laplace Gaussian, continuing its pilot; then the rest, and those whose Gaussian run
    failed, from the Laplace Student-t."""
    max_draws = int(MAX_DRAWS_PER_ESS * settings.ess)
    runs, kept = {}, {}
    for i, (z, log_g, lp, rng, interpolants, cholesky) in pilots.items():
        proposal = GaussianProposal(*laplace[i], cholesky=cholesky)
        runs[i] = ImportanceRun(
            proposal, settings.ess, max_draws, rng, first=(z, log_g, lp), margin=GAUSSIAN_MARGIN
        )
        kept[i] = interpolants
    _advance(stack, model, runs, kept)
    failed = []
    for i, run in runs.items():
        if not _accept(i, run, "the Laplace Gaussian", model, streams, settings, out):
            failed.append(i)
    runs = {}
    for i in sorted(set(todo) - set(pilots) | set(failed)):
        random = np.random.RandomState(np.random.MT19937(streams[i]["draws"]))
        try:
            proposal = IndependenceMove(*laplace[i])
        except np.linalg.LinAlgError:
            out[i]["info"]["why"] = "chain: the Laplace covariance is not positive definite"
            continue
        runs[i] = ImportanceRun(proposal, settings.ess, max_draws, random)
    _advance(stack, model, runs, {})
    for i, run in runs.items():
        _accept(i, run, "the Laplace Student-t", model, streams, settings, out)


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


def _accept(i, run, source: str, model, streams, settings, out) -> bool:
    """Record run ``i``'s outcome in ``out[i]``: its resampled draws where k-hat and the ESS
    pass (True), or why not."""
    info = out[i]["info"]
    before = info["why"] + "; " if "weight_sd" in info else ""  # what auto tried before
    facts = f"k-hat {run.khat:.2f}, ESS {run.achieved:.0f} of {len(run.weights)} draws"
    info.update(khat=run.khat, draws_scored=info.get("draws_scored", 0) + len(run.weights))
    if run.khat > KHAT_MAX or run.achieved < settings.ess:
        info["why"] = f"{before}chain: importance sampling from {source} failed ({facts})"
        return False
    n = CHAINS * int(run.achieved // CHAINS)
    index = systematic_resample(run.weights, n, np.random.default_rng(streams[i]["resample"]))
    out[i]["draws"] = model.from_unconstrained(run.draws[index])
    info.update(
        method="importance",
        ess=float(run.achieved),
        why=f"{before}importance sampling from {source} ({facts})",
    )
    return True


__all__ = [
    "LAPLACE_WEIGHT_SD",
    "PILOT",
    "cheap_posteriors",
    "laplace_in_z",
    "random_streams",
]
