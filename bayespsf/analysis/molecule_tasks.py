"""``analyze``'s work beside the posteriors, as tasks on the run's workers.

The posteriors (``sample_many``) and the joint posteriors are the run's bulk, spread over its
workers. What ``analyze`` computes besides them would otherwise run in the calling process
while the workers wait, and bound what more workers can gain (Amdahl):

* per chunk of whole molecules (``molecule_chunks``), the MLE with its Cramér-Rao bound, the
  paper's least squares and the widths by window (``estimates_task``), sent before the
  posteriors so that they run beside them (``send_estimates``);
* the report's figures (``send_figures``), drawn while the joint posteriors run, and sent
  back as PNG bytes that this process writes (a Dask worker need not see the output folder).

In one process the same chunks run in turn, so the tables do not depend on the workers, to
the last bit.
"""

from __future__ import annotations

import concurrent.futures as cf
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf._runtime import one_blas_thread
from bayespsf.analysis.misfit import width_by_window
from bayespsf.inference import fit_lsq, fit_mle
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

#: ROIs per chunk of the estimates: whole molecules, closed once a chunk holds this many.
CHUNK = 512


def estimates(counts: np.ndarray, model: Model, lsq: bool = True) -> pd.DataFrame:
    """The MLE and, with ``lsq``, the paper's least squares of every ROI, one row each.

    Parameters
    ----------
    counts : numpy.ndarray, shape (n, roi, roi)
        ROIs in ADU.
    model : Model
        Their model.
    lsq : bool, default True
        Whether to fit the least squares too.

    Returns
    -------
    pandas.DataFrame
        Per parameter ``<p>`` the MLE ``<p>_mle`` with its Cramér-Rao bound ``crlb_<p>``
        and, with ``lsq``, the least squares ``<p>_lsq`` (NaN where it did not converge);
        ``mle_converged``, and ``fit_mle``'s ``status`` and ``message`` as ``mle_status``
        and ``mle_message``.
    """
    mle = fit_mle(counts, model, laplace=False)
    squares = fit_lsq(counts, model) if lsq else None
    out = pd.DataFrame(index=mle.index)
    for p in PARAMETER_NAMES:
        out[f"{p}_mle"] = mle[p].to_numpy()
        out[f"crlb_{p}"] = mle[f"crlb_{p}"].to_numpy()
        if squares is not None:
            out[f"{p}_lsq"] = squares[p].where(squares["converged"]).to_numpy()
    out["mle_converged"] = mle["converged"].to_numpy(bool)
    out["mle_status"] = mle["status"].to_numpy(object)
    out["mle_message"] = mle["message"].to_numpy(object)
    return out


def molecule_chunks(molecules: np.ndarray, size: int = CHUNK) -> list[np.ndarray]:
    """ROIs in chunks of whole molecules: the molecules in increasing order, each with all its
    ROIs (in their order), a chunk closing at the first molecule at or past ``size`` ROIs.

    Parameters
    ----------
    molecules : numpy.ndarray, shape (n,)
        The molecule of each ROI.
    size : int, default CHUNK
        ROIs after which a chunk closes.

    Returns
    -------
    list of numpy.ndarray
        Each chunk's ROI indices; together every ROI once (no chunk for no ROI).
    """
    molecules = np.asarray(molecules)
    order = np.argsort(molecules, kind="stable")  # each molecule's ROIs together, in order
    ranked = molecules[order]
    later = np.flatnonzero(ranked[1:] != ranked[:-1]) + 1  # each later molecule's first
    chunks, first = [], 0
    for start in [*later.tolist(), len(order)]:
        if start > first and (start - first >= size or start == len(order)):
            chunks.append(order[first:start])
            first = start
    return chunks


@one_blas_thread
def estimates_task(task) -> tuple[pd.DataFrame, pd.DataFrame]:
    """One chunk's ``estimates`` and ``width_by_window``: the task of a worker (picklable in
    and out). ``task``: ``(counts, model, molecules)``."""
    counts, model, molecules = task
    return estimates(counts, model), width_by_window(counts, model, molecules)


def send_estimates(
    counts: np.ndarray, model: Model, molecules: np.ndarray, runner: cf.Executor | None
) -> Callable[[], tuple[pd.DataFrame, pd.DataFrame]]:
    """Send every chunk's ``estimates_task`` to ``runner`` now; what gathers their results.

    Parameters
    ----------
    counts, model
        As ``estimates``.
    molecules : numpy.ndarray, shape (n,)
        The molecule of each ROI.
    runner : concurrent.futures.Executor or None
        The run's workers (``bayespsf.parallel.task_runner``); None: the chunks run in this
        process when gathered.

    Returns
    -------
    callable
        Returns ``(estimates, windows)``: ``estimates``' rows in the order of ``counts``,
        and ``width_by_window``'s rows by window, then molecule.
    """
    chunks = molecule_chunks(molecules) or [np.arange(0)]  # no ROI: the empty tables
    tasks = [(counts[c], model, molecules[c]) for c in chunks]
    if runner is None:
        return lambda: _gather(map(estimates_task, tasks), chunks)
    futures = [runner.submit(estimates_task, task) for task in tasks]
    return lambda: _gather((future.result() for future in futures), chunks)


def _gather(parts, chunks) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The chunks' tables joined: the fits back in the ROIs' order, the windows by window,
    then molecule (as ``width_by_window`` orders them)."""
    fits, windows = zip(*parts, strict=True)
    fits = pd.concat(fits).set_axis(np.concatenate(chunks)).sort_index()
    windows = pd.concat(windows).sort_values(["window", "molecule"], kind="stable")
    return fits.reset_index(drop=True), windows.reset_index(drop=True)


def figures_task(task) -> dict[str, bytes]:
    """The report's figures as PNG bytes by file name: the task of a worker. ``task``:
    ``report_figures``' arguments before ``out``."""
    from bayespsf.analysis.figures import report_figures  # matplotlib only when drawn

    with tempfile.TemporaryDirectory() as folder:
        made = report_figures(*task, Path(folder))
        return {name: path.read_bytes() for name, path in made.items()}


def send_figures(runner: cf.Executor | None, *task) -> Callable[[Path], dict[str, Path]]:
    """Send the report's figures to ``runner`` now; what writes them into a folder.

    Parameters
    ----------
    runner : concurrent.futures.Executor or None
        The run's workers; None: drawn in this process, into the folder, when written.
    *task
        ``bayespsf.analysis.figures.report_figures``' arguments before ``out``.

    Returns
    -------
    callable
        Takes the folder; returns the files' paths by name.
    """
    if runner is None:

        def draw(out: Path) -> dict[str, Path]:
            from bayespsf.analysis.figures import report_figures

            return report_figures(*task, out)

        return draw
    future = runner.submit(figures_task, task)

    def write(out: Path) -> dict[str, Path]:
        paths = {}
        for name, data in future.result().items():
            paths[name] = out / name
            paths[name].write_bytes(data)
        return paths

    return write


__all__ = [
    "CHUNK",
    "estimates",
    "estimates_task",
    "figures_task",
    "molecule_chunks",
    "send_estimates",
    "send_figures",
]
