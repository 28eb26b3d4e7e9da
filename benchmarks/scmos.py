"""sCMOS: what the exact pixel law costs, and a fit and a posterior of sCMOS ROIs against picasso.

On the pixels of simulated `scmos-typical` ROIs (15 x 15, N = 1 000, 10 background photons,
gain 2.17 ADU/e-, readout 1.6 e- rms), at the true expected counts, one thread: nanoseconds per
pixel of the sCMOS law's evaluations that inference makes (the `exact` tier's log p, with its
score, with its score and curvature; the `huang` tier's; the exact Fisher information that
the Cramér-Rao bound needs, and Huang's `1 / (lam + s^2)` that steers the fit's steps), each as
a ratio to the Poisson log-pmf of the same pixels in the same run. Then `fit_mle` (with its
Laplace and Cramér-Rao bound) and `sample_many(method="auto")` on the same ROIs against
picasso's `gaussmle` (the counts converted to photons with the camera's gain and offset), in
rounds (`throughput.alternated`: each round's ratio to its own `gaussmle`, CPU seconds).

    pip install -e ".[bench]"
    python benchmarks/scmos.py            # full run, rewrites its section of README.md
    python benchmarks/scmos.py --quick    # a small run that prints only (the tests)
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # picasso and bayespsf compile with numba
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import machine, publish, quick_run  # noqa: E402
from throughput import alternated  # noqa: E402

from bayespsf import load_scene, simulate  # noqa: E402
from bayespsf._runtime import best_time  # noqa: E402
from bayespsf.cameras import SCMOS  # noqa: E402
from bayespsf.cameras.photon import poisson_log_pmf  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.psf import PARAMETER_NAMES  # noqa: E402

SCENE = "scmos-typical"


def law(quick: bool) -> pd.DataFrame:
    """Nanoseconds per pixel of each evaluation, and its ratio to the Poisson log-pmf's."""
    scene = load_scene(SCENE)
    model = Model.from_scene(scene)
    n = 20 if quick else 400
    counts, truth = simulate(scene, n, seed=3)
    lam = model.expected(truth[list(PARAMETER_NAMES)].to_numpy())
    counts = np.ascontiguousarray(counts, dtype=np.float64)
    exact = model.camera
    camera = scene.camera
    huang = SCMOS(camera["gain"], camera["offset"], camera["variance"], likelihood="huang")
    photons = np.round(np.maximum(model.to_photons(counts), 0.0))
    evaluations = {
        "Poisson log-pmf (the baseline)": lambda: poisson_log_pmf(photons, lam),
        "exact: log p": lambda: exact.log_likelihood_unchecked(counts, lam),
        "exact: log p and score": lambda: exact.log_likelihood_and_score_unchecked(counts, lam),
        "exact: score and curvature": lambda: exact.score_and_curvature_unchecked(counts, lam),
        "exact: Fisher information": lambda: exact.fisher_information_unchecked(lam),
        "Huang's 1 / (lam + s^2) (the fit's steps)": lambda: exact.step_information_unchecked(lam),
        "huang: log p": lambda: huang.log_likelihood_unchecked(counts, lam),
        "huang: log p and score": lambda: huang.log_likelihood_and_score_unchecked(counts, lam),
    }
    pixels = lam.size
    rows = []
    for name, run in evaluations.items():
        run()  # compilation
        seconds = best_time(run, 2 if quick else 5)
        rows.append({"evaluation": name, "pixels": pixels, "ns per pixel": 1e9 * seconds / pixels})
    table = pd.DataFrame(rows)
    table["time / Poisson"] = table["ns per pixel"] / table["ns per pixel"].iloc[0]
    return table


def markdown(per_pixel: pd.DataFrame, turns: pd.DataFrame, command: str) -> str:
    fmt = {"floatfmt": ".3g", "index": False}
    return (
        f"The law per pixel ({SCENE}, at the true expected counts):\n\n"
        f"{per_pixel.to_markdown(**fmt)}\n\n"
        '`fit_mle` (with its Laplace and Cramér–Rao bound) and `sample_many(method="auto")` '
        "against picasso's `gaussmle` on the same ROIs, in rounds (each round's ratio of "
        f"ROIs/s to its own `gaussmle`):\n\n{turns.to_markdown(**fmt)}\n\n"
        f"Command: `{command}` on {machine()}."
    )


def main(argv=None):
    quick = quick_run(__doc__, argv)
    per_pixel = law(quick)
    turns = alternated(SCENE, 40 if quick else 1000, 2 if quick else 5)
    command = "python benchmarks/scmos.py" + (" --quick" if quick else "")
    publish("scmos", markdown(per_pixel, turns, command), quick)
    return per_pixel, turns


if __name__ == "__main__":
    main()
