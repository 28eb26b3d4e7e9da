"""Gain calibration (Eq. photonConv) on simulated movies: its bias and spread.

Movies of one immobile molecule on an EMCCD (EM gain 100, readout 30 e-, offset 100 ADU,
5 e-/ADU: 20 ADU per photon; Poisson background of 5 photons per pixel), at a bright and a dim
molecule (nine centre pixels, or the centre pixel alone below SNR 3), for movies of 100 and 500
frames: the mean of the estimates, its bias relative to the truth with its Monte Carlo error,
and the spread of single-movie estimates.

    python validation/gain_calibration.py [--quick]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import Scene, simulate
from bayespsf.calibration import calibrate_gain

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, study

CAMERA = {"kind": "emccd", "gain": 100.0, "readout_sd": 30.0, "offset": 100.0, "e_per_adu": 5.0}
TRUE_M = 20.0


def run(movies: int, frames=(100, 500), photons=(2000.0, 60.0)):
    """The table, and the single-movie estimates of M per (N, frames)."""
    rows, estimates = [], {}
    for n_photons in photons:
        scene = Scene.from_dict(
            {
                "geometry": {"roi": 11, "pixel_size": 100.0},
                "emitter": {"photons": n_photons, "s0x": 120.0, "s0y": 120.0},
                "background": {"kind": "poisson", "mean": 5.0},
                "camera": CAMERA,
            }
        )
        for n_frames in frames:
            results = [calibrate_gain(simulate(scene, n_frames, seed=k)[0]) for k in range(movies)]
            m = np.array([r.adu_per_photon for r in results])
            estimates[(n_photons, n_frames)] = m
            rows.append(
                {
                    "N": n_photons,
                    "frames": n_frames,
                    "movies": movies,
                    "pixels used": len(results[0].pixel_estimates),
                    "mean M": m.mean(),
                    "bias %": 100 * (m.mean() / TRUE_M - 1),
                    "bias MC error %": 100 * m.std(ddof=1) / np.sqrt(movies) / TRUE_M,
                    "spread (SD) %": 100 * m.std(ddof=1) / TRUE_M,
                }
            )
    return pd.DataFrame(rows), estimates


def figure(estimates: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(estimates), figsize=(3.2 * len(estimates), 3), sharey=True)
    for ax, ((n_photons, n_frames), m) in zip(np.atleast_1d(axes), estimates.items(), strict=True):
        ax.hist(m, bins=20, color="C0")
        ax.axvline(TRUE_M, color="k", lw=1)
        ax.set_title(f"N = {n_photons:g}, {n_frames} frames", fontsize=9)
        ax.set_xlabel("M (ADU per photon)")
    fig.suptitle("Single-movie gain estimates (Eq. photonConv); line: the truth", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    args, started, stem = study(__doc__, argv, "gain_calibration", posteriors=False)
    table, estimates = run(5 if args.quick else 200, (100,) if args.quick else (100, 500))
    figure(estimates, args.out / f"{stem}.png")
    text = (
        f"# Gain calibration (Eq. photonConv): true M = {TRUE_M:g} ADU per photon\n\n"
        + table.to_markdown(index=False, floatfmt=".3g")
        + f"\n\nFigure: [{stem}.png]({stem}.png), the single-movie estimates."
    )
    summary = table.to_markdown(index=False, floatfmt=".3g") + (
        f"\n\n![gain estimates](results/{stem}.png)"
    )
    return finish(args, "gain_calibration", table, text, started, summary)


if __name__ == "__main__":
    main()
