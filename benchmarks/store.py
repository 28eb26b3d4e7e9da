"""What keeping every posterior costs: `sample_many` with and without a store.

On simulated `emccd-typical` ROIs (15 x 15, N = 1 000), one process (`workers=1`, one
thread), `method="auto"`: in each round, on ROIs of its own, `sample_many` without a store,
then with a new store (what `bayespsf fit` and `analyze` write), then again on that store (a
resume that reads every molecule back and samples none), then `Store.posterior` of one
molecule, then with a store that keeps no draws (`keep_draws=False`, `bayespsf analyze
--per-frame --no-draws`). Wall-clock seconds, as the store's cost is writing files; the
ratio of stored to unstored throughput is taken within each round.

    pip install -e ".[bench]"
    python benchmarks/store.py            # full run, rewrites its section of README.md
    python benchmarks/store.py --quick    # a small run that prints only (the tests)
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import publish_table, quick_run  # noqa: E402

from bayespsf import load_scene, simulate  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.parallel import Store, sample_many  # noqa: E402

SCENE = "emccd-typical"


def _seconds(function):
    started = time.perf_counter()
    function()
    return time.perf_counter() - started


def rounds(n: int, count: int) -> pd.DataFrame:
    """One row per round: ROIs/s without and with a store, the resume, one molecule's read,
    and a store without draws."""
    scene = load_scene(SCENE)
    model = Model.from_scene(scene)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        warm, _ = simulate(scene, 16, seed=99)  # numba's compilation, the writer's imports
        sample_many(warm, model, seed=1, workers=1, store=Path(folder) / "warm", scene=scene)
        Store(Path(folder) / "warm").posterior(0)  # imports ArviZ
        for k in range(count):
            counts, _ = simulate(scene, n, seed=k)
            store = Path(folder) / f"round-{k}"
            run = {"seed": k, "workers": 1, "scene": scene, "progress": False}
            plain = _seconds(lambda c=counts, r=run: sample_many(c, model, **r))
            stored = _seconds(lambda c=counts, r=run, s=store: sample_many(c, model, store=s, **r))
            resumed = _seconds(lambda c=counts, r=run, s=store: sample_many(c, model, store=s, **r))
            read = _seconds(lambda s=store: Store(s).posterior(n // 2))
            bare = store.with_name(store.name + "-bare")
            light = _seconds(
                lambda c=counts, r=run, s=bare: sample_many(
                    c, model, store=s, keep_draws=False, **r
                )
            )
            files, bare_files = Store(store).files(), Store(bare).files()
            rows.append(
                {
                    "round": k,
                    "ROIs": n,
                    "ROIs/s, no store": n / plain,
                    "ROIs/s, store": n / stored,
                    "store / no store": plain / stored,
                    "store's ms per ROI": 1e3 * (stored - plain) / n,
                    "resume (s per 1 000)": 1e3 * resumed / n,
                    "Store.posterior (ms)": 1e3 * read,
                    "files": len(files),
                    "kB per ROI": sum(f.stat().st_size for f in files) / n / 1e3,
                    "ROIs/s, store without draws": n / light,
                    "kB per ROI without draws": sum(f.stat().st_size for f in bare_files) / n / 1e3,
                }
            )
    return pd.DataFrame(rows)


def main(argv=None) -> pd.DataFrame:
    quick = quick_run(__doc__, argv)
    n, count = (48, 2) if quick else (2048, 5)
    table = rounds(n, count)
    ratio = table["store / no store"]
    intro = (
        f'`sample_many(method="auto")` of {n} {SCENE} ROIs per round, one process, without '
        "and with a store (wall-clock; each round on its own ROIs): stored throughput "
        f"{np.median(ratio):.2f}x unstored, median of {count} rounds "
        f"({ratio.min():.2f}-{ratio.max():.2f}x)."
    )
    publish_table("store", intro, table, quick)
    return table


if __name__ == "__main__":
    main()
