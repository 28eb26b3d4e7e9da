"""Pareto-smoothed importance sampling from the Laplace approximation: a posterior without a
Markov chain, for molecules whose posterior is close to its Laplace approximation.

Draws come from the multivariate Student-t of the sampler's independence move (centred at the
maximum-likelihood fit, scaled by the inverse observed information, in sampling coordinates),
all scored in one vectorised log-posterior call. The importance ratios ``pi(z) / g(z)`` are
Pareto-smoothed (PSIS; Vehtari, Simpson, Gelman, Yao & Gabry, JMLR 25 (2024); ``arviz_stats``'
algorithm, batched in ``bayespsf.inference.psis``), and their Pareto shape k-hat says whether
the estimate can be trusted: below 0.7 the smoothed estimates converge at a usable rate, above it
they do not, and the molecule is sampled by MCMC instead (``bayespsf.sample_posterior``
does this when ``method="importance"``; the result says which method made it).

Draws are added in batches (the first ``first_batch(ess)`` draws, then as many as the ESS per
draw so far predicts) until the effective sample size of the smoothed weights,
``1 / sum(w**2)``, reaches the target; the result holds ``ess`` (rounded down) draws resampled
from the weighted set by systematic resampling (Kitagawa, J. Comput. Graph. Stat. 5 (1996)),
so that a Posterior keeps its meaning: equally weighted draws whose number is their effective
sample size.
"""

from __future__ import annotations

import emcee
import numpy as np

from bayespsf.inference.psis import psis as pareto_smoothed

KHAT_MAX = 0.7
MIN_BATCH = 200
CHAINS = 4


class IndependenceMove(emcee.moves.MHMove):
    """Independence Metropolis-Hastings: every walker proposes a fresh draw from a fixed
    multivariate Student-t ``t_dof(centre, scale)``, accepted with probability
    ``min(1, pi(z') g(z) / (pi(z) g(z')))`` (Tierney, Ann. Stat. 22 (1994), sec. 2.3.3).

    With ``centre`` and ``scale`` from the Laplace approximation at the maximum-likelihood fit
    (a function of the data only, so the chain is a valid Markov chain), proposals are nearly
    independent draws from a near-Gaussian posterior; the t's heavier tails keep the importance
    ratio bounded where the posterior's tails are heavier than the Laplace Gaussian's.
    """

    def __init__(self, centre, scale, dof: float = 5.0):
        self.centre = np.asarray(centre, dtype=np.float64)
        self.cholesky = np.linalg.cholesky(np.asarray(scale, dtype=np.float64))
        self.whiten = np.linalg.inv(self.cholesky)  # z - centre -> independent coordinates
        self.dof = float(dof)
        super().__init__(self._propose, ndim=len(self.centre))

    def _log_kernel(self, u) -> np.ndarray:
        return -0.5 * (self.dof + len(self.centre)) * np.log1p(np.sum(u * u, axis=-1) / self.dof)

    def log_density(self, z) -> np.ndarray:
        """Log proposal density up to a constant."""
        return self._log_kernel((np.asarray(z) - self.centre) @ self.whiten.T)

    def draw(self, n: int, random) -> tuple[np.ndarray, np.ndarray]:
        """``n`` draws (a NumPy RandomState's stream) and their log density."""
        radius = np.sqrt(self.dof / random.chisquare(self.dof, n))
        u = radius[:, None] * random.standard_normal((n, len(self.centre)))
        return self.centre + u @ self.cholesky.T, self._log_kernel(u)

    def _propose(self, coords, random):
        new, log_new = self.draw(len(coords), random)
        return new, self.log_density(coords) - log_new


def psis(log_ratio: np.ndarray) -> tuple[np.ndarray, float | np.ndarray]:
    """Normalised Pareto-smoothed importance weights of ``log_ratio`` (draws on the last
    axis, any leading batch shape; ``bayespsf.inference.psis``, ``arviz_stats``' algorithm)
    and their k-hat (a float for one vector of draws)."""
    # Ratios spanning more than the double range (a proposal far too wide: a 401 x 401 ROI
    # without background) overflow the tail fit; k-hat or the weights are then not finite,
    # which the callers read as a failed run (``ImportanceRun``), so the warnings are noise
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        log_w, khat = pareto_smoothed(np.asarray(log_ratio, dtype=np.float64))
        w = np.exp(log_w - log_w.max(axis=-1, keepdims=True))
        w = w / w.sum(axis=-1, keepdims=True)
    return (w, float(khat)) if np.ndim(khat) == 0 else (w, khat)


def first_batch(ess: float) -> int:
    """Draws scored in an importance run's first batch: the ESS target over the efficiency
    of a good Laplace proposal (~0.8 on bright molecules, ``benchmarks/README.md``), at
    least ``MIN_BATCH``."""
    return max(MIN_BATCH, int(np.ceil(ess / 0.77)))


class GaussianProposal:
    """The Laplace approximation itself, ``N(centre, scale)``, as an importance proposal: the
    first stage of ``auto`` (``bayespsf.inference.batched``), whose pilot draws it continues.

    Where the pilot's weights have a small SD the posterior is close to this Gaussian, and it
    is a more efficient proposal than the Student-t (ESS per draw ``1 / (1 + sd(w)**2)``, ~0.97
    at a pilot SD of 0.17, against ~0.77 for the t); a posterior whose tails are heavier than
    the Gaussian's shows as k-hat above ``KHAT_MAX``, and the ROI goes on to the t.
    """

    def __init__(self, centre, scale, cholesky=None):
        self.centre = np.asarray(centre, dtype=np.float64)
        if cholesky is None:
            cholesky = np.linalg.cholesky(np.asarray(scale, dtype=np.float64))
        self.cholesky = cholesky  # of ``scale``, where the caller has it already

    def draw(self, n: int, random) -> tuple[np.ndarray, np.ndarray]:
        """``n`` draws (``random``: a NumPy Generator or RandomState) and their log density
        up to a constant."""
        u = random.standard_normal((n, len(self.centre)))
        return self.centre + u @ self.cholesky.T, -0.5 * np.sum(u * u, axis=1)


class DefensiveMixture:
    """A mixture of Student-t proposals (``IndependenceMove``) in fixed shares, as one
    importance proposal: each draw comes from one part, its density is the mixture's.

    With a part that covers the posterior's bulk (the Laplace Student-t) the importance
    ratio stays below ``1 / share`` of that part's own wherever it is bounded, whatever the
    other parts do (defensive importance sampling: Hesterberg, Technometrics 37 (1995)); the
    other part is fitted to weighted draws of the posterior (``fitted_t``), which follows a
    shifted or skewed posterior the Laplace misses (adaptive importance sampling: Cornuet,
    Marin, Mira & Robert, Scand. J. Stat. 39 (2012)).
    """

    def __init__(self, parts, shares):
        self.parts = list(parts)
        shares = np.asarray(shares, dtype=np.float64)
        self.shares = shares / shares.sum()
        # each part's normalisation relative to the others: its Cholesky factor's determinant
        # (same dimension and degrees of freedom, so the rest of the constant is shared)
        self.log_weights = np.log(self.shares) - [
            np.sum(np.log(np.diag(part.cholesky))) for part in self.parts
        ]

    def log_density(self, z) -> np.ndarray:
        """Log mixture density up to a constant."""
        pairs = zip(self.log_weights, self.parts, strict=True)
        terms = [w + part.log_density(z) for w, part in pairs]
        return np.logaddexp.reduce(terms, axis=0)

    def draw(self, n: int, random) -> tuple[np.ndarray, np.ndarray]:
        """``n`` draws (a NumPy RandomState's stream: the parts' counts, then each part's
        draws in turn) and their log mixture density."""
        counts = random.multinomial(n, self.shares)
        z = np.concatenate(
            [part.draw(int(k), random)[0] for part, k in zip(self.parts, counts, strict=True) if k]
        )
        return z, self.log_density(z)


def fitted_t(draws: np.ndarray, weights: np.ndarray) -> IndependenceMove:
    """The Student-t proposal with the weighted mean and covariance of ``draws`` (k, 6)
    under normalised ``weights`` (k,).

    Raises
    ------
    numpy.linalg.LinAlgError
        Where that covariance is not positive definite (too few draws carry the weight).
    """
    mean = weights @ draws
    centred = draws - mean
    return IndependenceMove(mean, (weights[:, None] * centred).T @ centred)


class ImportanceRun:
    """One ROI's importance sampling, batch by batch: ``propose()`` gives the next batch's
    draws (sampling coordinates), ``take(log_posterior)`` scores them; ``done`` once the
    smoothed weights' ESS reaches ``ess``, or k-hat exceeds ``KHAT_MAX``, or ``max_draws``
    are scored. Several runs advance together in ``bayespsf.inference.batched`` (one
    vectorised log-posterior call for the batches of many ROIs, and ``add`` then ``judge``
    with the smoothed weights of many ROIs computed together); each keeps its own random
    stream, so a ROI's draws do not depend on its neighbours. ``first`` (draws, their log
    proposal density and log posterior) are draws of the same proposal scored already (a
    pilot): they are added and size the first batch by their raw ESS; the run is judged
    (k-hat, ESS) from its first batch on, as a pilot's tail is too short for k-hat.
    ``margin``: each batch after the first scores this factor more draws than the ESS per
    draw so far predicts are needed (1.2; less where that prediction is sharp).
    """

    def __init__(self, proposal, ess: float, max_draws: int, random, first=None, margin=1.2):
        self.proposal, self.ess, self.max_draws, self.random = proposal, ess, max_draws, random
        self.margin = margin
        self.batch = min(first_batch(ess), max_draws)
        self._z, self._log_ratio, self._pending = [], [], None
        self.done = False
        self.weights, self.khat, self.achieved = None, np.nan, 0.0
        if first is not None:  # sized by its raw ESS: k-hat from a pilot's tail is noise
            z, log_g, log_posterior = first
            self._pending = (z, log_g)
            ratio = self.add(log_posterior)
            with np.errstate(invalid="ignore"):
                w = np.exp(ratio - ratio.max())
                raw = np.sum(w) ** 2 / np.sum(w * w)
            self._size(raw if np.isfinite(raw) else 1.0, len(ratio))

    def propose(self) -> np.ndarray:
        z, log_g = self.proposal.draw(self.batch, self.random)
        self._pending = (z, log_g)
        return z

    def add(self, log_posterior: np.ndarray) -> np.ndarray:
        """Keep the pending batch with its log posterior; returns every log ratio so far."""
        z, log_g = self._pending
        self._z.append(z)
        self._log_ratio.append(log_posterior - log_g)
        return self.log_ratio

    @property
    def log_ratio(self) -> np.ndarray:
        """The log importance ratios of every draw scored so far (empty before the first)."""
        return np.concatenate(self._log_ratio) if self._log_ratio else np.empty(0)

    def judge(self, weights: np.ndarray, khat: float) -> None:
        """Take the smoothed normalised weights of every draw so far and their k-hat: done,
        or the size of the next batch."""
        self.weights, self.khat = weights, khat
        self.achieved = 1.0 / np.sum(self.weights * self.weights)
        scored = len(weights)
        if not (np.isfinite(self.khat) and np.isfinite(self.achieved)):  # overflowed: failed
            self.khat, self.achieved, self.done = np.inf, 0.0, True
            return
        if self.achieved >= self.ess or self.khat > KHAT_MAX or scored >= self.max_draws:
            self.done = True
            return
        self._size(self.achieved, scored)

    def _size(self, achieved: float, scored: int) -> None:
        """The next batch: the draws still needed as the ESS per draw so far predicts them,
        times the margin."""
        needed = int(self.margin * (self.ess - achieved) * scored / max(achieved, 1.0))
        self.batch = int(np.clip(needed, MIN_BATCH // 2, self.max_draws - scored))

    def take(self, log_posterior: np.ndarray) -> None:
        """``add`` and ``judge`` for this run alone."""
        self.judge(*psis(self.add(log_posterior)))

    @property
    def draws(self) -> np.ndarray:
        """Every draw scored so far (sampling coordinates), in the order of ``weights``."""
        return np.concatenate(self._z)


def systematic_resample(weights: np.ndarray, n: int, rng) -> np.ndarray:
    """Indices of ``n`` draws by systematic resampling, in random order."""
    positions = (rng.random() + np.arange(n)) / n
    index = np.searchsorted(np.cumsum(weights), positions)
    return rng.permutation(np.minimum(index, len(weights) - 1))


__all__ = [
    "KHAT_MAX",
    "DefensiveMixture",
    "GaussianProposal",
    "ImportanceRun",
    "IndependenceMove",
    "first_batch",
    "fitted_t",
    "psis",
    "systematic_resample",
]
