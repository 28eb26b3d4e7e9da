"""z posteriors of a stack of ROIs, one summary row each, on local processes or a cluster
(issue 16, item 6: z in the localisation tables that ``bayespsf analyze`` writes)."""

from __future__ import annotations

import pandas as pd

from bayespsf._progress import progress_bar
from bayespsf.axial.calibrate import Calibration
from bayespsf.axial.defocus import Defocus
from bayespsf.axial.posterior import z_posterior
from bayespsf.axial.push import check_z_range
from bayespsf.errors import BayespsfInputError

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
        row = {"index": first + k, "z_mean": z.mean(), "z_sd": z.std(),
               "z_q0025": z.quantile(0.025), "z_q0975": z.quantile(0.975),
               "z_khat": post.info["khat"], "z_converged": post.info["converged"],
               "z_why": post.info.get("why", "")}  # fmt: skip
        if "above_plane" in post.info:
            row["z_above_plane"] = post.info["above_plane"]
        rows.append(row)
    return rows


def z_posteriors(counts, model, calibration, *, seed: int = 0, ess: float = 400.0,
                 z_range=(-800.0, 800.0), workers: int | None = None, executor=None,
                 progress: bool | None = None) -> pd.DataFrame:  # fmt: skip
    """``z_posterior`` of every ROI of ``counts`` (n, roi, roi): one row per ROI with
    ``COLUMNS`` (nm; ``z_above_plane`` where the curves are symmetric) and ``z_why`` where
    the posterior did not pass. ROI ``i`` is sampled with ``molecule_seed(seed, i)``; tasks
    run on ``workers`` local processes or ``executor`` as in ``sample_many``."""
    from bayespsf.batch import _results, molecule_seed, task_runner

    counts = model.check_counts(counts)
    z_range = check_z_range(z_range)  # named here, not once per ROI in the workers
    if not isinstance(calibration, Calibration | Defocus):
        raise BayespsfInputError(
            f"calibration must be a Calibration or a Defocus, got {type(calibration).__name__}"
        )
    if counts.ndim != 3:
        raise BayespsfInputError(f"counts must be a stack (n, roi, roi), got {counts.shape}")
    seeds = [molecule_seed(seed, i) for i in range(len(counts))]
    tasks = [(first, counts[first : first + CHUNK], model, calibration,
              seeds[first : first + CHUNK], ess, z_range)
             for first in range(0, len(counts), CHUNK)]  # fmt: skip
    rows = []
    with (progress_bar(len(counts), progress, unit="ROI", desc="z posteriors") as bar,
          task_runner(executor, workers) as runner):  # fmt: skip
        for chunk in _results(_z_chunk, tasks, runner):
            rows += chunk
            bar.update(len(chunk))
    table = pd.DataFrame(rows, columns=["index", *COLUMNS, "z_why"] + (
        ["z_above_plane"] if any("z_above_plane" in r for r in rows) else []
    ))  # fmt: skip
    return table.sort_values("index").drop(columns="index").reset_index(drop=True)


__all__ = ["COLUMNS", "z_posteriors"]
