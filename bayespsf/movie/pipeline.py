"""From a movie to selected molecules: the stages of ``bayespsf.movie`` composed.

``find_molecules`` runs, in order: detection on a temporal projection (``detect_movie``), each
accepted candidate's trace over time with its bleaching steps and drift
(``molecules_over_time``), a maximum-likelihood fit of every frame's central ROI before
bleaching (``frame_fits``: widths for the selection rules), and the paper's selection rules
(``select``). Every stage's table is kept, so a user can stop at any of them and look.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.io import run_record
from bayespsf.model import Model
from bayespsf.movie._metadata import resolve_pixel_size
from bayespsf.movie.detect import detect_movie
from bayespsf.movie.extract import RoiStack, iter_rois, open_movie, photon_model
from bayespsf.movie.found import FoundMolecules
from bayespsf.movie.geometry import movie_geometry, periphery_background, periphery_masks
from bayespsf.movie.psf_width import resolve_psf_sd
from bayespsf.movie.read import Movie
from bayespsf.movie.select import Rules, select
from bayespsf.movie.tasks import fit_stacks, movie_runner
from bayespsf.movie.traces import molecules_over_time

if TYPE_CHECKING:
    from distributed import Client


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
    periphery: np.ndarray | None = None,
    executor: Executor | None = None,
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
    periphery : numpy.ndarray of bool, shape (molecules, roi, roi), optional
        Each molecule's periphery pixels for the background (``periphery_masks``); default
        the whole ring outside ``fit``.
    executor : concurrent.futures.Executor, optional
        Where the fits run (``bayespsf.parallel.task_runner``'s runner, a
        ``local_executor()`` or a Dask ``Client``'s executor); default this process. The
        results do not depend on it.

    Returns
    -------
    pandas.DataFrame
        One row per fitted (molecule, frame): ``molecule``, ``frame``, ``row0``, ``col0``,
        ``s_x``, ``s_y`` (nm), ``N_fit``, ``b_fit`` (detected photoelectrons),
        ``fit_converged``, ``peak`` (``I0``: the central ROI's brightest pixel above the
        periphery's mean, photons) and ``background_var`` (``sigma_b^2``, photons²).

    See Also
    --------
    bayespsf.fit_mle : the fit (its stack engine, in pieces of ``movie.tasks.PIECE`` ROIs).
    select : uses ``peak`` and ``background_var`` for the SNR rule.

    Notes
    -----
    ``I0`` and ``sigma_b^2`` make the paper's SNR ``I0 / sqrt(I0 + sigma_b^2)``, criterion
    3; ``sigma_b^2`` is the periphery's variance (its mean's squared SE times its pixels).
    """
    fitting = fit_model(model, fit)
    order = pd.Index(molecules["molecule"])
    cut = dict(roi=roi, fit=fit, frames=frames, block=block, progress=progress, desc="fits")

    def stacks():  # each block's ROIs before bleaching, with their centres to fit
        for stack in iter_rois(movie, molecules, **cut):
            keep = np.ones(len(stack), dtype=bool)
            if until is not None:
                end = stack.table["molecule"].map(until)
                keep = (end.isna() | (stack.table["frame"] < end)).to_numpy(bool)
            if keep.any():
                stack = RoiStack(stack.counts[keep], stack.table[keep].reset_index(drop=True), fit)
                yield stack, stack.central()

    parts = []
    with movie_runner(executor) as runner:
        for stack, fits in fit_stacks(stacks(), fitting, runner):
            ring = periphery_background(
                stack, model, periphery, order.get_indexer(stack.table["molecule"])
            )
            central = fitting.to_photons(stack.central())
            part = stack.table.copy()
            part["s_x"], part["s_y"] = fits["s_x"].to_numpy(), fits["s_y"].to_numpy()
            part["N_fit"], part["b_fit"] = fits["N"].to_numpy(), fits["b"].to_numpy()
            part["fit_converged"] = fits["converged"].to_numpy(bool)
            part["peak"] = central.max(axis=(-2, -1)) - ring["b"].to_numpy()
            part["background_var"] = ring["b_se"].to_numpy() ** 2 * ring["pixels"].to_numpy()
            parts.append(part)
    return pd.concat(parts, ignore_index=True)


def selection_run(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float | None,
    roi: int | None = None,
    fit: int | None = None,
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
        sd`` (or ``"estimated"``), ``roi`` and ``fit`` (pixels, or ``"from s0"`` where they
        follow an estimated SD), ``geometry`` (their source, ``resolve_geometry``), ``false
        positives``, ``projection``, ``rules``.

    Raises
    ------
    BayespsfInputError
        Even or inconsistent ``roi`` and ``fit``, or a movie file that cannot be read.
    """
    movie = open_movie(movie)
    roi, fit, source = movie_geometry(movie, model, roi, fit, s0)
    files = movie.path if isinstance(movie.path, tuple) else (movie.path,)
    camera = [repr(model)]
    if isinstance(model, Model):
        fitting = model.for_roi(model.roi if fit is None else fit)
        camera = [repr(fitting), fitting.clock_induced_charge, fitting.saturation]
    shape = [*movie.shape, str(movie.dtype), movie.metadata.get("channel")]
    return {
        "command": "detect",
        "movie": {"files": [run_record.file_fingerprint(f) for f in files], "shape": shape},
        "camera": camera,
        "psf sd": "estimated" if s0 is None else s0,
        "roi": "from s0" if roi is None else roi,
        "fit": "from s0" if fit is None else fit,
        "geometry": source,
        "false positives": false_positives,
        "projection": projection,
        "selection rules": asdict(Rules() if rules is None else rules),
    }


def find_molecules(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float | None = None,
    roi: int | None = None,
    fit: int | None = None,
    false_positives: float = 0.01,
    projection: str = "mean",
    rules: Rules | None = None,
    block: int = 64,
    progress: bool | None = None,
    executor: Executor | Client | str | None = None,
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
    roi, fit : int, optional
        Odd sides in pixels of the cut around each molecule and of its fitted centre; default
        from the spot's SD (``geometry_for_psf``: the paper's 25 and 15 at s0 = 120 nm on
        79 nm pixels). The cut's periphery outside ``fit``, less the pixels its neighbours'
        light reaches (``periphery_masks``), gives the background.
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
    executor : concurrent.futures.Executor, distributed.Client or str, optional
        Where the fits (the spot's SD, the widths) and the bleaching steps run, as
        ``sample_many``'s ``executor`` (a ``local_executor()``, a Dask ``Client`` or a
        scheduler's address); default this process. This process reads the movie, detects
        and traces; the results do not depend on where the rest runs.

    Returns
    -------
    FoundMolecules
        Every stage's table, photons in detected photoelectrons (``photon_unit``):

        - ``candidates``: ``detect``'s columns and ``photon_unit``;
        - ``molecules``: one row per candidate with ``molecule``, ``x``, ``y`` (camera
          pixels, picasso's convention), ``steps``, ``bleach_frame`` (nullable integer),
          ``frames_before``, ``multiple_steps``, ``photons_mean``, ``drift_x``,
          ``drift_x_se``, ``drift_y``, ``drift_y_se`` (nm per frame), ``rejected_by``,
          ``selected``, ``valid_frames`` and ``photon_unit``; candidates rejected at
          detection have only ``molecule``, ``x``, ``y``, ``selected`` (False) and
          ``rejected_by`` (``detection: edge`` or ``detection: neighbour``) filled;
        - ``frames``: one row per (molecule, frame) of the accepted candidates: the trace's
          ``photons``, ``photons_se``, ``photons_psf``, ``photons_psf_se``, ``b``, ``b_se``,
          ``x``, ``y``; the ROI's ``row0``,
          ``col0``; the fit's ``s_x``, ``s_y`` (nm), ``N_fit``, ``b_fit``,
          ``fit_converged``; ``peak`` (``I0``, photons) and ``background_var``
          (``sigma_b^2``, photons²); ``before_bleach``, ``rejected_by``, ``valid`` and
          ``photon_unit`` (fits only before the bleaching step: NaN after it);
        - ``report``: the selection report (``select``);
        - ``rules``: the rules applied; ``psf_width``: the SD used (given or estimated);
          ``geometry``: the sides used and their source.

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
    if "photon_window" not in rules.skip and len(movie) < rules.min_valid_frames:
        raise BayespsfInputError(
            f"the movie has {len(movie)} frame(s), fewer than the {rules.min_valid_frames} "
            "valid frames the photon_window rule needs (--min-valid-frames N, --skip-rule "
            "photon_window or --rules none on the command line; Rules(min_valid_frames=...) or "
            "skip=('photon_window',) in Python)"
        )
    with movie_runner(executor) as runner:
        sides = {} if fit is None else {"fit": fit}
        width = resolve_psf_sd(
            movie, model, s0, false_positives=false_positives, executor=runner, **sides
        )
        roi, fit, source = movie_geometry(movie, model, roi, fit, width.sd)
        if roi > min(movie.shape[1:]):
            raise BayespsfInputError(
                f"roi ({roi}) is larger than the movie's frames ({movie.shape[1]} x "
                f"{movie.shape[2]}): every candidate would lie too close to an edge (geometry "
                f"{source}; roi= or --roi states a smaller one)"
            )
        rules = rules.for_psf(width.sd)  # the width range follows the spot's SD
        options = dict(camera=model, projection=projection, false_positives=false_positives)
        candidates = detect_movie(movie, psf_sd=width.sd, roi=roi, fit=fit, **options)
        accepted = candidates[candidates["status"] == "accepted"].reset_index(drop=True)
        if accepted.empty:
            per_molecule = accepted[["molecule", "x", "y"]].assign(
                bleach_frame=pd.Series(dtype=float), selected=pd.Series(dtype=bool), rejected_by=""
            )
            frames = pd.DataFrame(columns=["molecule", "frame"])
            report = pd.DataFrame([{"rule": "no molecule accepted by detection"}])
        else:
            a = resolve_pixel_size(None, model, movie)
            kept = periphery_masks(
                accepted, candidates, s0=width.sd, pixel_size=a, roi=roi, fit=fit
            )
            cut = dict(roi=roi, fit=fit, block=block, progress=progress, periphery=kept)
            cut["executor"] = runner
            per_molecule, per_frame = molecules_over_time(
                movie, accepted, model, s0=width.sd, **cut
            )
            until = per_molecule.set_index("molecule")["bleach_frame"]
            fitted = frame_fits(movie, accepted, model, until=until, **cut)
            frames = per_frame.merge(
                fitted, on=["molecule", "frame"], how="left", suffixes=("", "_roi")
            )
            bleach = frames["molecule"].map(until)
            frames["before_bleach"] = (bleach.isna() | (frames["frame"] < bleach)).to_numpy(bool)
            per_molecule, frames, report = select(per_molecule, frames, rules)
    rejected = candidates[candidates["status"] != "accepted"]
    reason = "detection: " + rejected["status"].str.replace("rejected: ", "")
    others = rejected[["molecule", "x", "y"]].assign(selected=False, rejected_by=reason)
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
    geometry = {"roi": roi, "fit": fit, "source": source}
    return FoundMolecules(candidates, molecules, frames, report, rules, run, width, geometry)


__all__ = ["find_molecules", "fit_model", "frame_fits", "selection_run"]
