"""The first use of an EMCCD readout/gain ratio on a machine: building its tables, in time and
peak resident memory, against a process that reads them from the on-disk cache.

The ``table`` tier's likelihood table (``bayespsf/cameras/_emccd_table.py``) and the exact
Fisher-information spline (``_emccd_fisher.py``) of a new readout/gain ratio are built by
quadrature on the machine's first use of it, then kept in the on-disk cache
(``_table_cache``). Every row is a fresh process (``python -c``) with ``BAYESPSF_CACHE`` set to
a temporary folder: empty for a first use, filled by that first use for a warm run. The
process imports bayespsf, reads one ``emccd-typical`` ROI (readout/gain 0.25) and its parameters,
simulated by this script (so that, as in a user's first analysis of data, nothing has been
compiled before the timed calls: the first of them loads numba's compiled loops), builds its
model, evaluates ``Model.log_likelihood`` (the likelihood table) and then
``camera.fisher_information`` of the ROI's expected photons (the Fisher spline), each step
timed; its peak resident memory is read after the imports and at the end: ``VmHWM`` of
``/proc/self/status`` where there is one, else ``resource.getrusage(RUSAGE_SELF).ru_maxrss``
(which on Linux starts from the peak of the process that started this one, kept across
``exec``). A full run repeats
each kind of process 3 times (median times, largest peak) and adds first uses whose quadrature
evaluates every grid point in one pass (``_emccd_law._BLOCK`` above the grid's size) instead
of in blocks.

    python benchmarks/first_use.py            # full run, rewrites its section of README.md
    python benchmarks/first_use.py --quick    # one first use, one warm run, prints only
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from _report import publish_table, quick_run

CHILD = """
import json, resource, sys, time

started = time.perf_counter()
import numpy as np
import bayespsf
from bayespsf.cameras import _emccd_law


def peak_mib():
    # VmHWM: this process's own peak. ru_maxrss starts from the peak of the process that
    # started this one (Linux keeps it across exec): it is this process's only where that
    # one peaked lower
    try:
        with open("/proc/self/status") as status:
            return next(int(l.split()[1]) for l in status if l.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / 2**20 if sys.platform == "darwin" else peak / 1024


imported = time.perf_counter()
after_imports = peak_mib()
if len(sys.argv) > 2:
    _emccd_law._BLOCK = int(sys.argv[2])
scene = bayespsf.load_scene("emccd-typical")
with np.load(sys.argv[1]) as roi:
    counts, params = roi["counts"], roi["params"]
began = time.perf_counter()
model = bayespsf.Model.from_scene(scene)
model.log_likelihood(counts, params)
likelihood = time.perf_counter()
model.camera.fisher_information(model.expected(params))
fisher = time.perf_counter()
print(json.dumps({
    "imports (s)": imported - started,
    "likelihood table (s)": likelihood - began,
    "Fisher spline (s)": fisher - likelihood,
    "peak after imports (MiB)": after_imports,
    "peak (MiB)": peak_mib(),
}))
"""
ONE_PASS = 10**9  # a block larger than any grid: the quadrature over every point at once


def _megabytes(folder: Path) -> float:
    return sum(f.stat().st_size for f in folder.glob("*.npy")) / 1e6


def write_roi(folder: Path) -> Path:
    """One simulated ``emccd-typical`` ROI and its true parameters, as ``folder/roi.npz``."""
    import bayespsf

    counts, truth = bayespsf.simulate(bayespsf.load_scene("emccd-typical"), 1, seed=1)
    np.savez(folder / "roi.npz", counts=counts, params=truth.to_numpy())
    return folder / "roi.npz"


def process(cache: Path, roi: Path, block: int | None = None) -> dict:
    """One fresh process's times and peak memory, with ``BAYESPSF_CACHE=cache`` and the ROI
    file ``roi`` (``write_roi``), and the size of the cache's tables before and after it
    (MB)."""
    before = _megabytes(cache)
    env = {**os.environ, "BAYESPSF_CACHE": str(cache)}
    command = [sys.executable, "-c", CHILD, str(roi), *([] if block is None else [str(block)])]
    out = subprocess.run(command, env=env, capture_output=True, text=True, check=True).stdout
    return {
        **json.loads(out.splitlines()[-1]),
        "cache before (MB)": before,
        "cache after (MB)": _megabytes(cache),
    }


def run(quick: bool) -> pd.DataFrame:
    """Rows: the first use with an empty cache, the warm run reading it, and (full run) the
    first use with the quadrature in one pass; each the median time and largest peak of its
    processes."""
    repeats = 1 if quick else 3
    results: dict[str, list[dict]] = {"first use (empty cache)": [], "warm (cache filled)": []}
    with tempfile.TemporaryDirectory() as data:
        roi = write_roi(Path(data))
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as folder:
                cache = Path(folder)
                results["first use (empty cache)"].append(process(cache, roi))
                results["warm (cache filled)"].append(process(cache, roi))
        if not quick:
            name = "first use, quadrature in one pass (no blocks)"
            results[name] = []
            for _ in range(repeats):
                with tempfile.TemporaryDirectory() as folder:
                    results[name].append(process(Path(folder), roi, ONE_PASS))
    rows = []
    for name, runs in results.items():
        frame = pd.DataFrame(runs)
        row = {"process": name, "processes": len(runs), **frame.median().to_dict()}
        for column in ("peak after imports (MiB)", "peak (MiB)"):
            row[column] = round(frame[column].max())
        rows.append(row)
    return pd.DataFrame(rows)


def main(argv=None) -> pd.DataFrame:
    quick = quick_run(__doc__, argv)
    table = run(quick)
    intro = (
        "A fresh process per row, `emccd-typical` (readout/gain 0.25): `Model.log_likelihood` "
        "on one ROI, then `camera.fisher_information`; `BAYESPSF_CACHE` a temporary folder "
        "(the tables' size in it before and after the process); peak resident memory "
        "(`VmHWM`):"
    )
    publish_table("first_use", intro, table, quick)
    return table


if __name__ == "__main__":
    main()
