"""From a movie to per-molecule results: ``analyze`` (``bayespsf analyze``; issue 14, item 1).

The stages, in order:

1. ``bayespsf.movie.find_molecules``: detection, traces, bleaching steps and the paper's
   selection rules (in detected photoelectrons);
2. the central ``fit`` x ``fit`` ROI of every valid frame of every selected molecule;
3. a posterior per ROI (``sample_many``: local processes or a Dask cluster; its store is
   ``OUT/posteriors``, so a rerun with the same ``OUT`` continues and a killed run loses no
   finished ROI), the MLE with its Cramér-Rao bound (``fit_mle``) and the paper's least squares
   (``fit_lsq``), in the camera file's photon unit, and a bootstrap goodness-of-fit p-value
   per ROI (``bayespsf.model_check``, run by ``sample_many(check=True)`` beside each
   posterior and stored with it);
3b. per selected molecule, the joint posterior of its frames (``bayespsf.analysis.joint``:
   one position and width shared by the frames, N and b per frame);
4. the tables and files: ``locs.hdf5`` + ``locs.yaml`` (picasso), ``locs.csv``
   (ThunderSTORM), ``locs.parquet`` (every column), ``molecules.csv`` (the selection outcome
   and, per selected molecule, its joint posterior and, per parameter, the calibration check
   without ground truth), ``consistency.csv`` (that check over all molecules),
   ``width_spread.csv`` (the paper's experimental Delta s against N), ``width_by_window.csv``
   (``bayespsf.analysis.misfit``) and ``report.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.analysis.consistency import PARAMETERS, frame_consistency
from bayespsf.analysis.joint import joint_posteriors
from bayespsf.analysis.locs import localizations, write_all
from bayespsf.analysis.misfit import mean_residuals, width_by_window
from bayespsf.analysis.width_spread import width_spread
from bayespsf.batch import sample_many
from bayespsf.errors import BayespsfInputError
from bayespsf.estimators import fit_lsq, fit_mle
from bayespsf.model import Model
from bayespsf.model_check import check_discrepancy, flag_excess_p
from bayespsf.movie.extract import iter_rois, open_movie
from bayespsf.movie.pipeline import FoundMolecules, find_molecules
from bayespsf.movie.pipeline import write as write_selection
from bayespsf.psf import PARAMETER_NAMES


@dataclass
class Analysis:
    """What ``analyze`` made: its tables, and the files it wrote (``paths``, by name)."""

    found: FoundMolecules
    frames: pd.DataFrame  # one row per analysed (molecule, frame): posterior, MLE, LSQ
    molecules: pd.DataFrame
    consistency: pd.DataFrame
    width_spread: pd.DataFrame
    width_by_window: pd.DataFrame  # the mean widths when the central w x w pixels are fitted
    paths: dict[str, Path] = field(default_factory=dict)


def valid_rois(movie, found: FoundMolecules, fit: int, block: int = 64):
    """The ``fit`` x ``fit`` ROIs of the valid frames of the selected molecules, with their
    table (``molecule``, ``frame``, ``row``, ``col``: the movie pixel at each ROI's centre)."""
    valid = found.frames.loc[found.frames["valid"].astype(bool), ["molecule", "frame"]]
    chosen = found.molecules[found.molecules["molecule"].isin(valid["molecule"])]
    wanted = set(map(tuple, valid.to_numpy()))
    counts, tables = [], []
    for stack in iter_rois(movie, chosen, roi=fit, fit=fit, block=block):
        pairs = zip(stack.table["molecule"], stack.table["frame"], strict=True)
        keep = np.array([p in wanted for p in pairs], dtype=bool)
        counts.append(stack.counts[keep])
        tables.append(stack.table[keep])
    table = pd.concat(tables, ignore_index=True)
    table["row"] = table.pop("row0") + fit // 2
    table["col"] = table.pop("col0") + fit // 2
    return np.concatenate(counts).astype(np.float64), table


def _estimates(counts, model: Model) -> pd.DataFrame:
    """The MLE (``<p>_mle``, ``crlb_<p>``) and the paper's least squares (``<p>_lsq``)."""
    mle = fit_mle(counts, model, laplace=False)
    lsq = fit_lsq(counts, model)
    out = pd.DataFrame(index=mle.index)
    for p in PARAMETER_NAMES:
        out[f"{p}_mle"] = mle[p].to_numpy()
        out[f"crlb_{p}"] = mle[f"crlb_{p}"].to_numpy()
        out[f"{p}_lsq"] = lsq[p].where(lsq["converged"]).to_numpy()
    out["mle_converged"] = mle["converged"].to_numpy(bool)
    return out


def _per_molecule(found: FoundMolecules, molecules: pd.DataFrame) -> pd.DataFrame:
    """The selection outcome of every candidate; per analysed molecule and parameter the
    combined (inverse-variance) estimate, its SE and the check's chi-square p-value, z-score SD
    and coverage; and the molecule's joint posterior (``joint``)."""
    values = ["combined", "combined_se", "p_value", "p_two_sided", "z_sd", "coverage"]
    wide = molecules.pivot(index="molecule", columns="parameter", values=values)
    wide.columns = [f"{p}_{stat}" for stat, p in wide.columns]
    return found.molecules.merge(wide.reset_index(), on="molecule", how="left")


def analyze(
    movie, model: Model, *, s0: float, out, roi: int = 25, fit: int = 15, rules=None,
    method: str = "auto", ess: float | None = None, seed: int = 0, workers: int | None = None,
    executor=None, progress: bool | None = None, provenance: dict | None = None,
    z_calibration=None, z_range=(-800.0, 800.0), files: dict | None = None,
    gof_discrepancy: str = "likelihood",
) -> Analysis:  # fmt: skip
    """The module docstring's stages on ``movie`` with ``model`` (a camera file's model, its
    ROI size unused); every file goes into the folder ``out``. ``provenance`` (the camera
    file's text, the command) is recorded in ``locs.yaml`` and the report. With
    ``z_calibration`` (a ``bayespsf.axial.calibrate.Calibration``), every frame also gets its
    z posterior (``bayespsf.axial.table.z_posteriors``, z uniform on ``z_range`` nm), whose
    summary goes into the localisation tables and whose calibration into ``locs.yaml``.
    ``files`` (name: path) are files the caller put into ``out`` (the camera file), listed in
    the report beside the run's own. ``gof_discrepancy``: the goodness-of-fit test's
    discrepancy (``bayespsf.model_check.DISCREPANCIES``; ``"pearson"`` is calibrated at a
    background of a few photons per pixel, where the default is conservative)."""
    check_discrepancy("gof_discrepancy", gof_discrepancy)
    if gof_discrepancy != "likelihood":
        provenance = {**(provenance or {}), "goodness-of-fit discrepancy": gof_discrepancy}
    movie = open_movie(movie)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    found = find_molecules(movie, model, s0=s0, roi=roi, fit=fit, rules=rules, progress=progress)
    paths = {**(files or {}), **write_selection(found, out)}
    if not found.molecules["selected"].any():
        raise BayespsfInputError(
            "no molecule passed the selection rules: nothing to analyse (see "
            f"{paths['selection.md']})"
        )
    counts, place = valid_rois(movie, found, fit)
    fitting = model.for_roi(fit)
    effective = {} if ess is None else {"ess": ess}  # else each sampler's default
    posteriors = sample_many(counts, fitting, seed=seed, executor=executor, workers=workers,
                             store=out / "posteriors", progress=progress,
                             check=gof_discrepancy,
                             method=method, **effective)  # fmt: skip
    frames = pd.concat(
        [place, posteriors.drop(columns="molecule"), _estimates(counts, fitting)], axis=1
    )
    frames["selected"] = True
    if z_calibration is not None:
        from bayespsf.axial.table import z_posteriors

        z_rows = z_posteriors(counts, fitting, z_calibration, seed=seed, z_range=z_range,
                              workers=workers, executor=executor, progress=progress,
                              **effective)  # fmt: skip
        frames = pd.concat([frames, z_rows], axis=1)
        provenance = {**(provenance or {}), "z calibration": z_calibration.record()}
    frame_z, per_molecule, overall = frame_consistency(frames, PARAMETERS)
    joint = joint_posteriors(counts, frames, fitting, seed=seed, workers=workers,
                             executor=executor, progress=progress, **effective)  # fmt: skip
    molecules = _per_molecule(found, per_molecule).merge(joint, on="molecule", how="left")
    scale = fitting.photoelectrons_per_photon  # Eq. sigma2dp3 is stated in detected photons
    detected = frames.assign(N_mean=frames["N_mean"] * scale, b_mean=frames["b_mean"] * scale,
                             photon_unit="photoelectrons")  # fmt: skip
    spread = width_spread(detected, fitting.pixel_size)
    windows = width_by_window(counts, fitting, frames["molecule"].to_numpy())
    mle = frames[[f"{p}_mle" for p in PARAMETER_NAMES]].where(frames["mle_converged"], axis=0)
    residuals = mean_residuals(counts, fitting, mle.to_numpy(float), frames["molecule"])
    _, height, width = movie.shape
    info = {
        "Width": int(width), "Height": int(height), "Frames": len(movie),
        "Pixelsize": float(fitting.pixel_size), "Generated by": "bayespsf analyze",
        "bayespsf": {"model": repr(fitting), "photon_unit": fitting.photon_unit_label,
                     "method": method, "roi": roi, "fit": fit, **(provenance or {})},
    }  # fmt: skip
    paths.update(write_all(localizations(frames, fitting.pixel_size), out, info))
    tables = {"molecules.csv": molecules, "consistency.csv": overall,
              "width_spread.csv": spread, "width_by_window.csv": windows}  # fmt: skip
    for name, table in tables.items():
        paths[name] = out / name
        table.to_csv(paths[name], index=False)
    paths.update(_figures(movie, found, frame_z, spread, frames["gof_p"], residuals, out))
    result = Analysis(found, frames, molecules, overall, spread, windows, paths)
    paths["report.md"] = out / "report.md"
    paths["report.md"].write_text(report_markdown(result, provenance))
    return result


def _figures(movie, found, frame_z, spread, gof_p, residuals, out: Path) -> dict[str, Path]:
    """The report's figures (``bayespsf.analysis.figures``), by file name."""
    from bayespsf.analysis import figures
    from bayespsf.movie.project import project

    made = [
        figures.detections(project(movie, "mean"), found.molecules, out / "detections.png"),
        figures.traces(found.frames, found.molecules, out / "traces.png"),
        figures.zscores(frame_z, PARAMETERS, out / "zscores.png"),
        figures.width_precision(spread, out / "width_precision.png"),
        figures.gof_pvalues(gof_p, out / "gof_p.png"),
        figures.residual_images(*residuals, out / "residuals.png"),
    ]
    return {path.name: path for path in made}


def _flag_table(frames: pd.DataFrame) -> pd.DataFrame:
    """The fraction of frames flagged at each level, beside its value when the model holds,
    and the binomial p-value of at least that many flags when it holds (``flag_excess_p``)."""
    p = frames["gof_p"].dropna()
    rows = []
    for alpha in (0.02, 0.1):
        rate = float((p <= alpha).mean()) if len(p) else np.nan
        rows.append({"alpha": alpha, "frames": len(p), "flagged": rate,
                     "binomial SE": np.sqrt(alpha * (1 - alpha) / max(len(p), 1)),
                     "expected when the model holds": alpha,
                     "p (this many flags or more)": flag_excess_p(p, alpha)})  # fmt: skip
    return pd.DataFrame(rows)


def _window_table(windows: pd.DataFrame) -> pd.DataFrame:
    """Mean s_x (and its SE) per molecule, one column per fitting window."""
    wide = windows.pivot(index="molecule", columns="window", values=["s_x", "s_x_se"])
    wide.columns = [f"{stat} ({w} x {w})" for stat, w in wide.columns]
    return wide.reset_index()


def _joint_table(molecules: pd.DataFrame) -> pd.DataFrame:
    """The report's joint-posterior columns of the analysed molecules."""
    columns = ["molecule", "joint_frames", "x0_joint_mean", "x0_joint_sd", "s_x_joint_mean",
               "s_x_joint_sd", "s_x_frame_sd", "s_y_joint_mean", "s_y_joint_sd", "joint_method",
               "joint_khat"]  # fmt: skip
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
    check = result.consistency[["parameter", "frames", "molecules", "z_sd", "z_sd_se",
                                "p_value", "p_two_sided", "coverage", "coverage_se",
                                "expected_coverage"]]  # fmt: skip
    spread_columns = [c for c in ("molecule", "frames", "N", "delta_s_lsq", "delta_s_mle",
                                  "delta_s_mean", "posterior_sd", "crlb", "eq_sigma2dp3")
                      if c in result.width_spread]  # fmt: skip
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
        "(`bayespsf.analysis.joint`: importance sampling from the joint Laplace approximation). "
        "`s_x_frame_sd` is the mean per-frame posterior SD: the joint SD is expected near "
        "`s_x_frame_sd / sqrt(joint_frames)`.",
        "",
        _joint_table(result.molecules).to_markdown(**fmt),
        "",
        "## Can the model have made each image?",
        "",
        "A parametric-bootstrap goodness-of-fit test of every frame's ROI "
        f"(`bayespsf.model_check`: {discrepancy} against 49 "
        "refitted replicates; column `gof_p`). Where the model holds, a fraction alpha of the "
        "frames has `gof_p <= alpha`; more flags mean ROIs it does not describe (two "
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


__all__ = ["Analysis", "analyze", "report_markdown", "valid_rois"]
