"""What ``method="auto"`` chooses: the share of ROIs given the Laplace, importance sampling or
the chain against the photon count, with the Laplace pilot's weight SD and the time per ROI.

``sample_many`` (default ``method="auto"``, ESS 400, one process) on emccd-typical ROIs at
several N. The Laplace is taken where the pilot's weight SD is <= 0.05
(``bayespsf.inference.batched``), which bounds its error for every posterior summary.

    python benchmarks/auto.py            # full run, rewrites its section of README.md
    python benchmarks/auto.py --quick    # a small run that prints only (the tests)
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import re  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import publish_table, quick_run  # noqa: E402

from bayespsf import load_scene, simulate  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.parallel import sample_many  # noqa: E402

WEIGHT_SD = re.compile(r"pilot weight SD ([0-9.e+-]+|inf)")


def choices(photons, rois: int) -> pd.DataFrame:
    rows = []
    for n_photons in photons:
        scene = load_scene("emccd-typical").replace(emitter={"photons": float(n_photons)})
        model = Model.from_scene(scene)
        counts, _ = simulate(scene, rois, seed=1)
        sample_many(counts[:2], model, seed=1, workers=1)  # warm-up
        started = time.perf_counter()
        table = sample_many(counts, model, seed=1, workers=1)
        seconds = time.perf_counter() - started
        sds = [float(m.group(1)) for m in map(WEIGHT_SD.search, table["why"]) if m]
        share = table["method"].value_counts(normalize=True)
        rows.append(
            {
                "N": n_photons,
                "ROIs": rois,
                **{
                    f"{m} (share)": float(share.get(m, 0.0))
                    for m in ("laplace", "importance", "mcmc")
                },
                "pilot weight SD (median)": float(np.median(sds)) if sds else np.nan,
                "converged": float((table["status"] == "converged").mean()),
                "ms per ROI": 1e3 * seconds / rois,
            }
        )
    return pd.DataFrame(rows)


def main(argv=None):
    quick = quick_run(__doc__, argv)
    photons = (1000, 20_000) if quick else (150, 200, 300, 1000, 3000, 5000, 10_000, 20_000)
    table = choices(photons, 20 if quick else 400)
    intro = '`sample_many` (`method="auto"`, ESS 400, one process), emccd-typical at each N:'
    publish_table("auto", intro, table, quick)
    return table


if __name__ == "__main__":
    main()
