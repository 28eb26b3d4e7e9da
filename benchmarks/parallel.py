"""Parallel throughput: ``sample_many`` on one process, two local worker processes and a Dask
cluster, and a dataset of 10^5 ROIs on two workers (targets: two workers >= 1.8x one; 10^5
emccd-typical posteriors in <= 10 minutes on 2 cores).

Run it on an otherwise idle machine: the speed-up of two workers means nothing when other jobs
share the cores.

    python benchmarks/parallel.py            # full run, rewrites its section of README.md
    python benchmarks/parallel.py --quick    # a small run that prints only (the tests)
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import publish_table, quick_run  # noqa: E402

from bayespsf import load_scene, simulate  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.parallel import sample_many  # noqa: E402


def _timed(function):
    started = time.perf_counter()
    out = function()
    return out, time.perf_counter() - started


def parallel(n: int, dataset: int) -> pd.DataFrame:
    """``sample_many(method="auto")`` on ``n`` emccd-typical ROIs (N = 1000) in this process,
    on two local worker processes and on a Dask ``LocalCluster`` of two one-thread workers;
    then a ``dataset`` of ROIs on two local workers (target: 10^5 in <= 10 minutes)."""
    from distributed import Client, LocalCluster

    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, max(n, dataset), seed=3)
    sample_many(counts[:4], model, workers=1)  # warm-up
    rows = []

    def row(how, result, seconds, reference=None):
        count = len(result)
        same = (
            np.nan
            if reference is None
            else bool(
                np.array_equal(result["s_x_mean"].to_numpy(), reference["s_x_mean"].to_numpy())
            )
        )
        rows.append(
            {
                "how": how,
                "ROIs": count,
                "seconds": seconds,
                "ROIs/s": count / seconds,
                "same posteriors as one process": same,
            }
        )

    one, seconds = _timed(lambda: sample_many(counts[:n], model, workers=1))
    row("one process", one, seconds)
    two, seconds = _timed(lambda: sample_many(counts[:n], model, workers=2))
    row("two local worker processes", two, seconds, one)
    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, dashboard_address=None, processes=True
        ) as cluster,
        Client(cluster) as client,
    ):
        sample_many(counts[:4], model, executor=client)  # the workers' imports and tables
        dask, seconds = _timed(lambda: sample_many(counts[:n], model, executor=client))
    row("Dask LocalCluster, 2 workers x 1 thread", dask, seconds, one)
    data, seconds = _timed(lambda: sample_many(counts[:dataset], model, workers=2))
    row("two local worker processes (dataset)", data, seconds)
    table = pd.DataFrame(rows)
    table["speed-up vs one process"] = table["ROIs/s"] / table["ROIs/s"].iloc[0]
    return table


def main(argv=None):
    quick = quick_run(__doc__, argv)
    table = parallel(*((16, 32) if quick else (4000, 100_000)))
    intro = '`sample_many` (default `method="auto"`, emccd-typical, N = 1000):'
    publish_table("parallel", intro, table, quick)
    return table


if __name__ == "__main__":
    main()
