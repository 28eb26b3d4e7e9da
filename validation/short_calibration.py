"""The camera from one frame or a few (``bayespsf calibrate`` on fewer than 20 frames): does
the ADU per photon's stated error bar cover the declared camera?

Each movie is a simulated ``paper-movie`` field (256 x 256 pixels, 40 molecules of 500-5000
photons) with a Poisson background of 3 photons per pixel, of 1 or 10 frames, analysed as a
user would: ``calibrate_camera``, which for fewer than 20 frames tiles the background away from
the detected spots into 8 x 8 blocks and solves the photon-transfer relations of their pooled
cumulants (``bayespsf.calibration.spatial``), with bootstrap standard errors over the blocks.
Cases:

* EMCCD (gain 200, 12 e- per ADU: M = 16.667 ADU per photon; readout 50 e- declared, as it
  must be at this gain), 1 and 10 frames;
* sCMOS (M = 2.17 ADU per photoelectron, readout variance 12 ADU^2) with 20 dark frames, 1 and
  10 frames;
* the same sCMOS without dark frames (offset and readout from the third and fourth cumulants),
  1 and 10 frames: a single frame is often refused (its readout not measurable).

Per case: movies, refused, the mean relative SE beside the relative SD of ``M`` over the
movies, the bias, the SD of the z-scores, the fraction of accepted movies with ``|M - truth| <=
1.96 SE`` with its binomial SE, and the fraction within 1.96 SDs of ``M`` over the movies: what
an error bar equal to the estimate's own spread covers on the same movies, which tells a short
error bar from an unlucky draw of movies.

80 movies per case, and 400 single EMCCD frames: their coverage claim (at least 0.90) needs a
binomial SE of about 0.015 to be resolved; on the first 80 of them (seeds 0-79) an error bar
equal to the estimate's spread over the 400 covers only 71.

    python validation/short_calibration.py            # 80 or 400 movies per case (about 15 minutes)
    python validation/short_calibration.py --quick    # 3 small movies per case (128 x 128)
    python validation/short_calibration.py --case emccd-1 --movies 100   # one case, 100 movies

A run of some cases (``--case``, repeatable) or of another number of movies (``--movies``)
writes its own files (``short_calibration_<cases>_<movies>``) and leaves validation/README.md
alone.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import Scene, load_scene
from bayespsf.calibration import calibrate_camera
from bayespsf.errors import BayespsfInputError
from bayespsf.simulation import simulate_movie

sys.path.insert(0, str(Path(__file__).parent))
from _common import saved_figure, study, write

SCMOS = {
    "kind": "scmos",
    "gain": 2.17,
    "offset": 100.0,
    "variance": 12.0,
    "quantize": True,
    "saturation": 65535.0,
}
TRUE_M = {"emccd": 200.0 / 12.0, "scmos": 2.17}
CASES = [  # (name, camera kind, frames, dark frames)
    ("emccd, 1 frame, readout declared", "emccd", 1, False),
    ("emccd, 10 frames, readout declared", "emccd", 10, False),
    ("scmos, 1 frame, dark frames", "scmos", 1, True),
    ("scmos, 10 frames, dark frames", "scmos", 10, True),
    ("scmos, 1 frame, cumulants", "scmos", 1, False),
    ("scmos, 10 frames, cumulants", "scmos", 10, False),
]
KEYS = {  # --case: the short name of each case
    "emccd-1": CASES[0],
    "emccd-10": CASES[1],
    "scmos-dark-1": CASES[2],
    "scmos-dark-10": CASES[3],
    "scmos-1": CASES[4],
    "scmos-10": CASES[5],
}
MOVIES = 80  # per case in a full run, but for
MOVIES_OF = {"emccd-1": 400}  # whose coverage claim needs a binomial SE of ~0.015


def case_scene(kind: str, frames: int, quick: bool) -> Scene:
    table = load_scene("paper-movie").to_dict()
    table["background"] = {"kind": "poisson", "mean": 3.0}
    if kind == "scmos":
        table["camera"] = dict(SCMOS)
    table["movie"].update(frames=frames, dark_frames=20)
    if quick:
        table["movie"].update(height=128, width=128, molecules=8)
    return Scene.from_dict(table)


def one_movie(case, seed: int, folder: Path, quick: bool) -> dict:
    name, kind, frames, dark = case
    files = simulate_movie(case_scene(kind, frames, quick), seed=seed, out=folder / "m").files
    options = {"e_per_adu": 12.0, "readout_sd": 50.0} if kind == "emccd" else {}
    row = {"case": name, "seed": seed}
    try:
        cal = calibrate_camera(
            files["movie"], files["dark"] if dark else None, kind=kind, s0=120.0, **options
        )
    except BayespsfInputError as error:
        return row | {"refused": True, "reason": str(error)[:80]}
    e = cal.estimate
    truth = TRUE_M[kind]
    return row | {
        "refused": False,
        "M": e.adu_per_photon,
        "SE": e.adu_per_photon_se,
        "z": (e.adu_per_photon - truth) / e.adu_per_photon_se,
        "offset": e.offset,
        "offset SE": e.offset_se,
        "blocks": e.blocks,
    }


def summarise(movies: pd.DataFrame, cases=CASES) -> pd.DataFrame:
    rows = []
    for case in cases:
        name, kind = case[0], case[1]
        all_rows = movies[movies["case"] == name]
        kept = all_rows[~all_rows["refused"]]
        n = len(kept)
        truth = TRUE_M[kind]
        covered = float((kept["z"].abs() <= 1.96).mean()) if n else np.nan
        spread = kept["M"].std(ddof=1) if n > 1 else np.nan
        rows.append(
            {
                "case": name,
                "movies": len(all_rows),
                "refused": int(all_rows["refused"].sum()),
                "true M": truth,
                "mean SE %": 100 * kept["SE"].mean() / truth if n else np.nan,
                "SD of M %": 100 * spread / truth,
                "bias %": 100 * (kept["M"].mean() / truth - 1) if n else np.nan,
                "SD of z": kept["z"].std(ddof=1) if n > 1 else np.nan,
                "within 1.96 SE": covered,
                "binomial SE": np.sqrt(covered * (1 - covered) / n) if n else np.nan,
                "within 1.96 SD of M": float(((kept["M"] - truth).abs() <= 1.96 * spread).mean())
                if n > 1
                else np.nan,
                "mean offset SE (ADU)": kept["offset SE"].mean() if n else np.nan,
            }
        )
    return pd.DataFrame(rows)


def figure(movies: pd.DataFrame, path: Path, cases=CASES) -> None:
    with saved_figure(path, (7, 3)) as ax:
        kept = movies[~movies["refused"]]
        for k, (name, *_rest) in enumerate(cases):
            z = kept.loc[kept["case"] == name, "z"].to_numpy()
            ax.plot(np.full(z.size, k) + np.linspace(-0.2, 0.2, z.size), z, ".", ms=3)
        for level in (-1.96, 1.96):
            ax.axhline(level, color="k", lw=0.8, ls="--")
        ax.set_xticks(range(len(cases)), [c[0].replace(", ", "\n", 1) for c in cases], fontsize=6)
        ax.set_ylabel("z = (M - truth) / SE")


def arguments(p) -> None:
    p.add_argument(
        "--case",
        action="append",
        choices=list(KEYS),
        help="run this case only (repeatable; default all six)",
    )
    p.add_argument(
        "--movies",
        type=int,
        default=None,
        help=f"movies per case (default {MOVIES}, single EMCCD frames {MOVIES_OF['emccd-1']}; "
        "--quick 3)",
    )


def main(argv=None):
    args, started, stem = study(
        __doc__, argv, "short_calibration", posteriors=False, arguments=arguments
    )
    keys = list(dict.fromkeys(args.case or KEYS))
    cases = [KEYS[k] for k in keys]
    if args.movies is not None and args.movies < 2:
        raise SystemExit(f"--movies must be at least 2, got {args.movies}")
    command = "python validation/short_calibration.py" + (" --quick" if args.quick else "")
    command += "".join(f" --case {k}" for k in args.case or [])
    command += "" if args.movies is None else f" --movies {args.movies}"
    if args.case or args.movies is not None:  # their own files, never the README's section
        parts = [*(keys if args.case else []), *([f"{args.movies}"] if args.movies else [])]
        stem = stem.replace("short_calibration", "_".join(["short_calibration", *parts]), 1)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for key, case in zip(keys, cases, strict=True):
            if args.movies is not None:
                repeats = args.movies
            else:
                repeats = 3 if args.quick else MOVIES_OF.get(key, MOVIES)
            for seed in range(repeats):
                rows.append(one_movie(case, seed, Path(folder) / f"{case[1]}{seed}", args.quick))
    movies = pd.DataFrame(rows)
    table = summarise(movies, cases)
    figure(movies, args.out / f"{stem}.png", cases)
    fmt = {"index": False, "floatfmt": ".4g"}
    text = (
        "# The camera from one frame or a few: spatial photon transfer\n\n"
        f"{table.to_markdown(**fmt)}\n\nPer movie:\n\n{movies.to_markdown(**fmt)}\n\n"
        f"Figure: [{stem}.png]({stem}.png), each movie's z-score."
    )
    summary = f"{table.to_markdown(**fmt)}\n\n![short-movie z-scores](results/{stem}.png)"
    whole = not (args.quick or args.case or args.movies is not None)
    write(args.out, stem, table, text, command, started, summary if whole else None)
    print(text)
    return table


if __name__ == "__main__":
    main()
