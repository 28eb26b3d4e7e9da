"""The summary row of a molecule's posterior (``draws_row``; ``draws_rows`` for many at once),
and coverage over a table of rows.

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
BLOCK = 64  # most posteriors summarised in one array operation (~1 MB at 400 draws)


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
    return _rows(
        [flat],
        [index],
        [seed],
        [info],
        None if truth is None else [truth],
        [independent],
        [tau],
        [ess],
    )[0]


def draws_rows(draws, indices, seeds, infos, truths=None) -> list[dict]:
    """The summary rows of many posteriors' equally weighted draws, each equal to its
    ``draws_row``.

    The posteriors with the same number of draws are summarised together, up to ``BLOCK``
    at a time, in a few array operations; only the ranks' draws are chosen one posterior at
    a time (each from its own seed's generator).

    Parameters
    ----------
    draws : sequence of ndarray, each shape (k_i, 6)
        Each posterior's independent draws of ``x0 y0 s_x s_y N b`` (``k_i`` may differ).
    indices, seeds : sequence of int
        Each posterior's molecule and seed (its ranks' draws come from the seed).
    infos : sequence of dict
        Each posterior's sampler information, as ``draws_row`` reads it.
    truths : array_like, shape (n, 6), optional
        The true parameters: adds the truth and rank columns.

    Returns
    -------
    list of dict
        ``[draws_row(d, i, s, info, t) for ...]``: the same keys in the same order, and the
        same values bit for bit.

    Raises
    ------
    BayespsfInputError
        If ``indices``, ``seeds``, ``infos`` or ``truths`` do not hold one entry per
        posterior.
    """
    n = len(draws)
    if not len(indices) == len(seeds) == len(infos) == n:
        raise BayespsfInputError(
            f"draws_rows needs one index, seed and info per posterior; got {n} posteriors, "
            f"{len(indices)} indices, {len(seeds)} seeds and {len(infos)} infos"
        )
    if truths is not None and len(truths) != n:
        raise BayespsfInputError(f"truths must hold {n} rows, got {len(truths)}")
    return _rows(draws, indices, seeds, infos, truths, [None] * n, [None] * n, [None] * n)


def _quantiles_of_sorted(ordered: np.ndarray) -> np.ndarray:
    """``np.quantile(x, QUANTILES)`` of each row ``x`` of ``ordered`` (..., k), sorted along
    its last axis, as (..., 9): numpy's linear method (Hyndman & Fan type 7) in numpy's own
    arithmetic, so the values are numpy's bit for bit, without numpy's partition of each row
    for each quantile."""
    k = ordered.shape[-1]
    virtual = (k - 1) * np.asarray(QUANTILES)
    below = np.floor(virtual)
    above = below + 1
    top = virtual >= k - 1  # the largest value (numpy's index -1)
    below[top], above[top] = -1, -1
    below, above = below.astype(np.intp), above.astype(np.intp)
    gamma = virtual - below
    low, high = ordered[..., below], ordered[..., above]
    step = high - low
    values = low + step * gamma
    np.subtract(high, step * (1 - gamma), out=values, where=gamma >= 0.5)
    values[np.isnan(ordered[..., -1])] = np.nan  # NaN sorts last: a row with one has NaNs
    return values


def _statistics(group: np.ndarray) -> np.ndarray:
    """Mean, SD and ``QUANTILES`` (n, 6, 11) of each posterior in ``group`` (n, k, 6): the
    values ``x.mean(axis=0)``, ``x.std(axis=0, ddof=1)`` and ``np.quantile(x, QUANTILES,
    axis=0)`` give one posterior ``x`` at a time. Side by side in a (k, 6 n) array, the draws
    are summed in the order of those of one (k, 6) posterior."""
    n, k, p = group.shape
    columns = group.transpose(1, 0, 2).reshape(k, n * p)
    means = columns.mean(axis=0).reshape(n, p, 1)
    sds = columns.std(axis=0, ddof=1).reshape(n, p, 1)
    ordered = np.ascontiguousarray(group.transpose(0, 2, 1))  # (n, 6, k)
    ordered.sort(axis=-1)
    return np.concatenate([means, sds, _quantiles_of_sorted(ordered)], axis=-1)


def _row_head(index, seed, info: dict, count: int) -> dict:
    """The columns of a row before its parameters'."""
    converged = bool(info.get("converged", False))
    return {
        "molecule": int(index),
        "seed": int(seed),
        "converged": converged,
        "status": "converged" if converged else "not converged",
        "message": info.get("diagnosis") or ("" if converged else info.get("why", "")),
        "method": info.get("method", "mcmc"),
        "why": info.get("why", ""),
        "steps": int(info.get("steps", 0)),
        "draws": int(count),
        "acceptance": float(info.get("acceptance", np.nan)),
        "seconds": float(info.get("seconds", np.nan)),
    }


def _blocks(arrays, least: int = 0):
    """The positions of ``arrays`` of at least ``least`` rows, in blocks of at most ``BLOCK``
    arrays of the same number of rows: what one array operation takes."""
    groups: dict[int, list[int]] = {}
    for i, a in enumerate(arrays):
        if len(a) >= least:
            groups.setdefault(len(a), []).append(i)
    for members in groups.values():
        for start in range(0, len(members), BLOCK):  # arrays that stay in the cache
            yield members[start : start + BLOCK]


def _rank_block(spaced: np.ndarray, seeds, truths: np.ndarray) -> np.ndarray:
    """The truth's rank (n, 6) among ``RANK_DRAWS`` of each posterior's near-independent
    draws ``spaced`` (n, k, 6), drawn from its seed."""
    picks = np.stack(
        [
            np.random.default_rng([seed, 1]).choice(spaced.shape[1], RANK_DRAWS, replace=False)
            for seed in seeds
        ]
    )
    n, k, p = spaced.shape
    picked = spaced.reshape(n * k, p)[picks + k * np.arange(n)[:, None]]  # (n, RANK_DRAWS, 6)
    return np.sum(picked < truths[:, None], axis=1)


def _rows(draws, indices, seeds, infos, truths, independents, taus, esses) -> list[dict]:
    """``draws_rows`` with, per posterior, ``draws_row``'s ``independent``, ``tau`` and
    ``ess`` (each None or as ``draws_row`` takes it)."""
    n = len(draws)
    if n == 0:
        return []
    draws = [np.asarray(d) for d in draws]
    known = truths is not None
    # per posterior and parameter: mean, sd, the quantiles, tau, ess, and truth and rank,
    # as the Python floats (and ints) that float() and int() give one value at a time
    table = np.empty((n, 6, 15 if known else 13), dtype=object)
    for block in _blocks(draws):
        table[block, :, :11] = _statistics(np.stack([draws[i] for i in block]))
    table[:, :, 11] = np.array([(1.0,) * 6 if t is None else t for t in taus], dtype=float)
    table[:, :, 12] = np.array(
        [(f["ess"],) * 6 if e is None else e for f, e in zip(infos, esses, strict=True)],
        dtype=float,
    )
    if known:
        truths = np.asarray(truths, dtype=float).reshape(n, 6)
        table[:, :, 13] = truths
        table[:, :, 14] = np.nan  # a posterior too short to rank (a capped run) has no rank
        spaced = [
            d if s is None else np.asarray(s) for d, s in zip(draws, independents, strict=True)
        ]
        for block in _blocks(spaced, least=RANK_DRAWS):
            table[block, :, 14] = _rank_block(
                np.stack([spaced[i] for i in block]), [seeds[i] for i in block], truths[block]
            )
    keys = [
        key
        for name in PARAMETER_NAMES
        for key in (
            f"{name}_mean",
            f"{name}_sd",
            *(quantile_column(name, q) for q in QUANTILES),
            f"{name}_tau",
            f"{name}_ess",
            *((f"{name}_truth", f"{name}_rank") if known else ()),
        )
    ]
    rows = []
    for index, seed, info, d, values in zip(
        indices, seeds, infos, draws, table.reshape(n, -1).tolist(), strict=True
    ):
        row = _row_head(index, seed, info, d.shape[0])
        row.update(zip(keys, values, strict=True))
        row |= {key: info[key] for key in FIT_KEYS if key in info}  # the goodness of fit
        rows.append(row)
    return rows


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


def concat_tables(tables) -> pd.DataFrame:
    """Summary tables one after another (``pd.concat``, index renumbered), seeds kept whole.

    A table's ``seed`` column is uint64 where a seed is at or above 2**63 (half of
    ``molecule_seed``'s) and int64 where none is; ``pd.concat`` of the two gives float64, which
    rounds the seeds. Where the tables' seed columns differ, all become uint64, as the rows
    of all the tables in one ``pd.DataFrame`` give them.

    Parameters
    ----------
    tables : sequence of pandas.DataFrame
        Summary tables (at least one); those with a ``seed`` column have their seeds kept.

    Returns
    -------
    pandas.DataFrame
        The rows of every table in order; the columns in the order of their first
        appearance.
    """
    tables = list(tables)
    if len({table["seed"].dtype for table in tables if "seed" in table}) > 1:
        tables = [t.astype({"seed": np.uint64}) if "seed" in t else t for t in tables]
    out = pd.concat(tables, ignore_index=True, sort=False)
    # tables whose columns differ concatenate into a frame of many blocks, to which adding a
    # column is slow and warns (pandas' PerformanceWarning); a copy consolidates them
    return out.copy() if len(tables) > 1 else out


__all__ = [
    "QUANTILES",
    "RANK_DRAWS",
    "central_interval",
    "concat_tables",
    "coverage",
    "draws_row",
    "draws_rows",
    "molecule_row",
    "quantile_column",
]
