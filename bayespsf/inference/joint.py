"""The joint posterior of an immobile molecule over its frames.

An immobile molecule has one position and one width in every frame; its photon count and the
background may change from frame to frame (blinking, bleaching, a drifting background). The
joint model of its K valid frames shares ``x0, y0, s_x, s_y`` (and optionally ``b``) and gives
each frame its own ``N`` (and ``b``): ``4 + 2K`` parameters, the frames' likelihoods multiplied,
the prior of a shared parameter counted once.

It is sampled without a Markov chain, as the batched engine samples one ROI
(``bayespsf.inference.batched``), because a chain in 4 + 2K dimensions mixes slowly:

1. the joint maximum-likelihood fit, by the Levenberg-Marquardt iteration with Fisher scoring
   of ``bayespsf.inference.solver`` on the joint gradient and information (the frames' blocks summed
   over the shared parameters), from the per-frame fits;
2. its Laplace approximation: the Gaussian whose precision is the joint observed information
   (the frames' ``observed_information``, analytic: ``bayespsf.inference.solver``), in the
   sampling coordinates ``(x0, y0, log s_x, log s_y, log N, b)``;
3. Pareto-smoothed importance sampling (``bayespsf.inference.importance``) from that Gaussian
   mixed with a wider one (``DefensiveProposal``): exact where its k-hat is at most
   ``KHAT_MAX`` (0.7) and the ESS target is reached; otherwise the result says so
   (``converged`` False, ``why``) and keeps the Laplace draws.

The joint width SD is expected near ``1 / sqrt(K)`` of a single frame's;
``validation/movie_analysis.py`` measures that ratio and the joint posterior's coverage on
simulated movies.

Each frame's own N and b carry their own vague prior, and integrating them out leaves in each
frame's marginal likelihood a term, ``-(1/2) log det`` of the (N, b) information, that depends
on the widths: it pulls the posterior of s_x, s_y below the joint MLE by about 0.007 of one
frame's SD per frame (0.006-0.009 from N = 15 000 to 500, b per frame; 0.0002-0.004 with
``"one b"``). The posterior is exact for that model, but the shift grows with K against an SD
that shrinks as 1/sqrt(K): a z-score of about -0.007 sqrt(K), -0.09 at K ~ 150 (measured on
paper-movies: -0.0072 +- 0.0004 per frame) and -0.25 near K ~ 1 200. Sharing b (``"one b"``),
where the background is constant, removes most of it; very long traces would want a shared
(hierarchical) prior for N and b.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.batched import MAX_DRAWS_PER_ESS
from bayespsf.inference.fused import score
from bayespsf.inference.importance import KHAT_MAX, ImportanceRun, systematic_resample
from bayespsf.inference.settings import Settings, check_settings
from bayespsf.inference.solver import (
    DECREMENT,
    MAX_ITERATIONS,
    STATIONARY,
    box,
    evaluate,
    freeze_bounds,
    from_internal,
    observed_information,
    to_internal,
)
from bayespsf.model import LOG_PARAMETERS, Model
from bayespsf.psf import PARAMETER_NAMES

SHARED = {"b per frame": (0, 1, 2, 3), "one b": (0, 1, 2, 3, 5)}
DISAGREE_P = 1e-3  # per-frame positions this improbable under one position: not one position
MIN_LAPLACE_DRAWS = 50  # fewest Laplace draws inside the prior that summarise a posterior
WIDE_FRACTION, WIDE_SCALE = 0.1, 1.5  # the defensive mixture's wide component


@dataclass(frozen=True)
class Layout:
    """Where each frame's six parameters sit in the joint vector: the shared ones first, then
    each frame's own, frame after frame."""

    frames: int
    shared: tuple[int, ...]

    @property
    def own(self) -> tuple[int, ...]:
        return tuple(k for k in range(6) if k not in self.shared)

    @property
    def size(self) -> int:
        return len(self.shared) + self.frames * len(self.own)

    def split(self, v: np.ndarray) -> np.ndarray:
        """Joint vectors (..., size) to per-frame vectors (..., frames, 6)."""
        v = np.asarray(v, dtype=np.float64)
        out = np.empty((*v.shape[:-1], self.frames, 6))
        s = len(self.shared)
        out[..., list(self.shared)] = v[..., None, :s]
        out[..., list(self.own)] = v[..., s:].reshape(*v.shape[:-1], self.frames, -1)
        return out

    def join(self, per_frame: np.ndarray) -> np.ndarray:
        """Per-frame vectors (..., frames, 6) to joint vectors, the shared part from frame 0."""
        per_frame = np.asarray(per_frame, dtype=np.float64)
        own = per_frame[..., list(self.own)].reshape(*per_frame.shape[:-2], -1)
        return np.concatenate([per_frame[..., 0, list(self.shared)], own], axis=-1)

    def gather(self, per_frame: np.ndarray) -> np.ndarray:
        """A per-frame gradient (frames, 6) as the joint gradient (summed over the shared)."""
        own = per_frame[:, list(self.own)].reshape(-1)
        return np.concatenate([per_frame[:, list(self.shared)].sum(axis=0), own])

    def arrow(self, blocks: np.ndarray) -> np.ndarray:
        """Per-frame 6 x 6 information matrices (frames, 6, 6) as the joint matrix: shared
        blocks summed, each frame's own block and its coupling to the shared in place."""
        s, o = list(self.shared), list(self.own)
        ns, no = len(s), len(o)
        out = np.zeros((self.size, self.size))
        out[:ns, :ns] = blocks[:, s][:, :, s].sum(axis=0)
        for k, block in enumerate(blocks):
            at = slice(ns + k * no, ns + (k + 1) * no)
            out[at, at] = block[np.ix_(o, o)]
            out[:ns, at] = block[np.ix_(s, o)]
            out[at, :ns] = block[np.ix_(o, s)]
        return out


@dataclass
class JointPosterior:
    """Equally weighted draws of the joint parameters, and what made them.

    Attributes
    ----------
    layout : Layout
        Which parameters the frames share and where each sits in the joint vector.
    draws : ndarray, shape (m, frames, 6)
        ``x0 y0 s_x s_y`` (nm), ``N`` (photons), ``b`` (photons per pixel) per frame:
        ``draws[i, k]`` is draw ``i`` of frame ``k`` (one NaN draw where there are none).
    fit : ndarray, shape (frames, 6)
        The joint maximum-likelihood fit.
    info : dict
        What made the draws: ``frames``, ``shared``, ``mle_converged``, ``method``
        (``"importance"``, ``"laplace"`` or ``"none"``), ``converged``, ``why``, and where
        importance sampling ran ``khat``, ``ess``, ``draws_scored`` and ``seconds``.

    See Also
    --------
    joint_posterior : makes one.
    """

    layout: Layout
    draws: np.ndarray  # (m, frames, 6)
    fit: np.ndarray  # (frames, 6): the joint maximum-likelihood fit
    info: dict = field(default_factory=dict)

    def row(self) -> dict:
        """The molecule's summary, as one row of ``joint_posteriors``' table.

        Returns
        -------
        dict
            Per shared parameter its posterior mean, SD and central 68% and 95% intervals
            (``<p>_joint_mean``, ``_sd``, ``_q2.5``, ``_q16``, ``_q84``, ``_q97.5``; NaN
            without draws), the joint MLE (``<p>_joint_mle``), and ``info``, prefixed
            ``joint_``.
        """
        out = {}
        for k in self.layout.shared:
            name, x = PARAMETER_NAMES[k], self.draws[:, 0, k]
            usable = len(x) > 1 and np.isfinite(x).all()  # NaN where there are no draws
            out[f"{name}_joint_mean"] = float(x.mean()) if usable else np.nan
            out[f"{name}_joint_sd"] = float(x.std(ddof=1)) if usable else np.nan
            for q in (2.5, 16.0, 84.0, 97.5):
                out[f"{name}_joint_q{q:g}"] = float(np.percentile(x, q)) if usable else np.nan
            out[f"{name}_joint_mle"] = float(self.fit[0, k])
        out.update({f"joint_{key}": value for key, value in self.info.items()})
        return out


def _check(counts, model, starts, shared):
    counts = model.check_shape(counts)
    if counts.ndim != 3 or len(counts) < 2:
        raise BayespsfInputError(
            f"counts must be the frames (K >= 2, roi, roi) of one molecule, got shape "
            f"{np.shape(counts)}"
        )
    starts = np.asarray(starts, dtype=np.float64)
    if starts.shape != (len(counts), 6) or not np.all(np.isfinite(starts)):
        raise BayespsfInputError(
            f"starts must be finite per-frame parameters of shape ({len(counts)}, 6), got "
            f"shape {starts.shape}"
        )
    if np.any(starts[:, 2:5] <= 0):
        raise BayespsfInputError("starts: s_x, s_y and N must be > 0 in every frame")
    if shared not in SHARED:
        raise BayespsfInputError(f"shared must be one of {sorted(SHARED)}, got {shared!r}")
    problems = [p for p in model.roi_problems(counts) if p is not None]
    if problems:
        raise BayespsfInputError(f"counts: a frame the model cannot analyse: {problems[0]}")
    return counts, starts, Layout(len(counts), SHARED[shared])


def joint_mle(model, counts, starts, layout: Layout):
    """The joint maximum-likelihood fit (module docstring, step 1) from per-frame ``starts``
    (frames, 6; the shared parameters start at their per-frame median), with the rules of
    ``bayespsf.inference.solver``: a coordinate on the search box's edge whose gradient points
    out is held there (``freeze_bounds``: b = 0 for a background-free frame), and a fit where
    no step lowers ``-log L`` is converged if its Newton decrement is below ``STATIONARY`` per
    frame.
    Returns ``(params (frames, 6), converged, message)``."""
    a = model.pixel_size
    low, high = box(model.roi)
    u = np.clip(to_internal(starts, a), low, high)
    u[:, list(layout.shared)] = np.median(u[:, list(layout.shared)], axis=0)
    f, grad, metric = evaluate(model, counts, from_internal(u, a))
    if not np.isfinite(f.sum()):
        return from_internal(u, a), False, "non-finite likelihood at the start"
    damping = 1e-3
    for _ in range(MAX_ITERATIONS):
        g, m = freeze_bounds(u, grad, metric, low, high)
        g, m = layout.gather(g), layout.arrow(m)
        try:
            decrement = float(g @ np.linalg.solve(m, g))
            step = np.linalg.solve(m + damping * np.diag(np.diag(m)), -g)
        except np.linalg.LinAlgError:
            return from_internal(u, a), False, "singular joint information"
        if decrement < DECREMENT * layout.frames:
            return from_internal(u, a), True, "Newton decrement below 1e-10 per frame"
        trial = np.clip(layout.split(layout.join(u) + step), low, high)
        f_trial, grad_trial, metric_trial = evaluate(model, counts, from_internal(trial, a))
        if np.isfinite(f_trial.sum()) and f_trial.sum() < f.sum():
            u, f, grad, metric = trial, f_trial, grad_trial, metric_trial
            damping /= 10
            continue
        damping *= 10
        if damping > 1e12:  # no step lowers -log L: stationary in float64, or stuck
            if decrement < STATIONARY * layout.frames:
                return from_internal(u, a), True, "no step lowers -log L (stationary to rounding)"
            return from_internal(u, a), False, "no step lowers -log L away from a stationary point"
    return from_internal(u, a), False, f"iteration limit ({MAX_ITERATIONS})"


def _laplace(model, counts, fit, layout: Layout):
    """Centre and covariance of the joint Laplace approximation in sampling coordinates."""
    dp_dz = np.ones_like(fit)
    dp_dz[:, 2:5] = fit[:, 2:5]  # the sampling coordinates are the logs of s_x, s_y, N
    information = observed_information(model, counts, fit) * dp_dz[:, :, None]
    information *= dp_dz[:, None, :]
    precision = layout.arrow(information)
    centre = np.clip(fit, *model.prior_bounds())  # as batched.laplace_in_z
    return layout.join(model.to_unconstrained(centre)), np.linalg.inv(precision)


class DefensiveProposal:
    """The Laplace Gaussian ``N(centre, C)`` mixed with a fraction ``WIDE_FRACTION`` of
    ``N(centre, WIDE_SCALE^2 C)``: a defensive mixture (Hesterberg, Technometrics 37 (1995)),
    which bounds the importance weights wherever the posterior's tails are lighter than the
    wide component's, at little cost in efficiency (on 8 frames of 1 000 photons the share
    of effective draws fell from 0.94 to 0.89; on 100 frames from 0.42 to 0.38). A Student-t
    proposal, as for one ROI, loses more in 4 + 2K dimensions (0.2 with 30 degrees of freedom
    on 100 frames). Draws use a NumPy RandomState's stream, as ``ImportanceRun`` expects."""

    def __init__(self, centre, covariance):
        self.centre = np.asarray(centre, dtype=np.float64)
        self.cholesky = np.linalg.cholesky(covariance)

    def laplace(self, n: int, random) -> np.ndarray:
        """``n`` draws of the Laplace Gaussian alone."""
        return self.centre + random.standard_normal((n, len(self.centre))) @ self.cholesky.T

    def draw(self, n: int, random) -> tuple[np.ndarray, np.ndarray]:
        d = len(self.centre)
        e = random.standard_normal((n, d))
        e[random.random_sample(n) < WIDE_FRACTION] *= WIDE_SCALE
        r2 = np.sum(e * e, axis=-1)
        log_g = np.logaddexp(
            np.log1p(-WIDE_FRACTION) - 0.5 * r2,
            np.log(WIDE_FRACTION) - d * np.log(WIDE_SCALE) - 0.5 * r2 / WIDE_SCALE**2,
        )
        return self.centre + e @ self.cholesky.T, log_g


def joint_log_posterior(model, counts, layout: Layout, z, anchor) -> np.ndarray:
    """Log posterior (up to a constant) of joint draws ``z`` (n, size) in sampling
    coordinates: the frames' ``Model.log_posterior`` summed, less the ``K - 1`` extra copies of
    each shared parameter's log prior and log-coordinate Jacobian.

    The prior is a product over parameters, so a shared parameter's log prior is the log prior
    of a vector whose other parameters are held at ``anchor`` (one parameter vector (6,) inside
    the prior's support, the same for every call: the constant it adds must not change between
    the batches of one importance run)."""
    per_frame = layout.split(z)  # (n, K, 6)
    frames = per_frame.shape[1]
    total = np.sum(score(model, counts, [per_frame[:, k] for k in range(frames)]), axis=0)
    shared = list(layout.shared)
    reference = np.broadcast_to(np.asarray(anchor, dtype=np.float64), per_frame[:, 0].shape)
    reference = reference.copy()
    with np.errstate(over="ignore"):  # exp overflow -> inf -> outside the prior's support
        reference[:, shared] = model.from_unconstrained(per_frame[:, 0])[:, shared]
    extra = model.log_prior(reference)
    extra = extra + per_frame[:, 0, [k for k in shared if k in LOG_PARAMETERS]].sum(axis=1)
    out = np.full(len(per_frame), -np.inf)
    inside = np.isfinite(total) & np.isfinite(extra)
    out[inside] = total[inside] - (frames - 1) * extra[inside]
    return out


def joint_posterior(
    counts: ArrayLike,
    model: Model,
    starts: ArrayLike,
    *,
    seed: int = 0,
    ess: float = Settings.ess,
    shared: str = "b per frame",
) -> JointPosterior:
    """The joint posterior of one immobile molecule over its frames.

    Parameters
    ----------
    counts : array_like, shape (K, roi, roi)
        The molecule's valid frames (K >= 2), in ADU.
    model : Model
        The model of one frame (its ROI size that of ``counts``).
    starts : array_like, shape (K, 6)
        Per-frame estimates (``fit_mle``'s ``x0 y0 s_x s_y N b``: nm, photons, photons per
        pixel) to start the joint fit from.
    seed : int
        Seeds the importance draws and their resampling.
    ess : float
        Effective sample size of the importance sampling (the draws kept).
    shared : {"b per frame", "one b"}
        Whether the background is each frame's own (default) or shared by all frames.

    Returns
    -------
    JointPosterior
        Its draws per frame, the joint fit, and ``info``: ``method`` is ``"importance"``
        where importance sampling passed (``converged`` True), ``"laplace"`` where it did not
        (the Laplace draws inside the prior; ``why`` says so), ``"none"`` where the joint
        information is singular or too few Laplace draws lie inside the prior. A failure's
        ``why`` names frames whose own fits disagree on the position (a molecule that moved,
        or frames of more than one molecule) and a joint fit on the prior's edge (b = 0).

    Raises
    ------
    BayespsfInputError
        If ``counts`` is not ``(K >= 2, roi, roi)``, a frame is one the model cannot analyse,
        ``starts`` is not finite of shape ``(K, 6)`` with positive widths and N, ``shared``
        is unknown, or ``seed`` or ``ess`` is out of range.

    See Also
    --------
    bayespsf.parallel.joint_posteriors : the joint posteriors of many molecules.
    fit_mle : per-frame fits to start from.

    Notes
    -----
    The method (joint fit, Laplace approximation, defensive importance sampling) and the
    small pull of the widths by each frame's own N and b are described in the module
    docstring.
    """
    started = time.perf_counter()
    ess = check_settings(seed=seed, ess=ess).ess
    counts, starts, layout = _check(counts, model, starts, shared)
    fit, fit_ok, fit_message = joint_mle(model, counts, starts, layout)
    info = {"frames": layout.frames, "shared": shared, "mle_converged": fit_ok}
    random = np.random.RandomState(np.random.SeedSequence(int(seed)).generate_state(1)[0])
    anchor = np.clip(fit[0], *model.prior_bounds())
    try:
        centre, covariance = _laplace(model, counts, fit, layout)
        proposal = DefensiveProposal(centre, covariance)
    except np.linalg.LinAlgError:
        why = "the joint information is singular" + _cause(model, counts, starts)
        info.update(method="none", converged=False, why=why)
        return JointPosterior(layout, np.full((1, layout.frames, 6), np.nan), fit, info)
    run = ImportanceRun(proposal, ess, int(MAX_DRAWS_PER_ESS * ess), random)
    while not run.done:
        z = run.propose()
        run.take(joint_log_posterior(model, counts, layout, z, anchor))
    keep = max(int(ess), 1)
    # importance sampling is exact where k-hat passes, wherever its proposal is centred
    ok = run.khat <= KHAT_MAX and run.achieved >= ess
    if ok:
        draws = model.from_unconstrained(
            layout.split(run.draws[systematic_resample(run.weights, keep, random)])
        )
        why = f"importance sampling: k-hat {run.khat:.2f} <= {KHAT_MAX}"
    else:
        draws = _laplace_within_prior(model, layout, proposal, keep, random)
        why = (
            (
                f"the Laplace approximation: importance sampling failed (k-hat {run.khat:.2f}, "
                f"ESS {run.achieved:.0f} of {ess:g})"
            )
            + ("" if fit_ok else f"; {fit_message}")
            + _cause(model, counts, starts)
        )
    method = "importance" if ok else "laplace"
    if len(draws) < MIN_LAPLACE_DRAWS:
        method, draws = "none", np.full((1, layout.frames, 6), np.nan)
        edge = _on_edge(model, fit)
        why += (
            f"; and fewer than {MIN_LAPLACE_DRAWS} of its Laplace draws lie in the prior's "
            "support" + (f" (the joint fit is on its edge: {edge})" if edge else "")
        )
    info.update(
        method=method,
        converged=bool(ok),
        why=why,
        khat=float(run.khat),
        ess=float(run.achieved),
        draws_scored=len(run.draws),
        seconds=time.perf_counter() - started,
    )
    return JointPosterior(layout, draws, fit, info)


def _cause(model, counts, starts) -> str:
    """``"; "`` and why the frames are not one immobile molecule where their own fits'
    positions disagree: x0 or y0 scatters about its inverse-variance weighted mean more than
    the fits' SDs (inverse observed information) allow, at a chi-square p-value (K - 1
    degrees of freedom) below ``DISAGREE_P``; else ``""``."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        covariance = np.linalg.pinv(observed_information(model, counts, starts), hermitian=True)
    found = []
    for k, name in ((0, "x0"), (1, "y0")):
        var = covariance[:, k, k]
        good = np.isfinite(var) & (var > 0) & np.isfinite(starts[:, k])
        if good.sum() < 2:
            continue
        x, w = starts[good, k], 1.0 / var[good]
        z = (x - np.sum(w * x) / np.sum(w)) * np.sqrt(w)
        chi2, dof = float(np.sum(z**2)), int(good.sum()) - 1
        p = float(stats.chi2.sf(chi2, dof))
        if p < DISAGREE_P:
            found.append(
                f"{name}: chi-square {chi2:.3g} on {dof} degrees of freedom, p "
                + (f"= {p:.2g}" if p > 0 else "< 1e-300")
                + f", a frame {np.abs(z).max():.3g} SDs from their mean"
            )
    if not found:
        return ""
    return (
        "; the frames' own fits disagree on the position (" + "; ".join(found) + "): the "
        "molecule moved, or the frames are not one molecule, which the joint model's one "
        "position does not describe"
    )


def _on_edge(model, fit) -> str:
    """Which parameters of the joint fit ``fit`` (frames, 6) lie on (or beyond) an edge of the
    prior's support, and in which frames; ``""`` if none does."""
    low, high = model.prior_bounds()
    found = []
    for k, name in enumerate(PARAMETER_NAMES):
        for bound, beyond in ((low[k], fit[:, k] < low[k]), (high[k], fit[:, k] > high[k])):
            if not np.isfinite(bound):
                continue
            on = np.isclose(fit[:, k], bound, rtol=1e-9, atol=1e-9) | beyond
            if on.all():
                found.append(f"{name} = {bound:g} in every frame")
            elif on.any():
                frames = np.flatnonzero(on)
                listed = ", ".join(str(f) for f in frames[:5]) + (
                    ", ..." if len(frames) > 5 else ""
                )
                found.append(f"{name} = {bound:g} in frame{'s' * (len(frames) > 1)} {listed}")
    return "; ".join(found)


def _laplace_within_prior(model, layout: Layout, proposal, keep: int, random) -> np.ndarray:
    """``keep`` draws of the joint Laplace Gaussian (not the defensive mixture) inside the
    prior's support, as ``bayespsf.inference.batched`` keeps a ROI's Laplace draws; fewer if the
    support holds less than half of ``2 keep`` draws."""
    with np.errstate(over="ignore"):  # exp overflow -> inf -> outside the prior's support
        draws = model.from_unconstrained(layout.split(proposal.laplace(2 * keep, random)))
    inside = np.isfinite(model.log_prior(draws)).all(axis=1)
    return draws[inside][:keep]


__all__ = [
    "SHARED",
    "JointPosterior",
    "Layout",
    "joint_log_posterior",
    "joint_mle",
    "joint_posterior",
]
