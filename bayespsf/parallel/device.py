"""``sample_many``'s batched pass on JAX's device (``backend="jax"``).

The stack, screened by ``sample_many``, is fitted (``fit_screened(backend="jax")``) and its
chain-free posteriors made (``bayespsf.inference.jax_sampling``) in this process, on whatever
device JAX finds; the summary rows of the posteriors made are assembled column by column (a
dataset of 10^6 ROIs is not a loop of rows); the ROIs whose diagnostics need the chain are
handed back, with why, for ``sample_many`` to run on the CPU as with the NumPy backend. With a
store, the posteriors are written to it as the NumPy backend writes them.
"""

from __future__ import annotations

import time
from dataclasses import asdict

import numpy as np
import pandas as pd

from bayespsf.inference.summary import QUANTILES, RANK_DRAWS, concat_tables, quantile_column
from bayespsf.parallel.store import Store
from bayespsf.psf import PARAMETER_NAMES

CHUNK = 2**16  # ROIs per pass: the host holds this many ROIs' results and draws at a time


def device_posteriors(indices, stack, model, seeds, truths, settings, scene, store, check):
    """Posteriors of ``stack`` (the ROIs ``indices`` of a run) on JAX's device.

    Parameters
    ----------
    indices : ndarray of int
        The ROIs' molecule indices.
    stack : ndarray, shape (n, roi, roi)
        Their validated counts.
    model : Model
        The inference model.
    seeds : sequence of int
        Each ROI's seed (``molecule_seeds``).
    truths : ndarray, shape (n, 6), optional
        True parameters (SBC ranks).
    settings : Settings
        The sampler's settings (``method``: ``auto``, ``laplace`` or ``importance``).
    scene : Scene, optional
        Kept in each result file.
    store : path-like, optional
        The run's store: each posterior made is written to its file.
    check : str or bool
        The discrepancy of the parametric-bootstrap model check, or False.

    Returns
    -------
    table : pandas.DataFrame
        The summary rows of the posteriors made (``sample_many``'s columns).
    verdicts : dict
        For each ROI that needs the chain, its molecule index -> the method asked for and why.
    """
    tables, verdicts = [], {}
    seeds = np.asarray(seeds, dtype=np.uint64)  # whole: seeds span [0, 2**64)
    for first in range(0, len(indices), CHUNK):
        part = slice(first, first + CHUNK)
        table, chain = _chunk(
            np.asarray(indices)[part],
            stack[part],
            model,
            seeds[part],
            None if truths is None else truths[part],
            settings,
            scene,
            store,
            check,
        )
        tables.append(table)
        verdicts |= chain
    return concat_tables(tables) if tables else pd.DataFrame(), verdicts


def _chunk(indices, stack, model, seeds, truths, settings, scene, store, check):
    from bayespsf.inference import fit_screened
    from bayespsf.inference.gof import pearson_columns
    from bayespsf.inference.jax_sampling import pearson, posteriors

    started = time.perf_counter()
    fits = fit_screened(stack, model, backend="jax")  # screened by ``sample_many``
    out = posteriors(stack, model, fits, seeds, settings, truths, keep_draws=store is not None)
    seconds = (time.perf_counter() - started) / len(indices)
    made = out["made"]
    checks = {}
    if check:
        from bayespsf.inference.gof import check_rows

        checks = check_rows(stack, model, seeds, check, fits)
    verdicts = {
        int(indices[i]): {"requested": settings.method, "why": str(out["why"][i])}
        | ({"check": checks[i]} if check else {})
        for i in np.flatnonzero(~made)
    }
    rows = np.flatnonzero(made)
    every = rows.size == len(stack)  # then no copy of the stack
    theta = fits[list(PARAMETER_NAMES)].to_numpy(float)
    chi2 = pearson(model, stack if every else stack[rows], theta if every else theta[rows])
    gof = pearson_columns(model, chi2, "mle")
    table = _table(indices[rows], seeds[rows], out, rows, seconds, truths, gof)
    if check:
        for key in ("gof_p", "gof_discrepancy", "gof_replicates"):
            table[key] = [checks[i][key] for i in rows]
    if store is not None:
        _write(store, table, out, rows, indices, stack, model, truths, scene, settings)
    return table, verdicts


def _table(molecules, seeds, out, rows, seconds, truths, gof) -> pd.DataFrame:
    """The summary rows (``bayespsf.inference.summary.draws_row``'s columns, then ``gof``'s),
    as columns."""
    n = len(rows)
    mean, sd, quantiles = out["mean"][rows], out["sd"][rows], out["quantiles"][rows]
    ess, draws = out["ess"][rows], out["draws"][rows]
    columns = {
        "molecule": molecules.astype(int),
        "seed": seeds.tolist(),  # Python ints: 64-bit seeds, as the NumPy rows
        "converged": out["converged"][rows],
        "status": np.where(out["converged"][rows], "converged", "not converged"),
        "message": np.where(out["converged"][rows], "", out["why"][rows]).astype(object),
        "method": out["method"][rows],
        "why": out["why"][rows],
        "steps": np.zeros(n, int),
        "draws": draws,
        "acceptance": np.full(n, np.nan),
        "seconds": np.full(n, seconds),
    }
    if truths is not None:
        truth, rank = np.asarray(truths, float)[rows], out["rank"][rows]
    for k, name in enumerate(PARAMETER_NAMES):
        columns[f"{name}_mean"] = mean[:, k]
        columns[f"{name}_sd"] = sd[:, k]
        for j, q in enumerate(QUANTILES):
            columns[quantile_column(name, q)] = quantiles[:, j, k]
        columns[f"{name}_tau"] = np.ones(n)
        columns[f"{name}_ess"] = ess
        if truths is not None:
            columns[f"{name}_truth"] = truth[:, k]
            ranked = np.where((rank[:, k] >= 0) & (draws >= RANK_DRAWS), rank[:, k], np.nan)
            # whole numbers where every ROI is ranked, as the NumPy backend's rows give them
            columns[f"{name}_rank"] = ranked if np.isnan(ranked).any() else ranked.astype(int)
    return pd.DataFrame(columns | gof)


def _write(store, table, out, rows, indices, stack, model, truths, scene, settings) -> None:
    """The posteriors made, to the store (as the NumPy backend writes them)."""
    info_keys = ("method", "why", "converged", "ess", "khat", "weight_sd", "draws_scored")
    outcomes, plain = [], []
    for position, i in enumerate(rows):
        row = table.iloc[position].to_dict()
        info = {**asdict(settings), "requested": settings.method, "mle_converged": True}
        info |= {"stuck_walkers": 0} | {key: _plain(out[key][i]) for key in info_keys}
        info |= {key: _plain(row[key]) for key in ("chi2", "chi2_dof", "chi2_p", "chi2_at")}
        info |= {"backend": "jax", "seed": int(row["seed"]), "seconds": float(row["seconds"])}
        outcomes.append({"draws": out["samples"][i], "info": info})
        plain.append({k: _plain(v) for k, v in row.items()})
    Store(store).write_outcomes(
        [int(indices[i]) for i in rows],
        outcomes,
        stack[rows],
        plain,
        model,
        scene,
        None if truths is None else np.asarray(truths, float)[rows],
    )


def _plain(value):
    """A NumPy scalar as the Python number JSON writes."""
    if isinstance(value, np.generic):
        return value.item()
    return value


__all__ = ["CHUNK", "device_posteriors"]
