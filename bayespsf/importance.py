"""Pareto-smoothed importance sampling from the Laplace approximation: a posterior without a
Markov chain, for molecules whose posterior is close to its Laplace approximation.

Draws come from the multivariate Student-t of the sampler's independence move (centred at the
maximum-likelihood fit, scaled by the inverse observed information, in sampling coordinates),
all scored in one vectorised log-posterior call. The importance ratios
``pi(z) / g(z)`` are Pareto-smoothed (PSIS; Vehtari, Simpson, Gelman, Yao & Gabry, JMLR 25
(2024), as implemented in ``arviz_stats``), and their Pareto shape k-hat says whether the
estimate can be trusted: below 0.7 the smoothed estimates converge at a usable rate, above it
they do not, and the molecule is sampled by MCMC instead (``bayespsf.sample_posterior``
does this when ``method="importance"``; the result says which method made it).

Draws are added in batches until the effective sample size of the smoothed weights,
``1 / sum(w**2)``, reaches the target; the result holds ``ess`` (rounded down) draws resampled
from the weighted set by systematic resampling (Kitagawa, J. Comput. Graph. Stat. 5 (1996)),
so that a Posterior keeps its meaning: equally weighted draws whose number is their effective
sample size.
"""

from __future__ import annotations

import numpy as np

KHAT_MAX = 0.7
FIRST_BATCH = 1000
CHAINS = 4


def psis(log_ratio: np.ndarray) -> tuple[np.ndarray, float]:
    """Normalised Pareto-smoothed importance weights of ``log_ratio`` and their k-hat."""
    from arviz_stats.base.array import array_stats

    # arviz_stats smooths exp(-value) (its input is a log-likelihood in PSIS-LOO): negate
    log_w, khat = array_stats.psislw(-np.asarray(log_ratio, dtype=np.float64))
    w = np.exp(log_w - log_w.max())
    return w / w.sum(), float(khat)


def importance_draws(counts, model, proposal, ess: float, max_draws: int, random):
    """Weighted draws until the smoothed weights' ESS reaches ``ess`` (or k-hat exceeds
    ``KHAT_MAX``, or ``max_draws`` are scored); ``random`` is a NumPy RandomState.

    Returns ``(z, weights, khat)``, ``z`` in sampling coordinates.
    """
    zs, log_ratios = [], []
    batch = FIRST_BATCH
    while True:
        z, log_g = proposal.draw(batch, random)
        zs.append(z)
        log_ratios.append(model.log_posterior(z, counts) - log_g)
        z_all, log_ratio = np.concatenate(zs), np.concatenate(log_ratios)
        weights, khat = psis(log_ratio)
        achieved = 1.0 / np.sum(weights * weights)
        if achieved >= ess or khat > KHAT_MAX or len(z_all) >= max_draws:
            return z_all, weights, khat
        # the ESS per draw so far predicts the draws still needed (plus 20%)
        needed = int(1.2 * (ess - achieved) * len(z_all) / max(achieved, 1.0))
        batch = int(np.clip(needed, FIRST_BATCH // 2, max_draws - len(z_all)))


def systematic_resample(weights: np.ndarray, n: int, rng) -> np.ndarray:
    """Indices of ``n`` draws by systematic resampling, in random order."""
    positions = (rng.random() + np.arange(n)) / n
    index = np.searchsorted(np.cumsum(weights), positions)
    return rng.permutation(np.minimum(index, len(weights) - 1))


__all__ = ["KHAT_MAX", "importance_draws", "psis", "systematic_resample"]
