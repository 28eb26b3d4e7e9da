"""From a movie to selected molecules: the stages of ``bayespsf.movie`` composed (issue 13).

``find_molecules`` runs, in order: detection on a temporal projection (``detect_movie``), each
accepted candidate's trace over time with its bleaching steps and drift
(``molecules_over_time``), a maximum-likelihood fit of every frame's central ROI before
bleaching (``frame_fits``: widths for the selection rules), and the paper's selection rules
(``select``). Every stage's table is kept, so a user can stop at any of them and look.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.estimators import fit_mle
from bayespsf.model import Model
from bayespsf.movie.detect import detect_movie
from bayespsf.movie.extract import RoiStack, check_sizes, iter_rois, open_movie, photon_model
from bayespsf.movie.select import Rules, report_markdown, select
from bayespsf.movie.traces import molecules_over_time


@dataclass
class FoundMolecules:
    """What ``find_molecules`` found: every stage's table.

    Attributes
    ----------
    candidates : pandas.DataFrame
        ``detect_movie``'s table (accepted and rejected candidates).
    molecules : pandas.DataFrame
        One row per candidate: ``molecule``, ``x``, ``y`` (camera pixels, picasso's
        convention), ``bleach_frame`` (first frame without signal; empty if none),
        ``selected`` and ``rejected_by`` (the first rule that removed it, or
        ``detection: edge`` / ``detection: neighbour``; empty if selected), then the trace's
        and the selection's columns.
    frames : pandas.DataFrame
        One row per (molecule, frame) of accepted candidates: the trace (aperture photons,
        background, centroid), the frame's fit (``s_x``, ``s_y``, ``N_fit``, ``b_fit``,
        ``fit_converged``), ``peak``, ``background_var``, ``before_bleach``, ``valid`` and
        ``rejected_by``.
    report : pandas.DataFrame
        The selection report (``select``).
    rules : Rules
    """

    candidates: pd.DataFrame
    molecules: pd.DataFrame
    frames: pd.DataFrame
    report: pd.DataFrame
    rules: Rules

    def report_markdown(self) -> str:
        detected = self.candidates["status"].value_counts()
        counts = ", ".join(f"{k}: {v}" for k, v in detected.items()) or "none"
        return report_markdown(self.report, self.rules) + f"\nCandidates detected: {counts}.\n"


def fit_model(model: Model, fit: int) -> Model:
    """``model`` with a ``fit`` × ``fit`` ROI (same camera, pixel size, CIC and saturation;
    the prior's defaults for that geometry; N and b in detected photoelectrons, as every
    table of the movie path)."""
    return model.for_roi(fit, detected=True)


def frame_fits(movie, molecules, model: Model, *, roi=25, fit=15, frames=None, block=64,
               until=None, progress=None):  # fmt: skip
    """Per (molecule, frame): the maximum-likelihood fit of the central ``fit`` × ``fit`` ROI
    (``fit_mle``'s stack engine, one block of frames at a time), the peak photons above the
    background ``I0`` and the background variance ``sigma_b^2`` in photons from the ROI's
    periphery (the paper's SNR ``I0 / sqrt(I0 + sigma_b^2)``, criterion 3).

    ``until`` (molecule -> first frame without signal, or NA) limits the fits to the frames
    before each molecule's bleaching step: a frame without a spot has no width to measure.
    """
    fitting = fit_model(model, fit)
    ring_pixels = roi * roi - fit * fit
    parts = []
    for stack in iter_rois(movie, molecules, roi=roi, fit=fit, frames=frames, block=block,
                           progress=progress, desc="fits"):  # fmt: skip
        keep = np.ones(len(stack), dtype=bool)
        if until is not None:
            end = stack.table["molecule"].map(until)
            keep = (end.isna() | (stack.table["frame"] < end)).to_numpy(bool)
        if not keep.any():
            continue
        stack = RoiStack(stack.counts[keep], stack.table[keep].reset_index(drop=True), fit)
        fits = fit_mle(stack.central(), fitting, laplace=False, crlb=False)
        ring = stack.periphery_background(model)
        central = fitting.to_photons(stack.central())
        part = stack.table.copy()
        part["s_x"], part["s_y"] = fits["s_x"].to_numpy(), fits["s_y"].to_numpy()
        part["N_fit"], part["b_fit"] = fits["N"].to_numpy(), fits["b"].to_numpy()
        part["fit_converged"] = fits["converged"].to_numpy(bool)
        part["peak"] = central.max(axis=(-2, -1)) - ring["b"].to_numpy()
        part["background_var"] = ring["b_se"].to_numpy() ** 2 * ring_pixels
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


def find_molecules(
    movie,
    model: Model,
    *,
    s0: float,
    roi: int = 25,
    fit: int = 15,
    false_positives: float = 0.01,
    projection: str = "mean",
    rules: Rules | None = None,
    block: int = 64,
    progress: bool | None = None,
) -> FoundMolecules:
    """Detect, trace, fit and select the molecules of an immobile-molecule movie.

    Parameters
    ----------
    movie : Movie or path
    model : Model
        The camera (ADU to photons, its law) and pixel size; its ROI size is not used.
    s0 : float
        The spot's SD in nm (the detector's template and the traces' aperture).
    roi, fit : int
        The cut around each molecule and its fitted centre (the paper: 25 and 15).
    false_positives : float
        Expected false detections per projected image (``detect``).
    projection : {"mean", "median"}
    rules : Rules, optional
        The selection rules (default: the paper's numbers).
    block : int
        Frames read at a time.
    progress : bool, optional
        Progress bars of the traces and the fits on stderr (default: when it is a terminal).
    """
    movie = open_movie(movie)
    rules = Rules() if rules is None else rules
    check_sizes(roi, fit)
    if roi > min(movie.shape[1:]):
        raise BayespsfInputError(
            f"roi ({roi}) is larger than the movie's frames ({movie.shape[1]} x {movie.shape[2]}): "
            "every candidate would lie too close to an edge"
        )
    if "photon_window" not in rules.skip and len(movie) < rules.min_valid_frames:
        raise BayespsfInputError(
            f"the movie has {len(movie)} frame(s), fewer than the {rules.min_valid_frames} "
            "valid frames the photon_window rule needs (Rules(min_valid_frames=...) or "
            "skip=('photon_window',))"
        )
    candidates = detect_movie(movie, psf_sd=s0, camera=model, projection=projection,
                              false_positives=false_positives, roi=roi)  # fmt: skip
    accepted = candidates[candidates["status"] == "accepted"].reset_index(drop=True)
    if accepted.empty:
        per_molecule = pd.DataFrame(
            {
                "molecule": accepted["molecule"],
                "x": accepted["x"],
                "y": accepted["y"],
                "bleach_frame": pd.Series(dtype=float),
                "selected": pd.Series(dtype=bool),
                "rejected_by": "",
            }
        )
        frames = pd.DataFrame(columns=["molecule", "frame"])
        report = pd.DataFrame([{"rule": "no molecule accepted by detection"}])
    else:
        per_molecule, per_frame = molecules_over_time(movie, accepted, model, s0=s0, roi=roi,
                                                      fit=fit, block=block,
                                                      progress=progress)  # fmt: skip
        until = per_molecule.set_index("molecule")["bleach_frame"]
        fitted = frame_fits(movie, accepted, model, roi=roi, fit=fit, block=block, until=until,
                            progress=progress)  # fmt: skip
        frames = per_frame.merge(fitted, on=["molecule", "frame"], how="left",
                                 suffixes=("", "_roi"))  # fmt: skip
        bleach = frames["molecule"].map(until)
        frames["before_bleach"] = (bleach.isna() | (frames["frame"] < bleach)).to_numpy(bool)
        per_molecule, frames, report = select(per_molecule, frames, rules)
    rejected = candidates[candidates["status"] != "accepted"]
    others = pd.DataFrame({
        "molecule": rejected["molecule"].to_numpy(), "x": rejected["x"].to_numpy(),
        "y": rejected["y"].to_numpy(), "selected": False,
        "rejected_by": "detection: " + rejected["status"].str.replace("rejected: ", ""),
    })  # fmt: skip
    columns = list(dict.fromkeys([*per_molecule.columns, *others.columns]))
    parts = [t for t in (per_molecule, others) if len(t)]  # pandas warns on empty parts
    molecules = pd.concat(parts, ignore_index=True) if parts else per_molecule
    molecules = molecules.reindex(columns=columns)
    molecules["selected"] = molecules["selected"].astype(bool)
    molecules["bleach_frame"] = molecules["bleach_frame"].astype("Int64")
    molecules = molecules.sort_values("molecule", ignore_index=True)
    unit = photon_model(model).photon_unit_label
    for table in (candidates, molecules, frames):
        table["photon_unit"] = unit
    return FoundMolecules(candidates, molecules, frames, report, rules)


def _first_columns(table: pd.DataFrame, first) -> pd.DataFrame:
    return table[[*first, *(c for c in table.columns if c not in first)]]


def write(found: FoundMolecules, out) -> dict:
    """Write ``candidates.csv``, ``molecules.csv``, ``frames.csv`` and ``selection.md`` into
    the folder ``out``; returns their paths by name."""
    from pathlib import Path

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    first = ("molecule", "x", "y", "bleach_frame", "selected", "rejected_by")
    paths = {name: out / name for name in
             ("candidates.csv", "molecules.csv", "frames.csv", "selection.md")}  # fmt: skip
    found.candidates.to_csv(paths["candidates.csv"], index=False)
    _first_columns(found.molecules, first).to_csv(paths["molecules.csv"], index=False)
    found.frames.to_csv(paths["frames.csv"], index=False)
    paths["selection.md"].write_text(found.report_markdown())
    return paths


__all__ = ["FoundMolecules", "find_molecules", "fit_model", "frame_fits", "write"]
