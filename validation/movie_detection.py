"""From movies to selected molecules, against the simulator's truth, over repeated movies.

Each movie is a simulated ``paper-movie`` (300 frames of 256 x 256 pixels, 40 molecules with
N 500-5000 photons per frame, 10% with two fluorophores, 5% moving by 10 nm per frame), run
through ``find_molecules`` with the scene's own camera, as ``bayespsf detect`` does. Against the
truth (``match_truth``: a candidate within 1.5 pixels of a molecule, 10 of a moving one):

- found: the share of immobile molecules that are candidates (target >= 95%);
- false: the share of candidates that match no molecule (<= 1%);
- bleach frame within +-1: the share of single-fluorophore immobile molecules that bleach and
  pass detection whose bleach frame is found within one frame (>= 90%);
- where the truth decides a rule: two-fluorophore molecules whose both fluorophores bleach in
  the movie, that pass detection and then ``single_step`` (should be none; a second
  fluorophore that outlives the movie shows one step, which no rule can tell); single-
  fluorophore immobile molecules that bleach in the movie and are removed by ``single_step``
  (should be none; one that never bleaches is removed by it, as the paper's rule says); immobile
  molecules removed by ``no_drift`` (its false alarms: a 3-SE test on two axes, ~0.5%; a
  molecule that bleaches within a few frames has a noisy slope); and moving molecules selected
  (should be none).

    python validation/movie_detection.py            # 20 movies (about 1.5 minutes on 2 cores)
    python validation/movie_detection.py --quick    # 2 small movies
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import load_scene
from bayespsf.model import Model
from bayespsf.movie import find_molecules
from bayespsf.simulation import match_truth, simulate_movie

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, per_movie_figure, per_movie_report, study


def one_movie(scene, seed: int) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        truth = simulate_movie(scene, seed=seed, out=Path(folder) / "movie")
        found = find_molecules(truth.files["movie"], Model.from_scene(scene), s0=120.0)
    mol = truth.molecules
    which = match_truth(found.candidates, mol)
    immobile = ~mol["moving"].to_numpy(bool)
    hit = np.zeros(len(mol), bool)
    hit[which[which >= 0]] = True
    rows = found.molecules.set_index("molecule")
    outcome = pd.DataFrame({"candidate": found.candidates["molecule"], "true": which})
    outcome = outcome[outcome["true"] >= 0]
    true = mol.iloc[outcome["true"]].reset_index(drop=True)
    got = rows.loc[outcome["candidate"]].reset_index(drop=True)
    passed_detection = ~got["rejected_by"].fillna("").str.startswith("detection").to_numpy()
    single = (true["fluorophores"] == 1).to_numpy() & ~true["moving"].to_numpy(bool)
    bleaches = true["bleach_frame"].notna().to_numpy()
    judged = single & bleaches & passed_detection
    error = (got["bleach_frame"].astype(float) - true["bleach_frame"].astype(float)).abs()
    two = (true["fluorophores"] == 2).to_numpy()
    return {
        "seed": seed,
        "molecules": len(mol),
        "candidates": len(found.candidates),
        "found (immobile)": hit[immobile].mean(),
        "false candidates": float((which < 0).mean()),
        "bleach within 1 frame": float((error[judged] <= 1).mean()) if judged.any() else np.nan,
        "single-step judged": int(judged.sum()),
        "two-fluorophore passing single_step": int(
            (
                two & bleaches & passed_detection & (got["rejected_by"].fillna("") != "single_step")
            ).sum()
        ),
        "single bleaching immobile removed by single_step": int(
            (single & bleaches & (got["rejected_by"] == "single_step").to_numpy()).sum()
        ),
        "immobile removed by no_drift": int(
            (~true["moving"].to_numpy(bool) & (got["rejected_by"] == "no_drift").to_numpy()).sum()
        ),
        "moving selected": int(
            (true["moving"].to_numpy(bool) & got["selected"].to_numpy(bool)).sum()
        ),
        "selected": int(found.molecules["selected"].sum()),
    }


def main(argv=None):
    args, started, stem = study(__doc__, argv, "movie_detection", posteriors=False)
    scene = load_scene("paper-movie").replace(movie={"dark_frames": 0})
    if args.quick:
        scene = scene.replace(
            movie={"frames": 120, "height": 128, "width": 128, "molecules": 9, "bleach_mean": 50.0}
        )
    movies = pd.DataFrame([one_movie(scene, seed) for seed in range(2 if args.quick else 20)])
    counts = [
        "two-fluorophore passing single_step",
        "single bleaching immobile removed by single_step",
        "immobile removed by no_drift",
        "moving selected",
    ]
    table = pd.DataFrame(
        [
            {
                "movies": len(movies),
                "molecules": int(movies["molecules"].sum()),
                "found (immobile), mean": movies["found (immobile)"].mean(),
                "found, worst movie": movies["found (immobile)"].min(),
                "false candidates, mean": movies["false candidates"].mean(),
                "bleach within 1 frame": np.average(
                    movies["bleach within 1 frame"].fillna(0), weights=movies["single-step judged"]
                ),
                "single-step judged": int(movies["single-step judged"].sum()),
                **{name: int(movies[name].sum()) for name in counts},
                "selected per movie": movies["selected"].mean(),
            }
        ]
    )
    figure(movies, args.out / f"{stem}.png")
    text, summary = per_movie_report(
        "From movies to selected molecules, against the truth",
        table,
        movies,
        stem,
        "detection per movie",
    )
    return finish(args, "movie_detection", table, text, started, summary)


def figure(movies: pd.DataFrame, path: Path) -> None:
    with per_movie_figure(path, "share") as ax:
        k = np.arange(len(movies))
        for column, marker in (
            ("found (immobile)", "o"),
            ("bleach within 1 frame", "s"),
            ("false candidates", "x"),
        ):
            ax.plot(k, movies[column], marker, label=column)
        for level, colour in ((0.95, "C0"), (0.9, "C1"), (0.01, "C2")):  # the targets
            ax.axhline(level, color=colour, lw=0.8, ls="--")


if __name__ == "__main__":
    main()
