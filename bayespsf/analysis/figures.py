"""The figures of ``bayespsf analyze``'s report, each written to a PNG.

``detections``: the mean projection with every candidate (selected, rejected by a rule,
rejected by detection); ``traces``: the selected molecules' photons per frame with their
bleaching step; ``zscores``: the calibration check's per-frame z-scores against N(0, 1);
``width_precision``: the paper's experimental Delta s against N (each estimator), beside the
mean posterior SD, the CRLB and Eq. sigma2dp3 (DeSantis, DeCenzo, Li & Wang, Opt. Express 18
(2010), Fig. 2).
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

MAX_TRACES = 12  # the traces figure shows at most this many molecules


@contextmanager
def _figure(path: Path, figsize):
    """A figure of one axes, saved to ``path`` on exit. A bare ``Figure`` (no pyplot): the
    caller's matplotlib backend and open figures are left as they were."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    ax = fig.subplots()
    yield fig, ax
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def detections(image: np.ndarray, molecules: pd.DataFrame, path) -> Path:
    """The projection with each candidate marked by its outcome."""
    path = Path(path)
    with _figure(path, figsize=(5, 5)) as (_, ax):
        ax.imshow(image, cmap="gray", origin="upper")
        outcome = np.where(
            molecules["selected"].astype(bool),
            "selected",
            np.where(
                molecules["rejected_by"].fillna("").str.startswith("detection"),
                "rejected by detection",
                "rejected by a selection rule",
            ),
        )
        for label, marker, color in (
            ("selected", "o", "C2"),
            ("rejected by a selection rule", "s", "C1"),
            ("rejected by detection", "x", "C3"),
        ):
            part = molecules[outcome == label]
            style = (
                {"color": color} if marker == "x" else {"facecolors": "none", "edgecolors": color}
            )
            ax.scatter(
                part["x"], part["y"], s=60, marker=marker, label=f"{label} ({len(part)})", **style
            )
        ax.set_xlabel("x (pixels)")
        ax.set_ylabel("y (pixels)")
        ax.legend(fontsize=7, loc="upper right")
    return path


def traces(frames: pd.DataFrame, molecules: pd.DataFrame, path) -> Path:
    """The selected molecules' aperture photons per frame, each with its bleaching step."""
    path = Path(path)
    chosen = molecules[molecules["selected"].astype(bool)].head(MAX_TRACES)
    with _figure(path, figsize=(6, 3.5)) as (_, ax):
        for k, row in enumerate(chosen.itertuples()):
            trace = frames[frames["molecule"] == row.molecule].sort_values("frame")
            ax.plot(
                trace["frame"],
                trace["photons"],
                lw=0.8,
                color=f"C{k % 10}",
                label=f"molecule {row.molecule}",
            )
            if pd.notna(row.bleach_frame):
                ax.axvline(row.bleach_frame, color=f"C{k % 10}", lw=0.8, ls="--")
        ax.set_xlabel("frame")
        ax.set_ylabel("aperture photons (detected)")
        ax.set_title(f"selected molecules (first {len(chosen)}); dashed: bleaching step")
        if len(chosen):
            ax.legend(fontsize=6, ncol=2)
    return path


def zscores(frame_z: pd.DataFrame, parameters, path) -> Path:
    """Histograms of the per-frame z-scores of each parameter against N(0, 1)."""
    from scipy import stats

    path = Path(path)
    grid = np.linspace(-4, 4, 200)
    with _figure(path, figsize=(6, 3.5)) as (_, ax):
        for k, p in enumerate(parameters):
            z = frame_z[f"{p}_z"].dropna().to_numpy()
            if z.size:
                ax.hist(
                    z,
                    bins=np.linspace(-4, 4, 33),
                    density=True,
                    histtype="step",
                    color=f"C{k}",
                    label=f"{p} (SD {z.std(ddof=1):.2f})",
                )
        ax.plot(grid, stats.norm.pdf(grid), color="k", lw=1, label="N(0, 1)")
        ax.set_xlabel("per-frame z-score about the molecule's combined estimate")
        ax.legend(fontsize=7)
    return path


def gof_pvalues(p_values, path) -> Path:
    """The goodness-of-fit p-values against their law where the model holds: at each value
    ``s`` a p-value takes, the share of frames with ``gof_p <= s`` against ``s`` (the diagonal
    where the model holds, ``P(p <= s) = s`` at those values whether the replicates stopped
    early or not: ``bayespsf.inference.gof``), with a band of two binomial SEs. A misfit
    lifts the points above the diagonal at small ``s``. (A histogram in equal bins is not flat
    here: above ``stop_after / replicates`` the values ``10 / l`` crowd towards 0.2.)"""
    path = Path(path)
    p = np.asarray(p_values, dtype=float)
    p = np.sort(p[np.isfinite(p)])
    with _figure(path, figsize=(5, 3)) as (_, ax):
        ax.plot([0, 1], [0, 1], color="k", lw=1, ls="--", label="model holds")
        if p.size:
            s = np.unique(p)
            share = np.searchsorted(p, s, side="right") / p.size
            band = 2.0 * np.sqrt(s * (1.0 - s) / p.size)
            ax.fill_between(s, s - band, s + band, color="0.85", label="2 binomial SEs")
            ax.plot(s, share, ".", color="C0", ms=3, label="frames")
            ax.legend(fontsize=7)
        ax.set_xlabel("goodness-of-fit p-value s")
        ax.set_ylabel("share of frames with gof_p <= s")
    return path


def residual_images(ids, images, path, most: int = 16) -> Path:
    """Each molecule's mean Pearson residual image (``misfit.mean_residuals``; ~N(0, 1) per
    pixel where the model holds), the first ``most`` molecules, on one colour scale."""
    from matplotlib.figure import Figure

    path = Path(path)
    shown = min(len(ids), most)
    columns = max(1, min(4, shown))
    rows = max(1, -(-shown // columns))
    fig = Figure(figsize=(2.2 * columns + 1.0, 2.2 * rows + 0.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, columns)).ravel()
    for ax in axes:
        ax.set_axis_off()
    picture = None
    for ax, molecule, image in zip(axes, ids[:shown], images[:shown], strict=False):
        picture = ax.imshow(image, cmap="RdBu_r", vmin=-4, vmax=4)
        ax.set_title(f"molecule {molecule}: chi2/pixel {np.mean(image**2):.2f}", fontsize=7)
    if picture is not None:
        fig.colorbar(picture, ax=list(axes), shrink=0.8, label="sqrt(K) x mean residual")
    fig.savefig(path, dpi=80)
    return path


def width_precision(spread: pd.DataFrame, path) -> Path:
    """Delta s against N per molecule, each estimator and each prediction."""
    path = Path(path)
    with _figure(path, figsize=(6, 4)) as (_, ax):
        styles = {
            "delta_s_lsq": ("least squares (the paper's)", "s", "C3"),
            "delta_s_mle": ("MLE", "^", "C1"),
            "delta_s_mean": ("posterior mean", "o", "C0"),
            "posterior_sd": ("mean posterior SD", "_", "C0"),
            "crlb": ("mean CRLB", "_", "k"),
            "eq_sigma2dp3": ("Eq. sigma2dp3", "x", "C2"),
        }
        for column, (label, marker, color) in styles.items():
            if column in spread:
                ax.scatter(spread["N"], spread[column], marker=marker, color=color, label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("mean N per frame (detected photons)")
        ax.set_ylabel("width error of s_x (nm)")
        ax.legend(fontsize=7)
    return path


def report_figures(image, found, frame_z, spread, gof_p, residuals, out: Path) -> dict[str, Path]:
    """Every figure of the report, into one folder.

    Parameters
    ----------
    image : numpy.ndarray
        The movie's mean projection (``bayespsf.movie.project``).
    found : FoundMolecules
        Its molecules and per-frame table.
    frame_z : pandas.DataFrame
        The calibration check's per-frame z-scores, one column per parameter.
    spread : pandas.DataFrame
        The width spread against N (``width_spread``).
    gof_p : array_like
        Goodness-of-fit p-values per ROI.
    residuals : tuple
        ``(ids, images)`` of the mean residual images.
    out : Path
        The folder.

    Returns
    -------
    dict of str to Path
        The files' paths by name.
    """
    from bayespsf.analysis.consistency import PARAMETERS

    made = [
        detections(image, found.molecules, out / "detections.png"),
        traces(found.frames, found.molecules, out / "traces.png"),
        zscores(frame_z, PARAMETERS, out / "zscores.png"),
        width_precision(spread, out / "width_precision.png"),
        gof_pvalues(gof_p, out / "gof_p.png"),
        residual_images(*residuals, out / "residuals.png"),
    ]
    return {path.name: path for path in made}


__all__ = [
    "detections",
    "gof_pvalues",
    "report_figures",
    "residual_images",
    "traces",
    "width_precision",
    "zscores",
]
