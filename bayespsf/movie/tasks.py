"""The movie path's heavy steps as tasks: the maximum-likelihood fits of stacks of ROIs (the
spot's SD, the selection's widths) and each molecule's bleaching steps, run in this process or
on a runner's workers (``bayespsf.parallel.task_runner``: local processes, a Dask cluster).

This process reads the movie and sends the work: each stack in pieces of at most ``PIECE``
ROIs, each trace whole, a few tasks ahead per worker (``bayespsf.parallel.run_in_order``), the
results back in order. The pieces are the same whatever runs them, so the results do not
depend on the workers, to the last bit.
"""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Iterable, Iterator
from itertools import tee

import numpy as np
import pandas as pd

from bayespsf._runtime import one_blas_thread
from bayespsf.inference import fit_mle
from bayespsf.model import Model
from bayespsf.movie.steps import BleachSteps, bleach_steps
from bayespsf.parallel import run_in_order, task_runner

#: ROIs per fitted piece of a stack: one task.
PIECE = 512


def movie_runner(executor):
    """``task_runner`` for a movie function's ``executor``: that executor, client or address
    (shut down on leaving only where made here), or None (the default) for this process.

    Parameters
    ----------
    executor : concurrent.futures.Executor, distributed.Client, str or None
        As ``find_molecules``' ``executor``.

    Returns
    -------
    contextlib.AbstractContextManager
        Yields the runner to pass to ``fit_stacks`` and ``trace_steps``.
    """
    return task_runner(executor, 1 if executor is None else None)


@one_blas_thread
def fit_task(task) -> pd.DataFrame:
    """``fit_mle`` (no Laplace, no Cramér-Rao bound) of one piece: the task of a worker.
    ``task``: ``(counts, model)``."""
    counts, model = task
    return fit_mle(counts, model, laplace=False, crlb=False)


def fit_stacks[K](
    stacks: Iterable[tuple[K, np.ndarray]], model: Model, runner: cf.Executor | None
) -> Iterator[tuple[K, pd.DataFrame]]:
    """Each stack of ROIs with its maximum-likelihood fits, in order.

    Parameters
    ----------
    stacks : iterable of (key, numpy.ndarray)
        A key (what the caller needs back with the fits) and ROIs in ADU, shape (n, roi,
        roi), read lazily: memory holds the stacks of the pieces sent ahead.
    model : Model
        The ROIs' model.
    runner : concurrent.futures.Executor or None
        Where the pieces are fitted; None: here.

    Returns
    -------
    iterator of (key, pandas.DataFrame)
        Each key with ``fit_mle``'s table of its ROIs (``laplace=False``, ``crlb=False``),
        one row per ROI; a stack without ROIs is left out.
    """

    def pieces():
        for key, counts in stacks:
            for start in range(0, len(counts), PIECE):
                yield key, counts[start : start + PIECE], start + PIECE >= len(counts)

    mine, sent = tee(pieces())
    fits = run_in_order(fit_task, ((counts, model) for _, counts, _ in sent), runner)
    parts = []
    for (key, _, last), part in zip(mine, fits, strict=True):
        parts.append(part)
        if last:
            yield key, pd.concat(parts, ignore_index=True)
            parts = []


def steps_task(task) -> BleachSteps:
    """``bleach_steps`` of one trace: the task of a worker. ``task``: ``(trace, frames,
    penalty)``."""
    trace, frames, penalty = task
    return bleach_steps(trace, frames=frames, penalty=penalty)


def trace_steps(
    traces: Iterable[tuple[np.ndarray, np.ndarray]], penalty: float, runner: cf.Executor | None
) -> Iterator[BleachSteps]:
    """Each trace's bleaching steps, in order.

    Parameters
    ----------
    traces : iterable of (numpy.ndarray, numpy.ndarray)
        Each molecule's trace and the frame of each of its values.
    penalty : float
        ``bleach_steps``'s ``c``.
    runner : concurrent.futures.Executor or None
        Where the steps are found; None: here.

    Returns
    -------
    iterator of BleachSteps
    """
    tasks = ((trace, frames, penalty) for trace, frames in traces)
    return run_in_order(steps_task, tasks, runner)


__all__ = ["PIECE", "fit_stacks", "fit_task", "movie_runner", "steps_task", "trace_steps"]
