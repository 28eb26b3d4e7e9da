"""Many ROIs: reproducible (one seed per molecule, whatever the workers), resumable (a
``Store`` written molecule by molecule), on local processes or a Dask cluster."""

from bayespsf.parallel.batch import sample_many
from bayespsf.parallel.executors import (
    dask_settings,
    local_executor,
    parallelism,
    run_in_order,
    run_tasks,
    task_runner,
    worker_start,
)
from bayespsf.parallel.joint import joint_posteriors
from bayespsf.parallel.seeds import molecule_seed, molecule_seeds
from bayespsf.parallel.store import Store
from bayespsf.parallel.tables import write_csv

__all__ = [
    "Store",
    "dask_settings",
    "joint_posteriors",
    "local_executor",
    "molecule_seed",
    "molecule_seeds",
    "parallelism",
    "run_in_order",
    "run_tasks",
    "sample_many",
    "task_runner",
    "worker_start",
    "write_csv",
]
