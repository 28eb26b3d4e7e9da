"""``FoundMolecules``, what ``find_molecules`` gives: every stage's table, the selection
report, and the folder they are written to (``write``)."""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from bayespsf.io import run_record
from bayespsf.movie.psf_width import PsfWidth
from bayespsf.movie.select import Rules, report_markdown
from bayespsf.parallel.tables import write_csv


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
    geometry : dict
        The sides used, ``roi`` and ``fit`` (pixels), and their ``source``: ``given``, ``from
        s0`` (``geometry_for_psf``) or one of each.

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
    geometry: dict = field(default_factory=dict)

    def report_markdown(self) -> str:
        """The selection report as markdown (``select.report_markdown``), the number of
        candidates detected by status, the spot's SD (given or estimated) and the geometry.

        Returns
        -------
        str
            What ``selection.md`` holds.
        """
        detected = self.candidates["status"].value_counts()
        counts = ", ".join(f"{k}: {v}" for k, v in detected.items()) or "none"
        note = "" if self.psf_width is None else f"\nThe {self.psf_width.summary()}.\n"
        if self.geometry:
            roi, fit, source = (self.geometry[k] for k in ("roi", "fit", "source"))
            note += f"\nROI {roi} x {roi} pixels, fitted centre {fit} x {fit} ({source}).\n"
        text = report_markdown(self.report, self.rules)
        return text + f"\nCandidates detected: {counts}.\n{note}"


SELECTION_FILES = ("candidates.csv", "molecules.csv", "frames.csv", "selection.md")


def write_tables(
    found: FoundMolecules, out: str | Path, runner: cf.Executor | None = None
) -> dict[str, Path]:
    """Write ``SELECTION_FILES``, without a run record (``write`` and ``bayespsf.analyze``
    claim the folder first).

    Parameters
    ----------
    found : FoundMolecules
        From ``find_molecules``.
    out : str or Path
        The folder (made if missing).
    runner : concurrent.futures.Executor, optional
        Workers that format the tables' rows (``bayespsf.parallel.tables.write_csv``);
        default this process.

    Returns
    -------
    dict of str to Path
        The files' paths by name.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    first = ("molecule", "x", "y", "bleach_frame", "selected", "rejected_by")
    paths = {name: out / name for name in SELECTION_FILES}
    write_csv(found.candidates, paths["candidates.csv"], runner)
    columns = [*first, *(c for c in found.molecules.columns if c not in first)]
    write_csv(found.molecules[columns], paths["molecules.csv"], runner)
    write_csv(found.frames, paths["frames.csv"], runner)
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
        Kept in the record, not compared (the movie path); the spot's SD and the geometry
        used are added.

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
    width.update({"geometry": found.geometry} if found.geometry else {})
    copied = run_record.read_copies(copies)
    paths = run_record.claim_folder(
        out, run, SELECTION_FILES, force=force, copies=copied, about={**(about or {}), **width}
    )
    return {**paths, **write_tables(found, out)}


__all__ = ["SELECTION_FILES", "FoundMolecules", "write", "write_tables"]
