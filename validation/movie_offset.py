"""The offset and readout noise without dark frames (``bayespsf calibrate`` without ``--dark``):
do their error bars cover the declared camera in repeated movies, and is a background that is
not Poisson refused?

Three cases, each a simulated ``paper-movie`` (300 frames of 256 x 256, 40 molecules) analysed
as a user would (``calibrate_camera`` without dark frames: the cumulants' first camera,
detection and selection, ``M`` from the molecules, then the offset from the pixels no
candidate's ROI touches):

* EMCCD (gain 200, 12 e- per ADU, readout 50 e-, offset 100 ADU) with a Poisson background of
  3 photons; the readout is declared (``readout_sd``: at this gain the photon noise, 2 lam M^2
  ~ 1700 ADU^2, hides the readout's 17 ADU^2), so the offset is measured and the declaration
  checked;
* a CCD/sCMOS (2.17 ADU per photoelectron, variance 12 ADU^2, offset 100 ADU) with the same
  background: offset and readout both measured;
* paper-movie's own background (rounded Gaussian photon numbers, mean 2.75, SD 0.92: not
  Poisson) on the EMCCD with the readout declared: the check must refuse it (its cumulants
  would put the offset 23 ADU high).

    python validation/movie_offset.py            # 20 + 20 + 5 movies (28 minutes; the sCMOS
                                                 # movies' exact-law fits take most)
    python validation/movie_offset.py --quick    # one small EMCCD movie (128 x 128)
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
from _common import finish, per_movie_figure, per_movie_report, study

OFFSET = 100.0
SCMOS = {
    "kind": "scmos",
    "gain": 2.17,
    "offset": OFFSET,
    "variance": 12.0,
    "quantize": True,
    "saturation": 65535.0,
}
READOUT_ADU = {"emccd": 50.0 / 12.0, "scmos": np.sqrt(12.0 + 1 / 12)}  # + the ADC's rounding


def case_scene(case: str, quick: bool) -> Scene:
    table = load_scene("paper-movie").to_dict()
    if case != "paper background":
        table["background"] = {"kind": "poisson", "mean": 3.0}
    if case == "scmos":
        table["camera"] = dict(SCMOS)
    table["movie"]["dark_frames"] = 0
    if quick:
        table["movie"].update(frames=150, height=128, width=128, molecules=12, bleach_mean=100.0)
    return Scene.from_dict(table)


def one_movie(case: str, scene: Scene, seed: int, folder: Path) -> dict:
    files = simulate_movie(scene, seed=seed, out=folder / f"movie-{seed}").files
    kind = "scmos" if case == "scmos" else "emccd"
    declared = None if kind == "scmos" else 50.0
    row = {"case": case, "seed": seed}
    try:
        cal = calibrate_camera(
            files["movie"], kind=kind, s0=120.0, e_per_adu=12.0, readout_sd=declared
        )
    except BayespsfInputError as exc:
        return {**row, "refused": True, "why": str(exc)[:80]}
    o = cal.offset
    row.update(
        refused=False,
        why="",
        offset=o.offset,
        offset_se=o.offset_se,
        offset_z=(o.offset - OFFSET) / o.offset_se,
        readout=o.readout_sd,
        readout_se=o.readout_sd_se,
        photons=o.photons,
        pixels=o.pixels,
    )
    if declared is None:
        row["readout_z"] = (o.readout_sd - READOUT_ADU[kind]) / o.readout_sd_se
    return row


def summary_row(case: str, movies: pd.DataFrame) -> dict:
    measured = movies[~movies["refused"]]
    row = {"case": case, "movies": len(movies), "refused": int(movies["refused"].sum())}
    if measured.empty:
        return row
    n = len(measured)
    z = measured["offset_z"]
    row.update(
        {
            "offset bias (ADU)": measured["offset"].mean() - OFFSET,
            "mean offset SE": measured["offset_se"].mean(),
            "offset 95% covers": float((z.abs() <= 1.96).mean()),
            "binomial SE": np.sqrt(0.95 * 0.05 / n),
        }
    )
    if n > 1:  # spreads need two movies (a quick run has one)
        row["bias MC error"] = measured["offset"].std(ddof=1) / np.sqrt(n)
        row["SD of offset z"] = z.std(ddof=1)
    if "readout_z" in measured and measured["readout_z"].notna().any():
        rz = measured["readout_z"].dropna()
        row["readout bias (ADU)"] = measured["readout"].mean() - READOUT_ADU["scmos"]
        row["readout 95% covers"] = float((rz.abs() <= 1.96).mean())
        if len(rz) > 1:
            row["SD of readout z"] = rz.std(ddof=1)
    return row


def main(argv=None):
    args, started, stem = study(__doc__, argv, "movie_offset", posteriors=False)
    counts = {"emccd": 1} if args.quick else {"emccd": 20, "scmos": 20, "paper background": 5}
    rows, summaries = [], []
    with tempfile.TemporaryDirectory() as folder:
        for case, n in counts.items():
            scene = case_scene(case, args.quick)
            part = pd.DataFrame(
                [
                    one_movie(case, scene, seed, Path(folder))
                    for seed in range(1 if args.quick else n)
                ]
            )
            rows.append(part)
            summaries.append(summary_row(case, part))
    movies = pd.concat(rows, ignore_index=True)
    table = pd.DataFrame(summaries)
    figure(movies, args.out / f"{stem}.png")
    text, summary = per_movie_report(
        f"Offset and readout without dark frames: true offset {OFFSET:g} ADU",
        table,
        movies,
        stem,
        "offsets without dark frames",
    )
    return finish(args, "movie_offset", table, text, started, summary)


def figure(movies: pd.DataFrame, path: Path) -> None:
    with per_movie_figure(path, "offset (ADU)") as ax:
        for k, (case, part) in enumerate(movies[~movies["refused"]].groupby("case")):
            ax.errorbar(
                np.arange(len(part)),
                part["offset"],
                yerr=1.96 * part["offset_se"],
                fmt="o",
                ms=3,
                color=f"C{k}",
                label=f"{case}, 95% interval",
            )
        ax.axhline(OFFSET, color="k", lw=1)


if __name__ == "__main__":
    main()
