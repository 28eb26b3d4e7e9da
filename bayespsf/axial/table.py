"""z posteriors of a stack of ROIs, one summary row each, on local processes or a cluster: the
z columns of the localisation tables that ``bayespsf analyze`` writes."""

from __future__ import annotations

from concurrent.futures import Executor
from typing import TYPE_CHECKING

import pandas as pd

from bayespsf._runtime import progress_bar
from bayespsf.axial.match import check_calibration
from bayespsf.axial.posterior import z_posterior
from bayespsf.axial.push import check_z_range
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus, DefocusCalibration

if TYPE_CHECKING:
    from distributed import Client
    from numpy.typing import ArrayLike

    from bayespsf.model import Model

COLUMNS = ("z_mean", "z_sd", "z_q0025", "z_q0975", "z_khat", "z_converged")
CHUNK = 16  # ROIs per task: a task's start-up costs a few of them


def _z_chunk(task) -> list[dict]:
    first, counts, model, calibration, seeds, ess, z_range = task
    rows = []
    for k, roi in enumerate(counts):
        try:
            post = z_posterior(roi, model, calibration, z_range=z_range, seed=seeds[k], ess=ess)
        except BayespsfInputError as exc:  # a ROI without a fit anywhere in z_range
            rows.append({"index": first + k, "z_converged": False, "z_why": str(exc)})
            continue
        z = post.draws["z"]
        row = {
            "index": first + k,
            "z_mean": z.mean(),
            "z_sd": z.std(),
            "z_q0025": z.quantile(0.025),
            "z_q0975": z.quantile(0.975),
            "z_khat": post.info["khat"],
            "z_converged": post.info["converged"],
            "z_why": post.info.get("why", ""),
        }
        if "above_plane" in post.info:
            row["z_above_plane"] = post.info["above_plane"]
        rows.append(row)
    return rows


def z_posteriors(
    counts: ArrayLike,
    model: Model,
    calibration: DefocusCalibration | Defocus,
    *,
    seed: int = 0,
    ess: float = 400.0,
    z_range: tuple[float, float] = (-800.0, 800.0),
    workers: int | None = None,
    executor: Executor | Client | str | None = None,
    progress: bool | None = None,
) -> pd.DataFrame:
    """``z_posterior`` of every ROI of a stack, one summary row each.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU, as ``model`` reads them.
    model : Model
        Camera, geometry and the prior of x0, y0, N and b.
    calibration : DefocusCalibration or Defocus
        The widths' curves.
    seed : int, default 0
        ROI ``i`` is sampled with ``molecule_seed(seed, i)``: results do not depend on the
        number of workers.
    ess : float, default 400.0
        Effective sample size of each posterior.
    z_range : (float, float), default (-800.0, 800.0)
        Support ``(low, high)`` of z's uniform prior, nm.
    workers : int, optional
        Local processes when ``executor`` is None, as in ``sample_many``.
    executor : concurrent.futures.Executor, distributed.Client or str, optional
        Where tasks run, as in ``sample_many`` (a Dask ``Client`` or a scheduler address
        included).
    progress : bool, optional
        A progress bar of ROIs on stderr (default: when it is a terminal).

    Returns
    -------
    pandas.DataFrame
        One row per ROI, in order: ``COLUMNS`` (``z_mean``, ``z_sd``, ``z_q0025``,
        ``z_q0975`` in nm, ``z_khat``, ``z_converged``), ``z_why`` (why a posterior did not
        pass, empty where it did) and, where the curves are symmetric, ``z_above_plane``.
        A ROI with no converged fit anywhere in ``z_range`` gets ``z_converged`` False and
        the error in ``z_why``.

    Raises
    ------
    BayespsfInputError
        ``counts`` that are not a stack of the model's ROIs, a bad ``z_range``, a
        ``calibration`` of another type or made at another pixel size or camera kind than the
        model's (``check_calibration``), or bad ``workers`` or ``executor``.

    See Also
    --------
    z_posterior : one ROI, with its draws.
    bayespsf.sample_many : the widths' posteriors of a stack, run the same way.
    """
    from bayespsf.parallel import molecule_seed, run_tasks, task_runner

    counts = model.check_counts(counts)
    z_range = check_z_range(z_range)  # named here, not once per ROI in the workers
    if not isinstance(calibration, DefocusCalibration | Defocus):
        raise BayespsfInputError(
            "calibration must be a DefocusCalibration or a Defocus, got "
            f"{type(calibration).__name__}"
        )
    if isinstance(calibration, DefocusCalibration):
        check_calibration(calibration, model)  # before any ROI runs
    if counts.ndim != 3:
        raise BayespsfInputError(f"counts must be a stack (n, roi, roi), got {counts.shape}")
    seeds = [molecule_seed(seed, i) for i in range(len(counts))]
    tasks = [
        (
            first,
            counts[first : first + CHUNK],
            model,
            calibration,
            seeds[first : first + CHUNK],
            ess,
            z_range,
        )
        for first in range(0, len(counts), CHUNK)
    ]
    rows = []
    with (
        progress_bar(len(counts), progress, unit="ROI", desc="z posteriors") as bar,
        task_runner(executor, workers) as runner,
    ):
        for chunk in run_tasks(_z_chunk, tasks, runner):
            rows += chunk
            bar.update(len(chunk))
    table = pd.DataFrame(
        rows,
        columns=["index", *COLUMNS, "z_why"]
        + (["z_above_plane"] if any("z_above_plane" in r for r in rows) else []),
    )
    return table.sort_values("index").drop(columns="index").reset_index(drop=True)


__all__ = ["COLUMNS", "z_posteriors"]
