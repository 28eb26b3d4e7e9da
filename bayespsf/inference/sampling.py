"""The emcee driver: start from the MLE, run in chunks until converged, return a Posterior.

Moves (``laplace-de``, the default): 80% of steps propose for every walker an independent
draw from a Student-t built from the Laplace approximation at the MLE
(``IndependenceMove``), 15% a differential-evolution move and 5% a DE-snooker move
(ter Braak & Vrugt, Stat. Comput. 18 (2008)). On the near-Gaussian posteriors of bright
molecules the independence proposals are accepted ~70% of the time and the autocorrelation time
is ~2-3 steps, against ~20-25 for DE moves alone (``de-snooker``) and ~60 for emcee's stretch
move (``benchmarks/README.md``); the DE moves keep the chain moving where the Laplace
approximation is poor (dim molecules, heavy tails). Without a converged MLE fit the
``laplace-de`` run falls back to ``de-snooker``.

Convergence (Foreman-Mackey et al., PASP 125 (2013); Goodman & Weare 2010): after each chunk
the integrated autocorrelation time tau of every parameter is estimated from the chain after
burn-in (emcee's estimator, Sokal's window: ``integrated_time``); chunks start at 50 steps
and are sized to reach the predicted length; the run stops when every tau changed by < 10%
since the previous chunk, the chain is >= ``min_taus`` tau long, and every parameter's
effective sample size ``walkers * (steps - burn) / tau`` reaches ``ess``. A run that hits
``max_steps`` first is returned with ``converged = False`` (never silently).

Reproducibility: emcee draws from a NumPy ``RandomState``; each call builds its own from
``SeedSequence(seed)``, so posteriors in one process or in parallel workers never share a
stream, and the same seed gives the same draws.
"""

from __future__ import annotations

import itertools
import sys
import time
from dataclasses import asdict

import emcee
import numpy as np
from numpy.typing import ArrayLike

from bayespsf._runtime import one_blas_thread
from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import diagnostics
from bayespsf.inference.batched import as_posterior, cheap_posteriors, laplace_in_z, random_streams
from bayespsf.inference.diagnostics import no_density
from bayespsf.inference.estimators import fit_mle, start_values
from bayespsf.inference.gof import pearson_fit
from bayespsf.inference.importance import IndependenceMove
from bayespsf.inference.posterior import Posterior
from bayespsf.inference.settings import (
    MOVES,
    Settings,
    check_chain_work,
    check_model,
    check_settings,
    check_walkers_fit,
)
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import Scene


def _moves(name: str, proposal: IndependenceMove | None):
    """emcee moves by name; ``laplace-de`` without a Laplace proposal (the MLE failed) runs
    the ``de-snooker`` mixture."""
    if name == "laplace-de" and proposal is not None:
        moves = [(proposal, 0.8), (emcee.moves.DEMove(), 0.15), (emcee.moves.DESnookerMove(), 0.05)]
        return moves
    if name in ("laplace-de", "de-snooker"):
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if name == "stretch":
        return emcee.moves.StretchMove()
    raise BayespsfInputError(f"moves must be one of {', '.join(MOVES)}; got {name!r}")


def _start(counts, model, walkers, rng, fits=None):
    """Walkers around the MLE, spread by its Laplace SDs (in sampling coordinates), and the
    Laplace proposal of ``IndependenceMove`` (``None`` if the fit failed); ``fits`` is the
    ROI's ``fit_mle`` table if already made.

    A centre outside the prior's support (an informative prior that excludes the MLE) is
    moved to its edge; walkers that cannot be placed near it are drawn from the prior.
    """
    fits = fit_mle(counts, model) if fits is None else fits
    fit = fits.iloc[0]
    proposal = None
    if fit["converged"]:
        z0, cov = (a[0] for a in laplace_in_z(fits, model))
        proposal = IndependenceMove(z0, cov)
        centre, dz = model.from_unconstrained(z0), np.sqrt(np.diagonal(cov))
    else:  # a poor start: the sampler's burn-in has more to do, and the result says so
        low, high = model.prior_bounds()  # the support includes its ends
        centre = np.clip(start_values(model.to_photons(counts[None]), model)[0], low, high)
        z0 = model.to_unconstrained(centre)
        dz = np.array([model.pixel_size / 4] * 2 + [0.1, 0.1, 0.1, 0.1 * centre[5] + 0.1])
    proposals = itertools.chain(
        (z0 + 0.5 * dz * rng.standard_normal((walkers, 6)) for _ in range(100)),
        (model.to_unconstrained(model.sample_prior(walkers, rng)) for _ in range(100)),
    )
    out = np.empty((walkers, 6))
    filled = 0
    for trial in proposals:
        ok = trial[np.isfinite(model.log_posterior(trial, counts))]
        take = min(len(ok), walkers - filled)
        out[filled : filled + take] = ok[:take]
        filled += take
        if filled == walkers:
            return out, fit, proposal
    _explain_no_support(counts, model, centre)
    raise RuntimeError("could not place the walkers inside the prior's support")


def _explain_no_support(counts, model, centre) -> None:
    """Name the pixels the likelihood tier gives zero density, if that is why no walker fits."""
    reason = no_density(counts, model, centre)
    if reason:
        raise BayespsfInputError(reason)


def integrated_time(chain, c: float = 5.0) -> np.ndarray:
    """Integrated autocorrelation time of each parameter of an ensemble chain ``(steps,
    walkers, ndim)``: the normalised autocorrelation function of every walker (by FFT), averaged
    over walkers, summed up to Sokal's automatic window ``m >= c tau(m)`` (Sokal, Monte Carlo
    Methods in Statistical Mechanics (1997); Goodman & Weare 2010).

    The estimator of ``emcee.autocorr.integrated_time(chain, c, tol=0)``, in one FFT over all
    walkers and parameters instead of one per walker and parameter (emcee's Python loop was
    12% of a posterior's time).
    """
    x = np.asarray(chain, dtype=np.float64)
    steps = x.shape[0]
    size = 2 * (1 << (steps - 1).bit_length())
    f = np.fft.rfft(x - x.mean(axis=0), n=size, axis=0)
    acf = np.fft.irfft(f * np.conj(f), n=size, axis=0)[:steps]
    acf = (acf / acf[0]).mean(axis=1)  # (steps, ndim)
    taus = 2.0 * np.cumsum(acf, axis=0) - 1.0
    below = np.arange(steps)[:, None] >= c * taus
    window = np.where(below.any(axis=0), below.argmax(axis=0), steps - 1)
    return taus[window, np.arange(x.shape[-1])]


def _autocorrelation_time(segment):
    """The integrated autocorrelation time of each parameter over the walkers that moved,
    and the number of walkers that did not move at all in some coordinate (stuck, e.g. in a
    local mode of a multimodal posterior: the run cannot be called converged)."""
    # a variance that underflows to 0 (moves of 1e-300) has no autocorrelation function either
    moving = np.all(np.var(segment, axis=0) > 0, axis=-1)
    stuck = int((~moving).sum())
    if moving.sum() < 2:
        return np.full(segment.shape[-1], np.nan), stuck
    return integrated_time(segment[:, moving]), stuck


def _within_budget(chunk: int, steps: int, elapsed: float, settings: Settings) -> int:
    """The next chunk, shortened so that it ends near the wall-clock budget (if any) at the
    speed seen so far; at least one step."""
    if settings.max_seconds is None or steps == 0:
        return chunk
    per_step = elapsed / steps
    return int(max(1, min(chunk, (settings.max_seconds - elapsed) / per_step)))


def _next_chunk(steps: int, burn: int, tau, settings: Settings) -> int:
    """Steps to add so that the chain reaches the predicted length (``min_taus`` tau and the
    ESS target after burn-in, plus 10%), at least ``settings.chunk``, at most doubling it."""
    if not np.all(np.isfinite(tau)):
        return max(settings.chunk, steps)
    needed = max(settings.min_taus * tau.max(), np.max(settings.ess * tau / settings.walkers))
    return int(np.clip(1.1 * (burn + needed) - steps, settings.chunk, max(steps, settings.chunk)))


@one_blas_thread
def sample_posterior(
    counts: ArrayLike,
    model: Model,
    seed: int = 0,
    ess: float = 400.0,
    walkers: int = 32,
    max_steps: int = 50_000,
    moves: str = "laplace-de",
    truth: ArrayLike | None = None,
    scene: Scene | None = None,
    start: ArrayLike | None = None,
    progress: bool | None = None,
    method: str = "mcmc",
    max_seconds: float | None = None,
) -> Posterior:
    """Sample the posterior of ``x0 y0 s_x s_y N b`` for one ROI with emcee.

    Parameters
    ----------
    counts : array_like, shape (roi, roi)
        One ROI in ADU.
    model : Model
        Geometry, camera law (its likelihood tier), prior and photon unit.
    seed : int
        Seeds the walkers' start and emcee's random stream (and the draws of the other
        methods): the same seed gives the same draws.
    ess : float
        Effective sample size to reach on every parameter (default 400).
    walkers : int
        Ensemble size (even, >= 12; default 32).
    max_steps : int
        Step cap (>= 1); a capped run is flagged ``converged = False``.
    moves : {"laplace-de", "de-snooker", "stretch"}
        emcee moves (module docstring); default ``laplace-de``.
    truth : array_like, shape (6,), optional
        True ``x0 y0 s_x s_y N b`` (nm, photons, photons per pixel), kept in the result
        (corner plot truths, file).
    scene : Scene, optional
        Kept in the result file.
    start : array_like, shape (walkers, 6), optional
        Initial walkers in sampling coordinates (``Model.to_unconstrained``); default:
        around the maximum-likelihood fit, spread by its Laplace SDs.
    progress : bool, optional
        One line per chunk on stderr (steps, tau, ESS); default: when stderr is a terminal.
    method : {"mcmc", "auto", "laplace", "importance"}
        ``mcmc`` (default): the emcee run. ``importance``: Pareto-smoothed importance sampling
        from the Laplace proposal where its k-hat is <= 0.7 and the ESS target is reached
        within 50 x ``ess`` draws. ``laplace``: draws from the Laplace approximation (no
        check). ``auto``: the Laplace where a pilot of its draws shows it accurate, else
        importance sampling where its k-hat passes, else the chain
        (``bayespsf.inference.batched``). Without a converged MLE, with ``start``, or where
        the diagnostic fails, the emcee run; ``info["method"]`` says what ran and
        ``info["why"]`` why.
    max_seconds : float, optional
        Wall-clock budget of the chain in seconds; a run that exhausts it stops with
        ``converged = False``. Default: none (``max_steps`` bounds the run).

    Returns
    -------
    Posterior
        Draws of ``x0 y0 s_x s_y`` (nm), ``N`` (photons) and ``b`` (photons per pixel), one
        chain per walker, with ``info``: the settings, ``method`` (what ran), ``requested``,
        ``converged``, ``mle_converged``, and for a chain ``steps``, ``burn``, ``thin``,
        ``acceptance``, ``stuck_walkers`` and ``stopped``; and, whatever ran, the goodness of
        fit ``chi2``, ``chi2_dof``, ``chi2_p`` and ``chi2_at`` (Pearson's chi-square at the
        MLE, or the posterior mean where the MLE did not converge or ``start`` was given:
        ``bayespsf.inference.gof.pearson_fit``; a small ``chi2_p`` says the model does not
        describe the ROI, however narrow the posterior). ``info["stopped"]`` says why the
        chain ended: ``converged``, ``max_steps``, ``max_seconds``, or ``stalled``
        (``bayespsf.inference.diagnostics.stalled``: the autocorrelation time grows with the
        chain, or the walkers do not move, so running on would not converge). A run that did
        not converge has ``info["diagnosis"]``: the reason in words and its likely cause (the
        prior excludes the data, the ROI does not identify the posterior, the
        maximum-likelihood fit failed).

    Raises
    ------
    BayespsfInputError
        If ``counts`` is not one valid ROI of the model's shape (``Model.roi_problems``
        names the problem), a setting is out of range (``check_settings``), ``walkers`` so
        many that the chain cannot be held in memory (``check_walkers_fit``), a chain that
        may run for hours on large ROIs without ``max_seconds`` (``check_chain_work``; before
        the chain, where the chain-free methods did not serve), ``start`` has
        not the shape ``(walkers, 6)``, or the likelihood tier gives some pixel zero density
        at every parameter value tried.

    See Also
    --------
    sample_many : the posteriors of a stack of ROIs, in parallel and resumable.
    fit_mle : the maximum-likelihood fit the sampler starts from.
    Posterior.summary : the posterior's means, SDs, HDIs, ESS and tau.

    Notes
    -----
    The chain's moves, its convergence test and its random streams are described in the
    module docstring (ter Braak & Vrugt 2008; Foreman-Mackey et al. 2013; Goodman & Weare
    2010); the chain-free methods in ``bayespsf.inference.batched`` and
    ``bayespsf.inference.importance``. The emcee run starts from ``fit_mle`` at the ROI.

    Examples
    --------
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("paper-fig3")
    >>> counts, truth = bayespsf.simulate(scene, 2, seed=1)
    >>> model = bayespsf.Model.from_scene(scene)
    >>> post = bayespsf.sample_posterior(counts[0], model, seed=1, method="auto")
    >>> post.method, post.converged
    ('importance', True)
    >>> list(post.summary().index)
    ['x0', 'y0', 's_x', 's_y', 'N', 'b']
    """
    check_model(model)
    c = model.check_counts(counts)
    if c.ndim != 2:
        raise BayespsfInputError(
            f"counts must be one ROI of shape ({model.roi}, {model.roi}); got {c.shape} "
            "(use sample_many for a stack)"
        )
    settings = check_settings(
        seed=seed,
        walkers=walkers,
        ess=ess,
        max_steps=max_steps,
        moves=moves,
        method=method,
        max_seconds=max_seconds,
    )
    walkers, ess, max_steps = settings.walkers, settings.ess, settings.max_steps
    check_walkers_fit(walkers, model.roi)
    streams = random_streams(settings.seed)
    proposal, fit, fits, fallback = None, None, None, None
    if method != "mcmc":
        if start is None:
            fits = fit_mle(c[None], model)
            cheap = cheap_posteriors(c[None], model, fits, [settings.seed], settings)[0]
            if cheap["draws"] is not None:
                return as_posterior(cheap, c, model, truth, scene)
            fallback = cheap["info"]["why"]
        else:
            fallback = "chain: a start was given, so there is no Laplace proposal"
    check_chain_work(settings, model.roi)  # before the chain: hours on a large ROI, unbounded
    if start is None:
        z0, fit, proposal = _start(c, model, walkers, np.random.default_rng(streams["start"]), fits)
        mle_ok = bool(fit["converged"])
    else:
        z0, mle_ok = finite_array("start", start), True
        if z0.shape != (walkers, 6):
            raise BayespsfInputError(f"start must have shape ({walkers}, 6), got {z0.shape}")
    sampler = emcee.EnsembleSampler(
        walkers, 6, model.log_posterior, args=(c,), vectorize=True, moves=_moves(moves, proposal)
    )
    sampler.random_state = np.random.RandomState(np.random.MT19937(streams["chain"])).get_state()
    state, previous, stopped = z0, None, "max_steps"
    tau = np.full(6, np.nan)
    burn, stuck, chunk = 0, 0, settings.chunk
    history: list[tuple[int, float]] = []
    show = progress or (progress is None and sys.stderr.isatty())
    began = time.perf_counter()
    while sampler.iteration < max_steps:
        chunk = _within_budget(chunk, sampler.iteration, time.perf_counter() - began, settings)
        state = sampler.run_mcmc(state, min(chunk, max_steps - sampler.iteration))
        chain = sampler.get_chain()
        burn = (
            int(min(5 * np.nanmax(tau), chain.shape[0] // 2))
            if np.all(np.isfinite(tau))
            else (chain.shape[0] // 3)
        )
        tau, stuck = _autocorrelation_time(chain[burn:])
        n = chain.shape[0] - burn
        ess_now = walkers * n / tau
        stable = previous is not None and np.all(np.abs(tau - previous) < 0.1 * tau)
        enough = n >= settings.min_taus * tau.max() and np.all(ess_now >= ess)
        enough = enough and stuck == 0
        previous = tau
        if show:
            print(
                f"\rsampling: {sampler.iteration} steps, tau max {tau.max():.1f}, "
                f"min ESS {np.min(ess_now):.0f} (target {ess:g})",
                end="",
                file=sys.stderr,
                flush=True,
            )
        if stable and enough:
            stopped = "converged"
            break
        why = diagnostics.stalled(history, sampler.iteration, tau.max(), stuck, walkers)
        if why is not None:
            stopped = "stalled: " + why
            break
        history.append((sampler.iteration, float(tau.max())))
        if max_seconds is not None and time.perf_counter() - began >= max_seconds:
            stopped = f"max_seconds: the {max_seconds:g} s budget ran out"
            break
        chunk = _next_chunk(sampler.iteration, burn, tau, settings)
    if show:
        print(file=sys.stderr)  # ends the progress line
    converged = stopped == "converged"
    report = {}
    if not (converged and mle_ok):
        cause = "" if fit is None else diagnostics.explain(fit, model)
        head = f"not converged ({stopped})" if not converged else "the chain met its targets"
        report["diagnosis"] = head + (f"; {cause}" if cause else "")
    thin = max(1, int(0.5 * np.nanmin(tau))) if np.any(np.isfinite(tau)) else 1
    thin = min(thin, max(1, (sampler.iteration - burn) // walkers))  # keep draws >= walkers
    draws = sampler.get_chain(discard=burn, thin=thin)  # (draws, walkers, 6) in z
    params = model.from_unconstrained(draws)
    acceptance = float(np.mean(sampler.acceptance_fraction))
    if fit is not None and mle_ok:  # the goodness of fit at the MLE, else the posterior mean
        (gof,) = pearson_fit(
            model, c[None], fit[list(PARAMETER_NAMES)].to_numpy(float)[None], "mle"
        )
    else:
        (gof,) = pearson_fit(
            model, c[None], params.reshape(-1, 6).mean(axis=0)[None], "posterior mean"
        )
    return Posterior.from_draws(
        np.moveaxis(params, 1, 0),  # (walkers, draws, 6): walkers are the chains
        tau=tau,
        info={
            **asdict(settings),
            "method": "mcmc",  # what ran; "requested" what was asked, "why" why the chain ran
            "steps": int(sampler.iteration),
            "burn": burn,
            "thin": thin,
            "stuck_walkers": stuck,
            "converged": bool(converged and mle_ok),
            "mle_converged": mle_ok,
            "acceptance": acceptance,
            "stopped": stopped.split(":")[0],
            **report,
            "requested": settings.method,
            **({} if fallback is None else {"why": fallback}),
            **gof,
        },
        counts=c,
        model=model,
        truth=truth,
        scene=scene,
    )
