"""The summary row of one molecule's posterior, and coverage over a table of rows.

A row holds, per parameter, the posterior mean, SD, quantiles (the central 50/68/90/95%
intervals), ESS and autocorrelation time, and, when the truth is known, the truth and its rank
among ``RANK_DRAWS`` near-independent posterior draws (the statistic of simulation-based
calibration, Talts et al., arXiv:1804.06788). ``sample_many`` writes one row per molecule
whichever method made its posterior (``method`` column: ``laplace``, ``importance``, ``mcmc``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.gof import FIT_KEYS
from bayespsf.psf import PARAMETER_NAMES

QUANTILES = (0.025, 0.05, 0.16, 0.25, 0.5, 0.75, 0.84, 0.95, 0.975)
RANK_DRAWS = 99  # ranks 0..99: a histogram of 100 equally likely values under calibration


def quantile_column(name: str, q: float) -> str:
    return f"{name}_q{1000 * q:04.0f}"


def central_interval(prob: float) -> tuple[float, float]:
    """The quantiles bounding the central ``prob`` interval (one of 0.5, 0.68, 0.9, 0.95)."""
    low, high = round((1 - prob) / 2, 3), round((1 + prob) / 2, 3)
    if low not in QUANTILES or high not in QUANTILES:
        raise BayespsfInputError(f"prob must be one of 0.5, 0.68, 0.9, 0.95; got {prob!r}")
    return low, high


def draws_row(
    flat: np.ndarray,
    index: int,
    seed: int,
    info: dict,
    truth=None,
    independent: np.ndarray | None = None,
    tau=None,
    ess=None,
) -> dict:
    """The summary row of equally weighted draws ``flat`` (k, 6).

    ``independent`` are the near-independent draws that ranks are taken from (default
    ``flat``: draws that are independent already, as importance and Laplace draws are);
    ``tau`` and ``ess`` per parameter (default 1 and ``info["ess"]``). The goodness of fit
    in ``info`` (``bayespsf.inference.gof.FIT_KEYS``) ends the row where present.
    """
    method = info.get("method", "mcmc")
    converged = bool(info.get("converged", False))
    row = {
        "molecule": int(index),
        "seed": int(seed),
        "converged": converged,
        "status": "converged" if converged else "not converged",
        "message": info.get("diagnosis", ""),
        "method": method,
        "why": info.get("why", ""),
        "steps": int(info.get("steps", 0)),
        "draws": int(flat.shape[0]),
        "acceptance": float(info.get("acceptance", np.nan)),
        "seconds": float(info.get("seconds", np.nan)),
    }
    quantiles = np.quantile(flat, QUANTILES, axis=0)
    means, sds = flat.mean(axis=0), flat.std(axis=0, ddof=1)
    spaced = flat if independent is None else independent
    # a posterior too short for RANK_DRAWS near-independent draws (a capped run) gets no rank
    ranked = truth is not None and len(spaced) >= RANK_DRAWS
    if ranked:
        pick = np.random.default_rng([seed, 1]).choice(len(spaced), RANK_DRAWS, replace=False)
    for k, name in enumerate(PARAMETER_NAMES):
        row[f"{name}_mean"] = float(means[k])
        row[f"{name}_sd"] = float(sds[k])
        for q, value in zip(QUANTILES, quantiles[:, k], strict=True):
            row[quantile_column(name, q)] = float(value)
        row[f"{name}_tau"] = 1.0 if tau is None else float(tau[k])
        row[f"{name}_ess"] = float(info["ess"] if ess is None else ess[k])
        if truth is not None:
            row[f"{name}_truth"] = float(truth[k])
            row[f"{name}_rank"] = int(np.sum(spaced[pick, k] < truth[k])) if ranked else np.nan
    row |= {key: info[key] for key in FIT_KEYS if key in info}  # the goodness of fit
    return row


def molecule_row(posterior, index: int, seed: int) -> dict:
    """The summary row of one molecule's ``Posterior`` (see the module docstring)."""
    chains = np.stack(
        [posterior.tree["posterior"][n].values for n in PARAMETER_NAMES], axis=-1
    )  # (walkers, draws, 6), draws thinned by tau/2
    flat = chains.reshape(-1, 6)
    info = dict(posterior.info, method=posterior.method)
    truth = posterior.truth
    truth = None if truth is None else truth[list(PARAMETER_NAMES)].to_numpy(float)
    if posterior.method != "mcmc":
        return draws_row(flat, index, seed, info, truth)
    tau = posterior.tau[list(PARAMETER_NAMES)].to_numpy(float)
    steps_after_burn = info.get("steps", 0) - info.get("burn", 0)
    # every second thinned draw is ~tau apart: near-independent
    return draws_row(
        flat,
        index,
        seed,
        info,
        truth,
        independent=chains[:, ::2].reshape(-1, 6),
        tau=tau,
        ess=chains.shape[0] * steps_after_burn / tau,
    )


def coverage(table: pd.DataFrame, prob: float) -> pd.DataFrame:
    """Fraction of molecules whose central ``prob`` interval holds the truth, per parameter,
    with its binomial standard error; needs the truth columns."""
    low, high = central_interval(prob)
    missing = [f"{n}_truth" for n in PARAMETER_NAMES if f"{n}_truth" not in table]
    if missing or len(table) == 0:
        raise BayespsfInputError(
            f"coverage needs a table with molecules and truth columns (missing: {missing})"
        )
    rows = []
    for name in PARAMETER_NAMES:
        truth = table[f"{name}_truth"].to_numpy()
        inside = (table[quantile_column(name, low)] <= truth) & (
            truth <= table[quantile_column(name, high)]
        )
        n = len(table)
        p = float(inside.mean())
        rows.append(
            {"parameter": name, "nominal": prob, "coverage": p, "se": np.sqrt(p * (1 - p) / n)}
        )
    return pd.DataFrame(rows)


__all__ = [
    "QUANTILES",
    "RANK_DRAWS",
    "central_interval",
    "coverage",
    "draws_row",
    "molecule_row",
    "quantile_column",
]
