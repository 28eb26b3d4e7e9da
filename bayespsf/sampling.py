"""The emcee driver: start from the MLE, run in chunks until converged, return a Posterior.

Convergence (Foreman-Mackey et al., PASP 125 (2013); Goodman & Weare 2010): after each chunk
the integrated autocorrelation time tau of every parameter is estimated from the chain after
burn-in (emcee's estimator, Sokal's window); the run stops when every tau changed by < 10%
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
from dataclasses import asdict, dataclass

import emcee
import numpy as np

from bayespsf.errors import BayespsfInputError
from bayespsf.estimators import fit_mle, start_values
from bayespsf.model import Model
from bayespsf.posterior import Posterior
from bayespsf.psf import PARAMETER_NAMES


@dataclass(frozen=True)
class Settings:
    """Sampler settings (stored in every result file)."""

    seed: int = 0
    walkers: int = 32
    ess: float = 400.0
    chunk: int = 500
    max_steps: int = 50_000
    min_taus: float = 50.0
    moves: str = "de-snooker"  # 0.8 DEMove + 0.2 DESnookerMove; or "stretch"


def _moves(name: str):
    if name == "de-snooker":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if name == "stretch":
        return emcee.moves.StretchMove()
    raise BayespsfInputError(f"moves must be 'de-snooker' or 'stretch', got {name!r}")


def _start(counts, model, walkers, rng):
    """Walkers around the MLE, spread by its Laplace SDs (in sampling coordinates).

    A centre outside the prior's support (an informative prior that excludes the MLE) is
    moved to its edge; walkers that cannot be placed near it are drawn from the prior.
    """
    fit = fit_mle(counts, model).iloc[0]
    names = list(PARAMETER_NAMES)
    if fit["converged"]:
        centre = fit[names].to_numpy(float)
        sd = fit[[f"sd_{n}" for n in names]].to_numpy(float)
    else:  # a poor start: the sampler's burn-in has more to do, and the result says so
        centre = start_values(model.to_photons(counts[None]), model)[0]
        sd = np.array([model.pixel_size / 4] * 2 + [0.1 * centre[2], 0.1 * centre[3]])
        sd = np.concatenate([sd, [0.1 * centre[4], 0.1 * centre[5] + 0.1]])
    low, high = model.prior_bounds()  # the support includes its ends
    centre = np.clip(centre, low, high)
    z0 = model.to_unconstrained(centre)
    dz = sd / np.array([1.0, 1.0, centre[2], centre[3], centre[4], 1.0])
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
            return out, bool(fit["converged"])
    _explain_no_support(counts, model, centre)
    raise RuntimeError("could not place the walkers inside the prior's support")


def _explain_no_support(counts, model, centre) -> None:
    """Name the pixels the likelihood tier gives zero density, if that is why no walker fits."""
    lam = model.expected(centre)
    per_pixel = model.camera._log_likelihood(counts, lam)
    bad = np.argwhere(~np.isfinite(per_pixel))
    if bad.size:
        where = ", ".join(f"({r}, {c}) = {counts[r, c]:.6g} ADU" for r, c in bad[:5])
        tier = getattr(model.camera, "likelihood", "")
        raise BayespsfInputError(
            f"the {tier!r} likelihood gives zero density to {len(bad)} pixel(s) of this ROI at "
            f"every parameter value tried (row, column: {where}); they lie outside the tier's "
            "support: use a tier with full support (e.g. 'exact')"
        )


def _autocorrelation_time(segment):
    """emcee's integrated autocorrelation time of each parameter over the walkers that moved,
    and the number of walkers that did not move at all in some coordinate (stuck, e.g. in a
    local mode of a multimodal posterior: the run cannot be called converged)."""
    moving = np.all(np.ptp(segment, axis=0) > 0, axis=-1)
    stuck = int((~moving).sum())
    if moving.sum() < 2:
        return np.full(segment.shape[-1], np.nan), stuck
    return emcee.autocorr.integrated_time(segment[:, moving], tol=0), stuck


def sample_posterior(
    counts,
    model: Model,
    seed: int = 0,
    ess: float = 400.0,
    walkers: int = 32,
    max_steps: int = 50_000,
    moves: str = "de-snooker",
    truth=None,
    scene=None,
    start=None,
    progress: bool | None = None,
) -> Posterior:
    """Sample the posterior of ``x0 y0 s_x s_y N b`` for one ROI with emcee.

    Parameters
    ----------
    counts : array_like, shape (roi, roi)
        One ROI in ADU.
    model : Model
    seed : int
        Seeds the walkers' start and emcee's random stream.
    ess : float
        Effective sample size to reach on every parameter (default 400).
    walkers, max_steps, moves
        Ensemble size; step cap (a capped run is flagged ``converged = False``); emcee moves.
    truth, scene
        Optional true parameters and scene, kept in the result (corner plot truths, file).
    start : array_like, shape (walkers, 6), optional
        Initial walkers in sampling coordinates (:meth:`Model.to_unconstrained`); default:
        around the maximum-likelihood fit, spread by its Laplace SDs.
    progress : bool, optional
        One line per chunk on stderr (steps, tau, ESS); default: when stderr is a terminal.
    """
    c = model.check_counts(counts)
    if c.ndim != 2:
        raise BayespsfInputError(
            f"counts must be one ROI of shape ({model.roi}, {model.roi}); got {c.shape} "
            "(use sample_many for a stack)"
        )
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise BayespsfInputError(f"seed must be a non-negative integer, got {seed!r}")
    if walkers < 12 or walkers % 2:
        raise BayespsfInputError(f"walkers must be an even number >= 12, got {walkers!r}")
    settings = Settings(int(seed), int(walkers), float(ess), 500, int(max_steps), 50.0, moves)
    start_seq, emcee_seq = np.random.SeedSequence(seed).spawn(2)
    if start is None:
        z0, mle_ok = _start(c, model, walkers, np.random.default_rng(start_seq))
    else:
        z0, mle_ok = np.array(start, dtype=np.float64), True
        if z0.shape != (walkers, 6):
            raise BayespsfInputError(f"start must have shape ({walkers}, 6), got {z0.shape}")
    sampler = emcee.EnsembleSampler(
        walkers, 6, model.log_posterior, args=(c,), vectorize=True, moves=_moves(moves)
    )
    sampler.random_state = np.random.RandomState(np.random.MT19937(emcee_seq)).get_state()
    state, previous, converged = z0, None, False
    tau = np.full(6, np.nan)
    burn, stuck = 0, 0
    show = progress or (progress is None and sys.stderr.isatty())
    while sampler.iteration < max_steps:
        state = sampler.run_mcmc(state, min(settings.chunk, max_steps - sampler.iteration))
        chain = sampler.get_chain()
        burn = (
            int(min(5 * np.nanmax(tau), chain.shape[0] // 2))
            if np.all(np.isfinite(tau))
            else (chain.shape[0] // 3)
        )
        tau, stuck = _autocorrelation_time(chain[burn:])
        n = chain.shape[0] - burn
        stable = previous is not None and np.all(np.abs(tau - previous) < 0.1 * tau)
        enough = n >= settings.min_taus * tau.max() and np.all(walkers * n / tau >= ess)
        enough = enough and stuck == 0
        previous = tau
        if show:
            print(
                f"\rsampling: {sampler.iteration} steps, tau max {tau.max():.1f}, "
                f"min ESS {np.min(walkers * n / tau):.0f} (target {ess:g})",
                end="",
                file=sys.stderr,
                flush=True,
            )
        if stable and enough:
            converged = True
            break
    if show:
        print(file=sys.stderr)
    thin = max(1, int(0.5 * np.nanmin(tau))) if np.any(np.isfinite(tau)) else 1
    draws = sampler.get_chain(discard=burn, thin=thin)  # (draws, walkers, 6) in z
    params = model.from_unconstrained(draws)
    acceptance = float(np.mean(sampler.acceptance_fraction))
    return Posterior.from_draws(
        np.moveaxis(params, 1, 0),  # (walkers, draws, 6): walkers are the chains
        tau=tau,
        info={
            **asdict(settings),
            "steps": int(sampler.iteration),
            "burn": burn,
            "thin": thin,
            "stuck_walkers": stuck,
            "converged": bool(converged and mle_ok),
            "mle_converged": mle_ok,
            "acceptance": acceptance,
        },
        counts=c,
        model=model,
        truth=truth,
        scene=scene,
    )
