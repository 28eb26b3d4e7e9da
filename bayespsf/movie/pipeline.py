"""From a movie to selected molecules: the stages of ``bayespsf.movie`` composed.

``find_molecules`` runs, in order: detection on a temporal projection (``detect_movie``), each
accepted candidate's trace over time with its bleaching steps and drift
(``molecules_over_time``), a maximum-likelihood fit of every frame's central ROI before
bleaching (``frame_fits``: widths for the selection rules), and the paper's selection rules
(``select``). Every stage's table is kept, so a user can stop at any of them and look.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle
from bayespsf.io import run_record
from bayespsf.model import Model
from bayespsf.movie.detect import detect_movie
from bayespsf.movie.extract import RoiStack, check_sizes, iter_rois, open_movie, photon_model
from bayespsf.movie.psf_width import PsfWidth, resolve_psf_sd
from bayespsf.movie.read import Movie
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
        One row per candidate: ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention),
        ``bleach_frame`` (first frame without signal; empty if none), ``selected`` and
        ``rejected_by`` (the first rule that removed it, or ``detection: edge`` / ``detection:
        neighbour``; empty if selected), then the trace's and the selection's columns.
    frames : pandas.DataFrame
        One row per (molecule, frame) of accepted candidates: the trace (aperture photons,
        background, centroid), the frame's fit (``s_x``, ``s_y``, ``N_fit``, ``b_fit``,
        ``fit_converged``), ``peak``, ``background_var``, ``before_bleach``, ``valid`` and
        ``rejected_by``.
    report : pandas.DataFrame
        The selection report (``select``): one row per rule with ``rule``, ``molecules
        removed``, ``frames removed``, ``molecules left`` and ``frames left``.
    rules : Rules
        The selection rules applied.
    run : dict
        What identifies the run that found them (``selection_run``), for ``write``'s record.
    psf_width : PsfWidth or None
        The spot's SD used: given, or estimated with its error (``estimate_psf_sd``).

    See Also
    --------
    find_molecules : makes one.
    write : writes its tables and report to a folder.
    """

    candidates: pd.DataFrame
    molecules: pd.DataFrame
    frames: pd.DataFrame
    report: pd.DataFrame
    rules: Rules
    run: dict = field(default_factory=dict)
    psf_width: PsfWidth | None = None

    def report_markdown(self) -> str:
        """The selection report as markdown (``select.report_markdown``), the number of
        candidates detected by status and the spot's SD (given or estimated)."""
        detected = self.candidates["status"].value_counts()
        counts = ", ".join(f"{k}: {v}" for k, v in detected.items()) or "none"
        note = "" if self.psf_width is None else f"\nThe {self.psf_width.summary()}.\n"
        return (
            report_markdown(self.report, self.rules) + f"\nCandidates detected: {counts}.\n{note}"
        )


def fit_model(model: Model, fit: int) -> Model:
    """``model`` with a ``fit`` × ``fit`` ROI (same camera, pixel size, CIC and saturation;
    the prior's defaults for that geometry; N and b in detected photoelectrons, as every
    table of the movie path)."""
    return model.for_roi(fit, detected=True)


def frame_fits(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    model: Model,
    *,
    roi: int = 25,
    fit: int = 15,
    frames: slice | range | None = None,
    block: int = 64,
    until: pd.Series | None = None,
    progress: bool | None = None,
) -> pd.DataFrame:
    """Per (molecule, frame): the maximum-likelihood fit of the central ROI and its SNR terms.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU).
    molecules : pandas.DataFrame
        ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention), as ``cut_rois``.
    model : Model
        The camera and pixel size (its ROI size is replaced by ``fit``: ``fit_model``).
    roi, fit : int, default 25 and 15
        Odd sides in pixels of the cut and of its fitted centre.
    frames : slice or range, optional
        Consecutive frames (default all).
    block : int, default 64
        Frames read at a time.
    until : pandas.Series, optional
        Molecule id -> first frame without signal (or NA): fits only the frames before each
        molecule's bleaching step (a frame without a spot has no width to measure).
    progress : bool, optional
        A progress bar on stderr (default: when it is a terminal).

    Returns
    -------
    pandas.DataFrame
        One row per fitted (molecule, frame): ``molecule``, ``frame``, ``row0``, ``col0``,
        ``s_x``, ``s_y`` (nm), ``N_fit``, ``b_fit`` (detected photoelectrons),
        ``fit_converged``, ``peak`` (``I0``: the central ROI's brightest pixel above the
        periphery's mean, photons) and ``background_var`` (``sigma_b^2``, photons²).

    See Also
    --------
    bayespsf.fit_mle : the fit (its stack engine, one block of frames at a time).
    select : uses ``peak`` and ``background_var`` for the SNR rule.

    Notes
    -----
    ``I0`` and ``sigma_b^2`` make the paper's SNR ``I0 / sqrt(I0 + sigma_b^2)``, criterion
    3; ``sigma_b^2`` is the periphery's variance (its mean's squared SE times its pixels).
    """
    fitting = fit_model(model, fit)
    ring_pixels = roi * roi - fit * fit
    parts = []
    for stack in iter_rois(
        movie,
        molecules,
        roi=roi,
        fit=fit,
        frames=frames,
        block=block,
        progress=progress,
        desc="fits",
    ):
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


def selection_run(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float | None,
    roi: int = 25,
    fit: int = 15,
    false_positives: float = 0.01,
    projection: str = "mean",
    rules: Rules | None = None,
) -> dict:
    """What identifies a ``find_molecules`` run (``write`` records it in its folder,
    ``bayespsf.io.run_record``, as ``bayespsf.analyze`` its own): movie, camera, settings.

    Parameters
    ----------
    movie, model, s0, roi, fit, false_positives, projection, rules
        As ``find_molecules``.

    Returns
    -------
    dict
        ``command`` (``"detect"``), ``movie`` (per file its ``file_fingerprint``, then the
        movie's shape, data type and channel; not its path: a moved movie is the same),
        ``camera`` (the model for ``fit`` x ``fit`` ROIs, its CIC and saturation), ``psf
        sd`` (or ``"estimated"``), ``roi``, ``fit``, ``false positives``, ``projection``, ``rules``.

    Raises
    ------
    BayespsfInputError
        Even or inconsistent ``roi`` and ``fit``, or a movie file that cannot be read.
    """
    movie = open_movie(movie)
    check_sizes(roi, fit)
    files = movie.path if isinstance(movie.path, tuple) else (movie.path,)
    camera = [repr(model)]
    if isinstance(model, Model):
        fitting = model.for_roi(fit)
        camera = [repr(fitting), fitting.clock_induced_charge, fitting.saturation]
    shape = [*movie.shape, str(movie.dtype), movie.metadata.get("channel")]
    return {
        "command": "detect",
        "movie": {"files": [run_record.file_fingerprint(f) for f in files], "shape": shape},
        "camera": camera,
        "psf sd": "estimated" if s0 is None else s0,
        "roi": roi,
        "fit": fit,
        "false positives": false_positives,
        "projection": projection,
        "selection rules": asdict(Rules() if rules is None else rules),
    }


def find_molecules(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float | None = None,
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
        The movie in counts (ADU), from ``read_movie`` or a path it opens.
    model : Model
        The camera (ADU to photons, its law) and pixel size; its ROI size is not used.
    s0 : float, optional
        The spot's SD in nm (detector's template, traces' aperture); default estimated from
        the movie (``bayespsf.movie.estimate_psf_sd``, with ``model`` and ``fit``).
    roi, fit : int, default 25 and 15
        Odd sides in pixels of the cut around each molecule and of its fitted centre (the
        paper's 25 and 15); the cut's periphery outside ``fit`` gives the background.
    false_positives : float, default 0.01
        Expected false detections per projected image (``detect``).
    projection : {"mean", "median"}, default "mean"
        The temporal projection detection runs on.
    rules : Rules, optional
        The selection rules (default: the paper's numbers).
    block : int, default 64
        Frames read at a time.
    progress : bool, optional
        Progress bars of the traces and the fits on stderr (default: when it is a terminal).

    Returns
    -------
    FoundMolecules
        Every stage's table, photons in detected photoelectrons (``photon_unit``):

        - ``candidates``: ``detect``'s columns (``molecule``, ``x``, ``y``, ``row``, ``col``,
          ``score``, ``amplitude``, ``background``, ``status``, ``threshold``,
          ``noise_var``, ``noise_source``) and ``photon_unit``;
        - ``molecules``: one row per candidate with ``molecule``, ``x``, ``y`` (camera
          pixels, picasso's convention), ``steps``, ``bleach_frame`` (nullable integer),
          ``frames_before``, ``multiple_steps``, ``photons_mean``, ``drift_x``,
          ``drift_x_se``, ``drift_y``, ``drift_y_se`` (nm per frame), ``rejected_by``,
          ``selected``, ``valid_frames`` and ``photon_unit``; candidates rejected at
          detection have only ``molecule``, ``x``, ``y``, ``selected`` (False) and
          ``rejected_by`` (``detection: edge`` or ``detection: neighbour``) filled;
        - ``frames``: one row per (molecule, frame) of the accepted candidates: the trace's
          ``photons``, ``photons_se``, ``b``, ``b_se``, ``x``, ``y``; the ROI's ``row0``,
          ``col0``; the fit's ``s_x``, ``s_y`` (nm), ``N_fit``, ``b_fit``,
          ``fit_converged``; ``peak`` (``I0``, photons) and ``background_var``
          (``sigma_b^2``, photons²); ``before_bleach``, ``rejected_by``, ``valid`` and
          ``photon_unit`` (fits only before the bleaching step: NaN after it);
        - ``report``: the selection report (``select``);
        - ``rules``: the rules applied; ``psf_width``: the SD used (given or estimated).

    Raises
    ------
    BayespsfInputError
        Even or inconsistent ``roi`` and ``fit``, a ``roi`` larger than the frames, a movie
        shorter than the ``photon_window`` rule's ``min_valid_frames`` (unless skipped), or
        any error of the stages.

    See Also
    --------
    detect_movie : stage 1, detection on a temporal projection.
    molecules_over_time : stage 2, traces, bleaching steps and drift.
    frame_fits : stage 3, per-frame maximum-likelihood widths.
    select : stage 4, the paper's selection rules.
    write : the tables and the report as files.
    bayespsf.analyze : posteriors of the selected molecules' frames.

    Notes
    -----
    The stages run in the order of the module docstring; the selection rules are those of
    DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), "Data acquisition and selection".

    Examples
    --------
    A small simulated movie (3 molecules, 40 frames); the selection rules' 75 valid frames are
    relaxed to 20 for so short a movie:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> from bayespsf.movie import Rules
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 40, "height": 64, "width": 64, "molecules": 3, "dark_frames": 0,
    ...            "two_fluorophores": 0.0, "moving": 0.0}
    ... )
    >>> made = bayespsf.simulate_movie(scene, seed=2, out=Path(tempfile.mkdtemp()) / "m")
    >>> found = bayespsf.find_molecules(
    ...     made.files["movie"], bayespsf.Model.from_scene(scene), s0=120.0,
    ...     rules=Rules(min_valid_frames=20), progress=False,
    ... )
    >>> found.molecules[["molecule", "bleach_frame", "selected", "rejected_by"]]
       molecule  bleach_frame  selected  rejected_by
    0         0          <NA>     False  single_step
    1         1          <NA>     False  single_step
    2         2            32      True
    """
    movie = open_movie(movie)
    rules = Rules() if rules is None else rules
    settings = dict(s0=s0, roi=roi, fit=fit, false_positives=false_positives, rules=rules)
    run = selection_run(movie, model, **settings, projection=projection)  # checks roi, fit
    if roi > min(movie.shape[1:]):
        raise BayespsfInputError(
            f"roi ({roi}) is larger than the movie's frames ({movie.shape[1]} x {movie.shape[2]}): "
            "every candidate would lie too close to an edge"
        )
    if "photon_window" not in rules.skip and len(movie) < rules.min_valid_frames:
        raise BayespsfInputError(
            f"the movie has {len(movie)} frame(s), fewer than the {rules.min_valid_frames} "
            "valid frames the photon_window rule needs (--min-valid-frames N, --skip-rule "
            "photon_window or --rules none on the command line; Rules(min_valid_frames=...) or "
            "skip=('photon_window',) in Python)"
        )
    width = resolve_psf_sd(movie, model, s0, fit=fit, false_positives=false_positives)
    rules = rules.for_psf(width.sd)  # the width range follows the spot's SD
    candidates = detect_movie(
        movie,
        psf_sd=width.sd,
        camera=model,
        projection=projection,
        false_positives=false_positives,
        roi=roi,
    )
    accepted = candidates[candidates["status"] == "accepted"].reset_index(drop=True)
    if accepted.empty:
        per_molecule = pd.DataFrame(
            {
                "molecule": accepted["molecule"],
                "x": accepted["x"],
                "y": accepted["y"],
                "bleach_frame": pd.Series(dtype=float),
                "selected": pd.Series(dtype=bool), "rejected_by": ""}
        )  # fmt: skip
        frames = pd.DataFrame(columns=["molecule", "frame"])
        report = pd.DataFrame([{"rule": "no molecule accepted by detection"}])
    else:
        per_molecule, per_frame = molecules_over_time(
            movie, accepted, model, s0=width.sd, roi=roi, fit=fit, block=block, progress=progress
        )
        until = per_molecule.set_index("molecule")["bleach_frame"]
        fitted = frame_fits(
            movie, accepted, model, roi=roi, fit=fit, block=block, until=until, progress=progress
        )
        frames = per_frame.merge(
            fitted, on=["molecule", "frame"], how="left", suffixes=("", "_roi")
        )
        bleach = frames["molecule"].map(until)
        frames["before_bleach"] = (bleach.isna() | (frames["frame"] < bleach)).to_numpy(bool)
        per_molecule, frames, report = select(per_molecule, frames, rules)
    rejected = candidates[candidates["status"] != "accepted"]
    others = pd.DataFrame(
        {
            "molecule": rejected["molecule"].to_numpy(),
            "x": rejected["x"].to_numpy(),
            "y": rejected["y"].to_numpy(),
            "selected": False,
            "rejected_by": "detection: " + rejected["status"].str.replace("rejected: ", ""),
        }
    )
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
    return FoundMolecules(candidates, molecules, frames, report, rules, run, width)


SELECTION_FILES = ("candidates.csv", "molecules.csv", "frames.csv", "selection.md")


def write_tables(found: FoundMolecules, out: str | Path) -> dict[str, Path]:
    """Write ``SELECTION_FILES``, without a run record (``write`` and ``bayespsf.analyze``
    claim the folder first).

    Parameters
    ----------
    found : FoundMolecules
        From ``find_molecules``.
    out : str or Path
        The folder (made if missing).

    Returns
    -------
    dict of str to Path
        The files' paths by name.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    first = ("molecule", "x", "y", "bleach_frame", "selected", "rejected_by")
    paths = {name: out / name for name in SELECTION_FILES}
    found.candidates.to_csv(paths["candidates.csv"], index=False)
    columns = [*first, *(c for c in found.molecules.columns if c not in first)]
    found.molecules[columns].to_csv(paths["molecules.csv"], index=False)
    found.frames.to_csv(paths["frames.csv"], index=False)
    paths["selection.md"].write_text(found.report_markdown())
    return paths


def write(
    found: FoundMolecules,
    out: str | Path,
    *,
    force: bool = False,
    copies: Mapping[str, str | Path] | None = None,
    about: Mapping | None = None,
) -> dict[str, Path]:
    """Write ``candidates.csv``, ``molecules.csv``, ``frames.csv``, ``selection.md`` and the
    run record ``run.json``, refusing a folder that holds another run's results.

    Parameters
    ----------
    found : FoundMolecules
        From ``find_molecules``.
    out : str or Path
        The folder (made if missing).
    force : bool, default False
        Replace another run's results in ``out``: the files this function writes and those
        the folder's record lists are removed first (nothing else in the folder).
    copies : mapping of str to path, optional
        Files to copy verbatim into ``out``, by their name there (the command's camera file,
        as ``camera.toml``); their bytes are part of the run's record.
    about : mapping, optional
        Kept in the record, not compared (the movie path); the spot's SD used is added.

    Returns
    -------
    dict of str to Path
        The files' paths by name (``run.json`` and ``copies`` included).

    Raises
    ------
    BayespsfInputError
        ``out`` is or lies under a file, a file of ``copies`` cannot be read, or
        (``RunConflict``, naming what differs) ``out`` holds another run's results: its
        record is not ``found.run`` (``selection_run``; a hash of the tables when empty).
    """
    tables = "".join(t.to_csv() for t in (found.candidates, found.molecules, found.frames))
    run = found.run or {"command": "detect", "tables": run_record.bytes_digest(tables.encode())}
    width = {} if found.psf_width is None else {"psf sd": found.psf_width.record()}  # a result
    copied = run_record.read_copies(copies)
    paths = run_record.claim_folder(
        out, run, SELECTION_FILES, force=force, copies=copied, about={**(about or {}), **width}
    )
    return {**paths, **write_tables(found, out)}


__all__ = [
    "SELECTION_FILES",
    "FoundMolecules",
    "find_molecules",
    "fit_model",
    "frame_fits",
    "selection_run",
    "write",
    "write_tables",
]
