"""ADU per photon from whole movies (``bayespsf calibrate``): does the 95% interval cover the
declared camera in repeated movies?

Each movie is a simulated ``paper-movie`` (EMCCD gain 200, 12 e- per ADU: M = 16.667 ADU per
photon; molecules' photons fluctuating +-20% between frames; 10% with two fluorophores, 5%
moving; 20 dark frames), analysed as a user would: ``calibrate_camera`` (dark frames, a
provisional gain, ``find_molecules``, then Eq. photonConv over the selected molecules with its
fluctuation term). Per movie: the estimate, its SE, and whether its 95% interval holds the truth.
Beside it, the paper's Eq. photonConv without the fluctuation term (``calibrate_gain`` on each
selected molecule's ROI frames before bleaching, averaged over the molecules), to show what the
fluctuation does to it.

    python validation/movie_gain.py            # 40 paper-movies (about 9 minutes on 2 cores)
    python validation/movie_gain.py --quick    # 2 small movies (150 frames of 128 x 128)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import load_scene
from bayespsf.calibration import calibrate_camera, calibrate_gain
from bayespsf.movie import cut_rois
from bayespsf.simulation import simulate_movie

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, per_movie_figure, per_movie_report, study

TRUE_M = 200.0 / 12.0


def one_movie(scene, seed: int, folder: Path) -> dict:
    files = simulate_movie(scene, seed=seed, out=folder / f"movie-{seed}").files
    cal = calibrate_camera(files["movie"], files["dark"], kind="emccd", s0=120.0)
    gain = cal.gain
    kept = gain.per_molecule[~gain.per_molecule["outlier"]]
    rois = cut_rois(files["movie"], kept, roi=25, fit=15)
    # the paper's Eq. photonConv per molecule, on the same frames (those before bleaching)
    plain_m = [
        calibrate_gain(
            rois.counts[rois.table["molecule"].to_numpy() == m][:k].astype(float)
        ).adu_per_photon
        for m, k in zip(kept["molecule"], kept["frames"], strict=True)
    ]
    low, high = gain.interval
    return {
        "seed": seed,
        "molecules": len(kept),
        "outliers": int(gain.per_molecule["outlier"].sum()),
        "M": gain.adu_per_photon,
        "SE": gain.se,
        "low": low,
        "high": high,
        "covered": bool(low <= TRUE_M <= high),
        "z": (gain.adu_per_photon - TRUE_M) / gain.se,
        "provisional M": cal.provisional_adu_per_photon,
        "Eq. photonConv without fluctuation (mean over molecules)": float(np.mean(plain_m)),
    }


def run(movies: int, scene) -> pd.DataFrame:
    with tempfile.TemporaryDirectory() as folder:
        return pd.DataFrame([one_movie(scene, seed, Path(folder)) for seed in range(movies)])


def main(argv=None):
    args, started, stem = study(__doc__, argv, "movie_gain", posteriors=False)
    scene = load_scene("paper-movie")
    if args.quick:
        scene = scene.replace(
            movie={
                "frames": 150,
                "height": 128,
                "width": 128,
                "molecules": 12,
                "bleach_mean": 100.0,
            }
        )
    movies = run(2 if args.quick else 40, scene)
    n = len(movies)
    covered = movies["covered"].mean()
    table = pd.DataFrame(
        [
            {
                "movies": n,
                "true M": TRUE_M,
                "mean M": movies["M"].mean(),
                "bias %": 100 * (movies["M"].mean() / TRUE_M - 1),
                "bias MC error %": 100 * movies["M"].std(ddof=1) / np.sqrt(n) / TRUE_M,
                "mean SE %": 100 * movies["SE"].mean() / TRUE_M,
                "SD of z": movies["z"].std(ddof=1),
                "95% interval covers": covered,
                "binomial SE": np.sqrt(0.95 * 0.05 / n),
                "mean molecules": movies["molecules"].mean(),
                "mean provisional M": movies["provisional M"].mean(),
                "plain Eq. photonConv bias %": 100
                * (
                    movies["Eq. photonConv without fluctuation (mean over molecules)"].mean()
                    / TRUE_M
                    - 1
                ),
            }
        ]
    )
    figure(movies, args.out / f"{stem}.png")
    text, summary = per_movie_report(
        f"ADU per photon from whole movies: true M = {TRUE_M:.4g}",
        table,
        movies,
        stem,
        "movie gain estimates",
    )
    return finish(args, "movie_gain", table, text, started, summary)


def figure(movies: pd.DataFrame, path: Path) -> None:
    with per_movie_figure(path, "M (ADU per photon)") as ax:
        k = np.arange(len(movies))
        error = [movies["M"] - movies["low"], movies["high"] - movies["M"]]
        ax.errorbar(
            k,
            movies["M"],
            yerr=error,
            fmt="o",
            ms=3,
            color="C0",
            label="bayespsf calibrate, 95% interval",
        )
        ax.plot(
            k,
            movies["Eq. photonConv without fluctuation (mean over molecules)"],
            "x",
            color="C3",
            label="Eq. photonConv without the fluctuation term",
        )
        ax.axhline(TRUE_M, color="k", lw=1)


if __name__ == "__main__":
    main()
