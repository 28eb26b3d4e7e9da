"""Per-frame localisation end to end: a movie in, localisations out, against picasso's Localize.

A user with a blinking (dSTORM, PAINT) movie would otherwise run picasso's ``localize``
(identification by its net-gradient threshold, then a fit per spot). Here both run on the same
simulated movies (emccd-typical's camera and spot: s0 = 130 nm, 100 nm pixels, 10 background
photons per pixel; 50 molecules that shine in every frame of 200 frames of 256 x 256 pixels,
at 1 000 and at 250 photons per frame), on every core of the machine (picasso ``threaded=True``;
bayespsf one worker per core), from the movie's file to the localisations in memory:

* picasso ``localize`` with ``gausslq`` (its default least squares) and ``gaussmle`` (its
  pixel-integrated MLE), box 13, with the camera's baseline, sensitivity and EM gain, at the
  net-gradient threshold of ``THRESHOLDS`` that misses and adds the fewest spots on that movie
  (found with the truth, which a user does not have: the peer's threshold is set in its
  favour; the table names it);
* ``bayespsf detect --per-frame`` (``localize_frames(posterior=False)``: the MLE and its
  Cramér-Rao bound) and ``bayespsf analyze --per-frame`` (the posterior, its model check and
  the least squares), window 13 (both from s0, as the command takes it from the camera file).

Each localisation is matched to the nearest molecule that is on in its frame (within one
pixel); reported are the seconds, localisations, those without a position (a fit that did not
converge: NaN, as picasso leaves such rows out), missed and false ones, the RMS error of x and
y against the truth, the median error bar (picasso's ``lpx``, ``lpy``: the fit's Cramér-Rao
bound or its least-squares error; bayespsf's: the posterior SD, or the bound after ``detect``)
and how often the truth lies within 1.96 error bars (0.95 when the error bars are right; its
binomial SE is in the table) and the SD of the errors over their error bars (1 when right).

    pip install -e ".[bench]"
    python benchmarks/localize.py            # full run, rewrites its section of README.md
    python benchmarks/localize.py --quick    # 3 frames of 64 x 64 pixels, 1 000 photons: prints
                                             # only (tests)
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from _report import publish_table, quick_run
from scipy.spatial import cKDTree

from bayespsf import Model, load_scene, simulate_movie
from bayespsf.analysis import localize_frames

SCENE = "emccd-typical"
BOX = 13  # picasso's box, and the window bayespsf takes from s0 = 130 nm on 100 nm pixels
THRESHOLDS = (2000.0, 3000.0, 5000.0, 10000.0)  # picasso's minimum net gradient, tried
PHOTONS = (1000.0, 250.0)


def movie_scene(frames: int, side: int, molecules: int, photons: float = 1000.0):
    """The benchmark's movie: emccd-typical's camera and spot, molecules on in every frame."""
    return load_scene(SCENE).replace(
        emitter={"photons": photons},
        movie={"frames": frames, "height": side, "width": side, "molecules": molecules}
        | {"dark_frames": 0, "bleach_mean": 1e6, "two_fluorophores": 0.0, "moving": 0.0},
    )


def picasso(path: Path, scene, method: str, net_gradient: float) -> pd.DataFrame:
    """picasso's ``localize`` of the movie file: ``frame``, ``x``, ``y``, ``lpx``, ``lpy``
    (pixels, picasso's convention)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # picasso's import and deprecation chatter
        from picasso import io, localize

        movie, _ = io.load_movie(str(path))
        camera = scene.to_dict()["camera"]
        info = {"Baseline": camera["offset"], "Sensitivity": camera["e_per_adu"]}
        info |= {"Gain": camera["gain"], "Qe": 1.0, "Pixelsize": scene.geometry["pixel_size"]}
        try:
            locs, _ = localize.localize(
                movie,
                camera_info=info,
                identification_parameters={"Min. Net Gradient": net_gradient, "Box Size": BOX},
                fitting_method=method,
                threaded=True,
            )
        finally:
            movie.close()  # its file stays open until then
    return locs[["frame", "x", "y", "lpx", "lpy"]]


def bayespsf(path: Path, scene, posterior: bool, out: Path) -> pd.DataFrame:
    """``localize_frames`` of the movie file on one worker per core: picasso's columns."""
    model = Model.from_scene(scene)
    found = localize_frames(
        path, model, s0=scene.emitter["s0x"], out=out, posterior=posterior, progress=False
    )
    return found.locs[["frame", "x", "y", "lpx", "lpy"]]


def score(locs: pd.DataFrame, truth: pd.DataFrame, pixel_size: float) -> dict:
    """Each localisation with a position and error bar matched to the nearest molecule on in
    its frame within one pixel: those without one (NaN: a fit that did not converge), missed
    and false ones, the RMS error (nm), the median error bar (nm), the share of errors within
    1.96 error bars and the SD of the errors over their error bars (x and y pooled)."""
    on = truth[truth["on"]]
    apart = 1e4  # frames this many pixels apart: no match across frames
    tree = cKDTree(np.column_stack([on["x"] + apart * on["frame"], on["y"]]))
    finite = locs.dropna(subset=["x", "y", "lpx", "lpy"])
    distance, nearest = tree.query(
        np.column_stack([finite["x"] + apart * finite["frame"], finite["y"]]),
        distance_upper_bound=1.0,
    )
    hit = np.isfinite(distance)
    # a molecule claimed twice keeps its nearest localisation; the other is a false one
    order = np.argsort(distance[hit])
    claimed = nearest[hit][order]
    first = np.zeros(len(claimed), dtype=bool)
    first[np.unique(claimed, return_index=True)[1]] = True
    keep = np.flatnonzero(hit)[order][first]
    matched, truth_at = finite.iloc[keep], on.iloc[nearest[keep]]
    error = np.concatenate(
        [matched["x"].to_numpy() - truth_at["x"], matched["y"].to_numpy() - truth_at["y"]]
    )
    bar = np.concatenate([matched["lpx"].to_numpy(), matched["lpy"].to_numpy()])
    inside = np.abs(error) <= 1.96 * bar
    return {
        "localisations": len(locs),
        "without a position": len(locs) - len(finite),  # a fit that did not converge
        "missed": len(on) - len(keep),
        "false": len(finite) - len(keep),
        "RMS error (nm)": pixel_size * np.sqrt(np.mean(error**2)),
        "median error bar (nm)": pixel_size * np.median(bar),
        "within 1.96 error bars": inside.mean(),
        "its SE": np.sqrt(0.95 * 0.05 / len(inside)),
        "SD of error / error bar": np.std(error / bar),
    }


def best_threshold(path: Path, scene, truth: pd.DataFrame) -> float:
    """The threshold of ``THRESHOLDS`` at which picasso's ``gausslq`` misses and adds the
    fewest spots of the movie (the first of equals)."""
    errors = []
    for net_gradient in THRESHOLDS:
        scored = score(picasso(path, scene, "gausslq", net_gradient), truth, 1.0)
        errors.append(scored["missed"] + scored["false"])
    return THRESHOLDS[int(np.argmin(errors))]


def run(frames: int, side: int, molecules: int, photons=PHOTONS) -> pd.DataFrame:
    """Every method on one simulated movie per photon count: one row each."""
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        # numba compilation and imports first
        small = movie_scene(1, 64, 2)
        warm = simulate_movie(small, seed=1, out=Path(folder) / "w").files["movie"]
        picasso(warm, small, "gausslq", THRESHOLDS[-1])
        picasso(warm, small, "gaussmle", THRESHOLDS[-1])
        bayespsf(warm, small, True, Path(folder) / "warm")
        for n in photons:
            scene = movie_scene(frames, side, molecules, n)
            made = simulate_movie(scene, seed=5, out=Path(folder) / f"m{n:g}")
            path, truth = made.files["movie"], pd.read_csv(made.files["truth"])
            threshold = best_threshold(path, scene, truth)
            out = Path(folder) / f"{n:g}"
            methods = {
                "picasso localize, gausslq": (picasso, "gausslq", threshold),
                "picasso localize, gaussmle": (picasso, "gaussmle", threshold),
                "bayespsf detect --per-frame (MLE, Cramér-Rao bound)": (
                    bayespsf,
                    False,
                    out / "detect",
                ),
                "bayespsf analyze --per-frame (posterior)": (bayespsf, True, out / "analyze"),
            }
            first = len(rows)
            for name, (method, *options) in methods.items():
                started = time.perf_counter()
                locs = method(path, scene, *options)
                seconds = time.perf_counter() - started
                rows.append(
                    {"photons": n, "method": name}
                    | {"threshold": threshold if name.startswith("picasso") else np.nan}
                    | {"seconds": seconds, "localisations/s": len(locs) / seconds}
                    | score(locs, truth, scene.geometry["pixel_size"])
                )
            for row in rows[first:]:
                row["time / picasso gausslq"] = row["seconds"] / rows[first]["seconds"]
    return pd.DataFrame(rows)


def main(argv=None) -> pd.DataFrame:
    quick = quick_run(__doc__, argv)
    frames, side, molecules = (3, 64, 3) if quick else (200, 256, 50)
    table = run(frames, side, molecules, PHOTONS[:1] if quick else PHOTONS)
    intro = (
        f"{frames} frames of {side} x {side} pixels ({SCENE}'s camera and spot, s0 = 130 nm), "
        f"{molecules} molecules on in every frame at each photon count, {os.cpu_count()} "
        "cores; each method from the movie's file to its localisations (`threshold`: "
        "picasso's minimum net gradient, chosen with the truth):"
    )
    publish_table("localize", intro, table, quick)
    return table


if __name__ == "__main__":
    main()
