"""Joint posteriors of many molecules, each over its frames (``bayespsf.inference.joint``), on
local processes or a Dask cluster, one seed per molecule as in ``sample_many``."""

from __future__ import annotations

from concurrent.futures import Executor
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from bayespsf._runtime import one_blas_thread, progress_bar
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import Settings, joint_posterior
from bayespsf.inference.joint import SHARED
from bayespsf.inference.settings import check_settings
from bayespsf.model import Model
from bayespsf.parallel.executors import run_tasks, task_runner
from bayespsf.parallel.seeds import molecule_seed
from bayespsf.psf import PARAMETER_NAMES

if TYPE_CHECKING:
    from distributed import Client


@one_blas_thread
def _molecule_task(task) -> dict:
    """Worker side: one molecule's joint posterior as its table row (picklable in and out)."""
    molecule, counts, model, starts, seed, ess, shared = task
    try:
        post = joint_posterior(counts, model, starts, seed=seed, ess=ess, shared=shared)
    except BayespsfInputError as error:  # one molecule's frames: its row says why
        return {
            "molecule": molecule,
            "joint_frames": len(counts),
            "joint_method": "failed",
            "joint_converged": False,
            "joint_why": str(error),
        }
    return {"molecule": molecule, **post.row()}


def joint_posteriors(
    counts: ArrayLike,
    frames: pd.DataFrame,
    model: Model,
    *,
    seed: int = 0,
    ess: float = Settings.ess,
    shared: str = "b per frame",
    workers: int | None = None,
    executor: Executor | Client | str | None = None,
    progress: bool | None = None,
) -> pd.DataFrame:
    """The joint posterior of every molecule in ``frames``, one row per molecule.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        Every molecule's frames, in ADU.
    frames : pandas.DataFrame
        One row per ROI of ``counts``: ``molecule``, the per-frame maximum-likelihood fit
        ``<p>_mle`` (nm, photons, photons per pixel) and ``mle_converged`` (the joint fit
        starts from it; frames whose fit did not converge are left out of the joint model),
        and optionally the per-frame posterior SDs ``<p>_sd``.
    model : Model
        The model of one frame.
    seed : int
        Molecule ``m`` is sampled with the seed ``molecule_seed(seed, m)``.
    ess : float
        Effective sample size of each molecule's importance sampling.
    shared : {"b per frame", "one b"}
        Whether the background is each frame's own or shared (``joint_posterior``).
    workers : int, optional
        Local processes when ``executor`` is None, as in ``sample_many``.
    executor : concurrent.futures.Executor, distributed.Client, str, optional
        What runs the molecules, as in ``sample_many``.
    progress : bool, optional
        A progress bar on stderr (default: when stderr is a terminal).

    Returns
    -------
    pandas.DataFrame
        One row per molecule, sorted by ``molecule``: ``molecule``; ``<p>_frame_sd`` (the
        mean of ``<p>_sd`` over the frames used, beside the joint SD) where ``frames`` has
        ``<p>_sd``; per shared parameter ``<p>_joint_mean``, ``_sd``, ``_q2.5``, ``_q16``,
        ``_q84``, ``_q97.5``, ``_mle`` (``JointPosterior.row``); and ``joint_frames``,
        ``joint_shared``, ``joint_mle_converged``, ``joint_method``, ``joint_converged``,
        ``joint_why``, ``joint_khat``, ``joint_ess``, ``joint_draws_scored``,
        ``joint_seconds``. A molecule with fewer than two usable frames gets
        ``joint_method`` ``"none"``, one whose frames its model refuses ``"failed"``, with
        the reason in ``joint_why``.

    Raises
    ------
    BayespsfInputError
        If ``seed``, ``ess`` or ``shared`` is invalid, ``frames`` has not one row per ROI or
        lacks a column, or the executor cannot be made.

    See Also
    --------
    bayespsf.inference.joint_posterior : one molecule's joint posterior.
    sample_many : per-frame posteriors of a stack.
    """
    ess = check_settings(seed=seed, ess=ess).ess  # named here, not in a worker
    counts = np.asarray(counts, dtype=np.float64)
    if len(frames) != len(counts):
        raise BayespsfInputError(
            f"frames has {len(frames)} rows for {len(counts)} ROIs; give one row per ROI"
        )
    names = [f"{p}_mle" for p in PARAMETER_NAMES]
    missing = [c for c in ("molecule", "mle_converged", *names) if c not in frames]
    if missing:
        raise BayespsfInputError(f"frames: no column {', '.join(missing)}")
    if shared not in SHARED:
        raise BayespsfInputError(f"shared must be one of {sorted(SHARED)}, got {shared!r}")
    usable = frames["mle_converged"].to_numpy(bool) & np.isfinite(frames[names]).all(axis=1)
    tasks, rows = [], []
    for molecule, index in frames.groupby("molecule").indices.items():
        use = index[usable.to_numpy()[index]]
        extra = {
            f"{p}_frame_sd": float(frames[f"{p}_sd"].iloc[use].mean())
            for p in PARAMETER_NAMES
            if f"{p}_sd" in frames
        }
        if len(use) < 2:
            rows.append(
                {
                    "molecule": molecule,
                    **extra,
                    "joint_frames": len(use),
                    "joint_method": "none",
                    "joint_converged": False,
                    "joint_why": "fewer than two frames with a converged fit",
                }
            )
            continue
        rows.append({"molecule": molecule, **extra})
        starts = frames[names].to_numpy(float)[use]
        tasks.append(
            (molecule, counts[use], model, starts, molecule_seed(seed, molecule), ess, shared)
        )
    made = {}
    with (
        progress_bar(len(tasks), progress, unit="molecule", desc="joint posteriors") as bar,
        task_runner(executor, workers) as runner,
    ):
        for row in run_tasks(_molecule_task, tasks, runner):
            made[row["molecule"]] = row
            bar.update(1)
    table = pd.DataFrame([{**row, **made.get(row["molecule"], {})} for row in rows])
    return table.sort_values("molecule", ignore_index=True)


__all__ = ["joint_posteriors"]
