"""The first use of an EMCCD readout/gain ratio on a machine: building its tables, in time and
peak resident memory, against a process that reads them from the on-disk cache.

The ``table`` tier's likelihood table (``bayespsf/cameras/_emccd_table.py``) and the exact
Fisher-information spline (``_emccd_fisher.py``) of a new readout/gain ratio are built by
quadrature on the machine's first use of it, then kept in the on-disk cache
(``_table_cache``). Every row is a fresh process (``python -c``) with ``BAYESPSF_CACHE`` set to
a temporary folder: empty for a first use, filled by that first use for a warm run. The
process imports bayespsf, simulates one ``emccd-typical`` ROI (readout/gain 0.25), builds its
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

import pandas as pd
from _report import publish_table, quick_run

CHILD = """
import json, resource, sys, time

started = time.perf_counter()
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
if len(sys.argv) > 1:
    _emccd_law._BLOCK = int(sys.argv[1])
scene = bayespsf.load_scene("emccd-typical")
counts, truth = bayespsf.simulate(scene, 1, seed=1)
params = truth.to_numpy()
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


def process(cache: Path, block: int | None = None) -> dict:
    """One fresh process's times and peak memory, with ``BAYESPSF_CACHE=cache``, and the size
    of the cache's tables before and after it (MB)."""
    before = _megabytes(cache)
    env = {**os.environ, "BAYESPSF_CACHE": str(cache)}
    command = [sys.executable, "-c", CHILD, *([] if block is None else [str(block)])]
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
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as folder:
            cache = Path(folder)
            results["first use (empty cache)"].append(process(cache))
            results["warm (cache filled)"].append(process(cache))
    if not quick:
        name = "first use, quadrature in one pass (no blocks)"
        results[name] = []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as folder:
                results[name].append(process(Path(folder), ONE_PASS))
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
