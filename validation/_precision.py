"""One point of a precision study: theory, least squares, MLE and posteriors on one scene.

Shared by precision_vs_photons.py and precision_vs_pixel_size.py. For s_x and x0: the paper's
closed forms (Eq. sigma2dp3, Eq. centroiderror), the Eq. pesum pixel sum (s_x), the Cramér–Rao
bound under the model's camera law, and from simulated images the spread of the least-squares
and maximum-likelihood estimates about the truth, the mean posterior SD, the spread of the
posterior means about the truth, and the coverage of central 68% and 95% posterior intervals,
each with its Monte Carlo standard error.
"""

from __future__ import annotations

import numpy as np
from _common import mean_and_error, sd_and_error

from bayespsf import simulate, theory
from bayespsf.inference import fit_lsq, fit_mle
from bayespsf.inference.summary import coverage
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

QUANTITIES = ("s_x", "x0")


def theory_columns(scene) -> dict:
    g, e, bg = scene.geometry, scene.emitter, scene.background
    sigma_b = bg["sd"] if "sd" in bg else np.sqrt(bg["mean"])
    args = (e["photons"], e["s0x"], e["s0y"], g["pixel_size"], sigma_b, bg["mean"])
    bound = theory.crlb(scene)
    return {
        "s_x closed (Eq. sigma2dp3)": float(theory.delta_s_analytic(*args)),
        "s_x pixel sum (Eq. pesum)": float(theory.delta_s_numeric(*args, roi=g["roi"])),
        "s_x CRLB": float(bound["s_x"]),
        "x0 closed (Eq. centroiderror)": float(theory.delta_x_analytic(*args)),
        "x0 CRLB": float(bound["x0"]),
    }


def point(
    scene, images: int, mle_images: int, posteriors: int, seed: int, runner, label: str, **options
) -> dict:
    """All columns of one (scene) point; ``runner`` is a _common.Runner."""
    model = Model.from_scene(scene)
    row = theory_columns(scene)
    counts, truth = simulate(scene, images, seed=seed)
    true = truth[list(PARAMETER_NAMES)].to_numpy(float)
    lsq = fit_lsq(counts, model)
    ok = lsq["converged"].to_numpy()
    row["LSQ images"], row["LSQ failures"] = int(ok.sum()), int((~ok).sum())
    mle = fit_mle(counts[:mle_images], model)
    mle_ok = mle["converged"].to_numpy()
    row["MLE images"], row["MLE failures"] = int(mle_ok.sum()), int((~mle_ok).sum())
    post = runner.posteriors(
        label, counts[:posteriors], model, true[:posteriors], seed=seed, scene=scene, **options
    )
    row["posteriors"] = len(post)
    row["posterior CPU s"] = float(post["seconds"].sum())
    row["posteriors not converged"] = int((~post["converged"]).sum())
    for q in QUANTITIES:
        k = PARAMETER_NAMES.index(q)
        row[f"{q} LSQ SD"], row[f"{q} LSQ SD err"] = sd_and_error(lsq[q][ok] - true[ok, k])
        row[f"{q} MLE SD"], row[f"{q} MLE SD err"] = sd_and_error(
            mle[q][mle_ok] - true[:mle_images][mle_ok, k]
        )
        row[f"{q} posterior SD (mean)"], row[f"{q} posterior SD err"] = mean_and_error(
            post[f"{q}_sd"]
        )
        row[f"{q} posterior-mean SD"], row[f"{q} posterior-mean SD err"] = sd_and_error(
            post[f"{q}_mean"] - post[f"{q}_truth"]
        )
        for prob in (0.68, 0.95):
            c = coverage(post, prob).set_index("parameter").loc[q]
            row[f"{q} coverage {prob:.0%}"] = c["coverage"]
            row[f"{q} coverage {prob:.0%} err"] = c["se"]
    # the background: the model's Poisson law against the scene's (often narrower) law
    row["b posterior-mean bias"], row["b posterior-mean bias err"] = mean_and_error(
        post["b_mean"] - post["b_truth"]
    )
    row["b posterior SD (mean)"] = float(post["b_sd"].mean())
    c = coverage(post, 0.68).set_index("parameter").loc["b"]
    row["b coverage 68%"], row["b coverage 68% err"] = c["coverage"], c["se"]
    closed = row["s_x closed (Eq. sigma2dp3)"]
    for column in (
        "s_x pixel sum (Eq. pesum)",
        "s_x CRLB",
        "s_x LSQ SD",
        "s_x MLE SD",
        "s_x posterior SD (mean)",
        "s_x posterior-mean SD",
    ):
        row[f"{column} / closed"] = row[column] / closed
    row["x0 LSQ SD / closed"] = row["x0 LSQ SD"] / row["x0 closed (Eq. centroiderror)"]
    row["x0 CRLB / closed"] = row["x0 CRLB"] / row["x0 closed (Eq. centroiderror)"]
    return row


def summary_columns(q: str) -> list[str]:
    """The columns of the short markdown table for quantity ``q``."""
    if q == "s_x":
        return [
            "s_x closed (Eq. sigma2dp3)",
            "s_x pixel sum (Eq. pesum) / closed",
            "s_x CRLB / closed",
            "s_x LSQ SD / closed",
            "s_x MLE SD / closed",
            "s_x posterior SD (mean) / closed",
            "s_x posterior-mean SD / closed",
            "s_x coverage 68%",
            "s_x coverage 95%",
        ]
    return [
        "x0 closed (Eq. centroiderror)",
        "x0 CRLB / closed",
        "x0 LSQ SD / closed",
        "x0 MLE SD",
        "x0 posterior SD (mean)",
        "x0 posterior-mean SD",
        "x0 coverage 68%",
        "x0 coverage 95%",
    ]


def plot_panel(ax, table, x: str, q: str, title: str, logx: bool = True) -> None:
    """Theory as lines, Monte Carlo as points with error bars, in the style of the paper."""
    xs = table[x].to_numpy(float)
    if q == "s_x":
        lines = [
            ("s_x closed (Eq. sigma2dp3)", "k--", "Eq. sigma2dp3"),
            ("s_x pixel sum (Eq. pesum)", "k:", "pixel sum (Eq. pesum)"),
            ("s_x CRLB", "k-", "CRLB"),
        ]
    else:
        lines = [
            ("x0 closed (Eq. centroiderror)", "k--", "Eq. centroiderror"),
            ("x0 CRLB", "k-", "CRLB"),
        ]
    for column, style, label in lines:
        ax.plot(xs, table[column], style, label=label)
    points = [
        (f"{q} LSQ SD", "o", "least squares (paper's method)"),
        (f"{q} MLE SD", "s", "maximum likelihood"),
        (f"{q} posterior-mean SD", "^", "posterior mean"),
        (f"{q} posterior SD (mean)", "v", "mean posterior SD"),
    ]
    for column, marker, label in points:
        err = table[column.replace(" (mean)", "") + " err"]
        ax.errorbar(xs, table[column], yerr=err, fmt=marker, ms=4, capsize=2, label=label)
    if logx:
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.set_ylabel(f"{'Δs_x' if q == 's_x' else 'Δx0'} rms (nm)")
