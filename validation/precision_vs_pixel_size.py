"""Width and position precision against pixel size (the paper's Fig. 3).

a/s0 from 0.2 to 2.5 on the shipped `paper-fig3` scene (N = 500 photons, fixed; s0 = 120 nm;
background sigma_b = 1, <b> = 4 photons, truncated Gaussian; 19x19 pixels at every pixel size,
as in the paper; the paper's camera): the columns of precision_vs_photons.py, plus the paper's
two empirical curves, Eq. sigma2dp3 x 1.57 and Eq. sigma2dp3 x (1.23 + 0.42 a/s0), and the
least-squares SD's ratio to the latter with its Monte Carlo error. The figure marks the paper's
theoretical optimum (a/s0 = 1.18, from Eq. sigma2dp3) and its simulated one (a/s0 = 0.73).
Writes precision_vs_pixel_size.{csv,md,png}.

    python validation/precision_vs_pixel_size.py [--quick] [--workers K | --scheduler ADDRESS]
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _common import Runner, finish, study
from _precision import plot_panel, point, summary_columns

from bayespsf import load_scene, theory

RATIOS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.73, 0.8, 0.9, 1.0, 1.18, 1.5, 2.0, 2.5)
S0 = 120.0
PAPER_THEORY_OPTIMUM, PAPER_SIMULATED_OPTIMUM = 1.18, 0.73
FULL = {"images": 2000, "mle_images": 500, "posteriors": 30}
QUICK = {"images": 40, "mle_images": 10, "posteriors": 3}


def run(args, ratios, sizes, options) -> pd.DataFrame:
    base = load_scene("paper-fig3")
    rows = []
    with Runner(args, "precision_vs_pixel_size") as runner:
        for k, ratio in enumerate(ratios):
            print(f"a/s0 = {ratio}", flush=True)
            scene = base.replace(geometry={"pixel_size": ratio * S0})
            row = point(
                scene, seed=500 + k, runner=runner, label=f"ratio{ratio:g}", **sizes, **options
            )
            rows.append({"a/s0": ratio, "a (nm)": ratio * S0, **row})
    table = pd.DataFrame(rows)
    closed = table["s_x closed (Eq. sigma2dp3)"]
    table["paper: closed x 1.57"] = 1.57 * closed
    table["paper: closed x (1.23 + 0.42 a/s0)"] = closed * (1.23 + 0.42 * table["a/s0"])
    law = table["paper: closed x (1.23 + 0.42 a/s0)"]
    table["LSQ SD / paper law"] = table["s_x LSQ SD"] / law
    table["LSQ SD / paper law err"] = table["s_x LSQ SD err"] / law
    return table


def optimum(table: pd.DataFrame, column: str, below: float = PAPER_THEORY_OPTIMUM) -> float:
    """a/s0 of the smallest value of ``column`` among a/s0 < ``below`` (the paper's local
    minimum of the simulated curve lies there)."""
    part = table[table["a/s0"] < below]
    return float(part.loc[part[column].idxmin(), "a/s0"])


def figure(table: pd.DataFrame, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, q in zip(axes, ("s_x", "x0"), strict=True):
        plot_panel(ax, table, "a/s0", q, f"paper-fig3, N = 500: {q}", logx=False)
        ax.set_xlabel("a / s0")
        ax.axvline(PAPER_THEORY_OPTIMUM, color="grey", ls="--", lw=0.8)
        ax.axvline(PAPER_SIMULATED_OPTIMUM, color="grey", ls=":", lw=0.8)
    axes[0].plot(table["a/s0"], table["paper: closed x 1.57"], "C7--", label="paper: closed x 1.57")
    axes[0].plot(
        table["a/s0"],
        table["paper: closed x (1.23 + 0.42 a/s0)"],
        "C7-",
        label="paper: closed x (1.23 + 0.42 a/s0)",
    )
    axes[0].legend(fontsize=7)
    fig.suptitle(
        "Precision against pixel size (cf. DeSantis et al., Opt. Express 18 (2010), Fig. 3); "
        "dashed: theoretical optimum 1.18, dotted: the paper's simulated optimum 0.73",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    args, started, stem = study(__doc__, argv, "precision_vs_pixel_size")
    sizes = QUICK if args.quick else FULL
    options = {"max_steps": 1000} if args.quick else {}
    ratios = (0.5, 1.4) if args.quick else RATIOS
    table = run(args, ratios, sizes, options)
    figure(table, args.out / f"{stem}.png")
    ours = theory.optimal_pixel_ratio(500.0, 1.0, 4.0)
    below = table[table["a/s0"] < PAPER_THEORY_OPTIMUM]
    law = below["LSQ SD / paper law"].to_numpy()
    law_err = below["LSQ SD / paper law err"].to_numpy()
    chi2 = float(np.sum(((law - 1) / law_err) ** 2))
    claims = pd.DataFrame(
        [
            {
                "claim": "theoretical optimum a/s0 (Eq. sigma2dp3)",
                "paper": 1.18,
                "ours": round(float(ours), 3),
            },
            {
                "claim": "simulated (least-squares) local optimum a/s0 < 1.18",
                "paper": 0.73,
                "ours": optimum(table, "s_x LSQ SD"),
            },
            {
                "claim": "MLE local optimum a/s0 < 1.18",
                "paper": None,
                "ours": optimum(table, "s_x MLE SD"),
            },
            {
                "claim": "CRLB optimum a/s0 < 1.18",
                "paper": None,
                "ours": optimum(table, "s_x CRLB"),
            },
            {
                "claim": "LSQ SD / closed x (1.23 + 0.42 a/s0), a/s0 < 1.18: range",
                "paper": 1.0,
                "ours": f"{law.min():.3f} to {law.max():.3f}",
            },
            {
                "claim": f"  chi^2 of that ratio against 1 ({len(law)} points)",
                "paper": None,
                "ours": round(chi2, 1),
            },
        ]
    )
    text = (
        f"# Precision against pixel size ({sizes['images']} images per point for least squares, "
        f"{sizes['mle_images']} for the MLE, {sizes['posteriors']} posteriors)\n\n"
        "## The paper's claims (DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), Fig. 3)\n\n"
        + claims.to_markdown(index=False)
        + "\n\nOptima are the grid point of smallest value (grid: "
        + ", ".join(f"{r:g}" for r in table["a/s0"])
        + "); compare neighbouring points with their errors in the tables below.\n\n## s_x\n\n"
        + table[
            ["a/s0", *summary_columns("s_x"), "LSQ SD / paper law", "LSQ SD / paper law err"]
        ].to_markdown(index=False, floatfmt=".3g")
        + "\n\n## x0\n\n"
        + table[["a/s0", *summary_columns("x0")]].to_markdown(index=False, floatfmt=".3g")
        + f"\n\nFigure: [{stem}.png]({stem}.png); every column with its Monte Carlo error in "
        f"[{stem}.csv]({stem}.csv). The ROI is 19x19 pixels at every pixel size, as in the "
        "paper: at a/s0 = 0.2 it spans only +-1.9 s0, so the tails of the spot fall outside it. "
        "The model assumes a Poisson background (variance <b> = 4); the scene draws the paper's "
        "truncated Gaussian (variance ~1)."
    )
    summary = (
        claims.to_markdown(index=False)
        + f"\n\n![precision against pixel size](results/{stem}.png)\n\nPosterior CPU time: "
        f"{table['posterior CPU s'].sum() / 3600:.2f} core-hours for {table['posteriors'].sum()} "
        "posteriors."
    )
    return finish(args, "precision_vs_pixel_size", table, text, started, summary)


if __name__ == "__main__":
    main()
