"""The report of ``bayespsf analyze`` (``report.md``): the selection, the calibration check
without ground truth, the joint posteriors, the goodness of fit, the misfit figures and the
width precision per molecule, with the files the run wrote."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf.inference.gof import flag_excess_p

if TYPE_CHECKING:
    from bayespsf.analysis.pipeline import Analysis


def _flag_table(frames: pd.DataFrame) -> pd.DataFrame:
    """Per level alpha, the frames tested, the number flagged (``gof_p <= alpha``) and their
    fraction, beside the fraction expected when the model holds, and the binomial p-value of
    at least that many flags when it holds (``flag_excess_p``)."""
    p = frames["gof_p"].dropna()
    rows = []
    for alpha in (0.02, 0.1):
        flagged = int((p <= alpha).sum())
        rows.append(
            {
                "alpha": alpha,
                "frames": len(p),
                "flagged frames": flagged,
                "flagged fraction": flagged / len(p) if len(p) else np.nan,
                "binomial SE": np.sqrt(alpha * (1 - alpha) / max(len(p), 1)),
                "expected when the model holds": alpha,
                "p (this many flags or more)": flag_excess_p(p, alpha),
            }
        )
    return pd.DataFrame(rows)


def _window_table(windows: pd.DataFrame) -> pd.DataFrame:
    """Mean s_x (and its SE) per molecule, one column per fitting window."""
    wide = windows.pivot(index="molecule", columns="window", values=["s_x", "s_x_se"])
    wide.columns = [f"{stat} ({w} x {w})" for stat, w in wide.columns]
    return wide.reset_index()


def _joint_table(molecules: pd.DataFrame) -> pd.DataFrame:
    """The report's joint-posterior columns of the analysed molecules."""
    columns = [
        "molecule",
        "joint_frames",
        "x0_joint_mean",
        "x0_joint_sd",
        "s_x_joint_mean",
        "s_x_joint_sd",
        "s_x_frame_sd",
        "s_y_joint_mean",
        "s_y_joint_sd",
        "joint_method",
        "joint_khat",
    ]
    analysed = molecules[molecules["joint_method"].notna()]
    return analysed[[c for c in columns if c in analysed]]


def report_markdown(result: Analysis, provenance: dict | None = None) -> str:
    """The run's report: selection, the calibration check, Delta s against N, the files."""
    fmt = {"index": False, "floatfmt": ".4g"}
    discrepancy = (
        "Pearson's statistic at the MLE"
        if (provenance or {}).get("goodness-of-fit discrepancy") == "pearson"
        else "the MLE's negative log-likelihood"
    )
    check = result.consistency[
        [
            "parameter",
            "frames",
            "molecules",
            "z_sd",
            "z_sd_se",
            "p_value",
            "p_two_sided",
            "coverage",
            "coverage_se",
            "expected_coverage",
        ]
    ]
    spread_columns = [
        c
        for c in (
            "molecule",
            "frames",
            "N",
            "delta_s_lsq",
            "delta_s_mle",
            "delta_s_mean",
            "posterior_sd",
            "crlb",
            "eq_sigma2dp3",
        )
        if c in result.width_spread
    ]
    lines = [
        "# bayespsf analyze",
        "",
        *(f"- {k}: `{v}`" for k, v in (provenance or {}).items() if "\n" not in str(v)),
        "",
        "![detections on the mean projection](detections.png)",
        "",
        "![traces of the selected molecules](traces.png)",
        "",
        result.found.report_markdown(),
        "## The calibration check without ground truth",
        "",
        "Per-frame posterior means about each molecule's combined (inverse-variance weighted) "
        "estimate, in units of their stated SDs (`bayespsf.analysis.consistency`): a calibrated "
        "model gives z-score SDs of 1 within their errors, chi-square p-values that are not "
        "small, and a coverage at its expected value. `p_value` is small when the frames "
        "scatter more than their SDs say (posteriors too narrow), `p_two_sided` also when "
        "they scatter less (too wide, as with a gain declared too high).",
        "",
        check.to_markdown(**fmt),
        "",
        "![z-scores of the calibration check](zscores.png)",
        "",
        "## The joint posterior of each molecule over its frames",
        "",
        "One position and width shared by a molecule's valid frames, N and b per frame "
        "(`bayespsf.inference.joint`: importance sampling from the joint Laplace approximation). "
        "`s_x_frame_sd` is the mean per-frame posterior SD: the joint SD is expected near "
        "`s_x_frame_sd / sqrt(joint_frames)`.",
        "",
        _joint_table(result.molecules).to_markdown(**fmt),
        "",
        "## Can the model have made each image?",
        "",
        "A parametric-bootstrap goodness-of-fit test of every frame's ROI "
        f"(`bayespsf.inference.gof`: {discrepancy} against up to 49 "
        "refitted replicates, stopped once 10 are as discrepant; column `gof_p`). `frames` "
        "counts the frames tested, `flagged "
        "frames` those with `gof_p <= alpha` and `flagged fraction` their share. Where the "
        "model holds, a fraction alpha of the frames has `gof_p <= alpha`; more flags mean "
        "ROIs it does not describe (two "
        "molecules, a hot pixel, a spot that is not Gaussian). `p (this many flags or more)` "
        "tests the whole dataset: small when more frames are flagged than the model allows. "
        "It sees a misfit that every frame shares (an Airy spot fitted with a Gaussian), "
        "which the check across frames above cannot.",
        "",
        _flag_table(result.frames).to_markdown(**fmt),
        "",
        "![goodness-of-fit p-values](gof_p.png)",
        "",
        "How a misfit shows (`bayespsf.analysis.misfit`): each molecule's mean Pearson residual "
        "image at its frames' fits, scaled to ~N(0, 1) per pixel where the model holds (a "
        "pattern, such as a core and a ring, is a spot the Gaussian does not describe), and "
        "its mean width when only the central w x w pixels are fitted (a Gaussian spot gives "
        "one width in every window, within its SE; `width_by_window.csv`).",
        "",
        "![residual images](residuals.png)",
        "",
        _window_table(result.width_by_window).to_markdown(**fmt),
        "",
        "## Width precision per molecule (the paper's Fig. 2, experimental points)",
        "",
        "`delta_s_*`: the SD over frames of each estimator's s_x (nm); beside it the mean "
        "posterior SD, the mean Cramér-Rao bound and Eq. sigma2dp3 of DeSantis, DeCenzo, Li & "
        "Wang, Opt. Express 18 (2010) at the molecule's mean N (detected photons).",
        "",
        result.width_spread[spread_columns].to_markdown(**fmt),
        "",
        "![width error against N](width_precision.png)",
        "",
        "## Files",
        "",
        *(f"- `{name}`" for name in result.paths),
        "",
    ]
    return "\n".join(lines)


__all__ = ["report_markdown"]
