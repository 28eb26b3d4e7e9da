"""From a movie to per-molecule results: ``analyze``, the library side of ``bayespsf analyze``.

The stages, in order:

1. ``bayespsf.movie.find_molecules``: detection, traces, bleaching steps and the paper's
   selection rules (in detected photoelectrons);
2. the central ``fit`` x ``fit`` ROI of every valid frame of every selected molecule;
3. a posterior per ROI (``sample_many``: local processes or a Dask cluster; its store is
   ``OUT/posteriors``, so a rerun with the same ``OUT`` continues and a killed run loses no
   finished ROI), the MLE with its Cramér-Rao bound (``fit_mle``) and the paper's least squares
   (``fit_lsq``), in the camera file's photon unit, and a bootstrap goodness-of-fit p-value
   per ROI (``bayespsf.inference.gof``, run by ``sample_many``'s ``check`` beside each
   posterior and stored with it);
3b. per selected molecule, the joint posterior of its frames (``bayespsf.inference.joint``:
   one position and width shared by the frames, N and b per frame);
4. the tables and files: ``locs.hdf5`` + ``locs.yaml`` (picasso), ``locs.csv``
   (ThunderSTORM), ``locs.parquet`` (every column), ``molecules.csv`` (the selection outcome
   and, per selected molecule, its joint posterior and, per parameter, the calibration check
   without ground truth), ``consistency.csv`` (that check over all molecules),
   ``width_spread.csv`` (the paper's experimental Delta s against N), ``width_by_window.csv``
   (``bayespsf.analysis.misfit``), the figures and ``report.md`` (``bayespsf.analysis.report``).
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf.analysis.consistency import PARAMETERS, frame_consistency
from bayespsf.analysis.localizations import localizations, locs_info
from bayespsf.analysis.misfit import mean_residuals
from bayespsf.analysis.molecule_tasks import send_estimates, send_figures
from bayespsf.analysis.report import report_markdown
from bayespsf.analysis.width_spread import width_spread
from bayespsf.axial import check_calibration, check_z_range
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.backends import check_backend
from bayespsf.inference.gof import check_discrepancy
from bayespsf.inference.settings import check_settings
from bayespsf.io import write_locs
from bayespsf.io.run_record import check_folder, claim_folder, read_copies
from bayespsf.model import Model
from bayespsf.movie import FoundMolecules, Movie, Rules, find_molecules, iter_rois, project
from bayespsf.movie.extract import open_movie
from bayespsf.movie.found import SELECTION_FILES, write_tables
from bayespsf.movie.pipeline import selection_run
from bayespsf.parallel import joint_posteriors, sample_many, task_runner
from bayespsf.psf import PARAMETER_NAMES, DefocusCalibration

if TYPE_CHECKING:
    from distributed import Client


#: What ``analyze`` writes into its folder (with ``run.json`` and the files it copies).
ANALYSIS_FILES = (
    *SELECTION_FILES,
    *("locs.hdf5", "locs.yaml", "locs.csv", "locs.parquet", "molecules.csv", "report.md"),
    *("consistency.csv", "width_spread.csv", "width_by_window.csv", "posteriors"),
    *("detections.png", "traces.png", "zscores.png", "width_precision.png", "gof_p.png"),
    "residuals.png",
)


@dataclass
class Analysis:
    """What ``analyze`` made: its tables, and the files it wrote (``paths``, by name).

    Attributes
    ----------
    found : FoundMolecules
        ``find_molecules``' tables: candidates, molecules, frames and the selection report.
    frames : pandas.DataFrame
        One row per analysed (molecule, frame): posterior, MLE, LSQ (``analyze``'s Returns
        lists the columns).
    molecules : pandas.DataFrame
        One row per candidate: the selection outcome and, per analysed molecule, the
        calibration check and its joint posterior over its frames.
    consistency : pandas.DataFrame
        The calibration check without ground truth over all molecules, one row per parameter
        (``frame_consistency``'s ``overall``).
    width_spread : pandas.DataFrame
        The paper's experimental Delta s against N, one row per molecule (``width_spread``).
    width_by_window : pandas.DataFrame
        The mean widths when the central w x w pixels are fitted (``width_by_window``).
    paths : dict of str to Path
        Every file in the output folder, by name.

    See Also
    --------
    analyze : makes one.
    """

    found: FoundMolecules
    frames: pd.DataFrame  # one row per analysed (molecule, frame): posterior, MLE, LSQ
    molecules: pd.DataFrame
    consistency: pd.DataFrame
    width_spread: pd.DataFrame
    width_by_window: pd.DataFrame  # the mean widths when the central w x w pixels are fitted
    paths: dict[str, Path] = field(default_factory=dict)


def valid_rois(
    movie: Movie | str | Path, found: FoundMolecules, fit: int, block: int = 64
) -> tuple[np.ndarray, pd.DataFrame]:
    """The ``fit`` x ``fit`` ROIs of the valid frames of the selected molecules.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU).
    found : FoundMolecules
        ``find_molecules``' result (its ``frames``' ``valid`` column).
    fit : int
        Odd side of the ROIs in pixels.
    block : int, default 64
        Frames read at a time.

    Returns
    -------
    counts : numpy.ndarray, shape (n, fit, fit)
        The ROIs in ADU, float64, in ``iter_rois``' order: by block of ``block`` frames,
        then by molecule, then frame.
    table : pandas.DataFrame
        One row per ROI: ``molecule``, ``frame``, ``row``, ``col`` (the movie pixel at the
        ROI's centre).
    """
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


def _check_sampler(method: str, ess, seed: int, max_seconds) -> dict:
    """The posterior's settings (``check_settings``), each named before the detection; the
    budget as ``sample_many`` takes it (none where not given), as a plain float."""
    given = {} if ess is None else {"ess": ess}
    checked = check_settings(method=method, seed=seed, max_seconds=max_seconds, **given)
    return {} if max_seconds is None else {"max_seconds": checked.max_seconds}


def _per_molecule(found: FoundMolecules, molecules: pd.DataFrame) -> pd.DataFrame:
    """The selection outcome of every candidate; per analysed molecule and parameter the
    combined (inverse-variance) estimate, its SE and the check's chi-square p-value, z-score SD
    and coverage; and the molecule's joint posterior (``joint``)."""
    values = ["combined", "combined_se", "p_value", "p_two_sided", "z_sd", "coverage"]
    wide = molecules.pivot(index="molecule", columns="parameter", values=values)
    wide.columns = [f"{p}_{stat}" for stat, p in wide.columns]
    return found.molecules.merge(wide.reset_index(), on="molecule", how="left")


def analyze(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float | None = None,
    out: str | Path,
    roi: int | None = None,
    fit: int | None = None,
    rules: Rules | None = None,
    method: str = "auto",
    backend: str = "numpy",
    ess: float | None = None,
    max_seconds: float | None = None,
    seed: int = 0,
    workers: int | None = None,
    executor: Executor | Client | str | None = None,
    progress: bool | None = None,
    provenance: dict | None = None,
    z_calibration: DefocusCalibration | None = None,
    z_range: tuple[float, float] = (-800.0, 800.0),
    files: dict[str, Path] | None = None,
    gof_discrepancy: str = "likelihood",
    force: bool = False,
    copies: dict[str, str | Path] | None = None,
) -> Analysis:
    """Analyse a movie of immobile molecules end to end: selection, posteriors, checks, files.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU), from ``read_movie`` or a path it opens.
    model : Model
        A camera file's model: camera law (ADU to photons), pixel size, prior and photon
        unit. Its ROI size is not used: the posteriors use ``model.for_roi(fit)``.
    s0 : float, optional
        The spot's SD in nm: the detector's template and the traces' aperture; default
        estimated from the movie (``find_molecules``); the report and the record state it.
    out : str or Path
        The folder every file goes into (made if missing), with the run record ``run.json``
        (``bayespsf.io.run_record``: the movie's fingerprint, the camera, every setting
        that changes the results, ``copies``). The posteriors' store is ``out/posteriors``:
        a rerun of the same run continues, and a killed run loses no finished ROI; a folder
        that holds another run's results is refused before anything is computed.
    roi : int, optional
        Odd side in pixels of the cut around each molecule for detection, traces and the
        selection's fits (its periphery gives the background); default from the spot's SD
        (``bayespsf.movie.geometry_for_psf``: the paper's 25 at s0 = 120 nm, 79 nm pixels).
    fit : int, optional
        Odd side in pixels of the central ROI whose posterior, MLE and least squares are
        computed; default from the spot's SD (the paper's 15 there).
    rules : Rules, optional
        The selection rules (default: the paper's numbers).
    method : {"auto", "laplace", "importance", "mcmc"}, default "auto"
        The per-ROI posterior's sampler (``sample_many``): ``"auto"`` the batched Laplace
        where its pilot passes, else importance sampling, else an emcee chain.
    backend : {"numpy", "jax"}, default "numpy"
        Where the batched sampler runs (``sample_many``'s ``backend``; ``"jax"``: a GPU).
    ess : float, optional
        Effective sample size of every posterior (per ROI, per molecule's joint posterior
        and, with ``z_calibration``, of z); default each sampler's own.
    max_seconds : float, optional
        Wall-clock budget of each ROI's chain, for the ROIs the batched engine leaves to it
        (``sample_many``); one that exhausts it is reported ``not converged``. Default: none.
        The joint posteriors and those of z are not budgeted.
    seed : int, default 0
        ROI ``i`` is sampled with ``molecule_seed(seed, i)`` (ROIs in the order of
        ``frames``), molecule ``m``'s joint posterior with ``molecule_seed(seed, m)``: the
        results do not depend on the number of workers.
    workers : int, optional
        Local processes when ``executor`` is None (default: all cores; 1 runs in this
        process), made once for the run.
    executor : concurrent.futures.Executor, distributed.Client or str, optional
        Where the work runs: an executor, a Dask ``Client`` or a scheduler address such as
        ``"tcp://10.0.0.5:8786"`` (not together with ``workers``). The workers fit the spot's
        SD and the selection's widths, find the bleaching steps, sample the posteriors with
        each frame's MLE, least squares and widths by window beside them, the joint
        posteriors and the figures; this process reads the movie, detects, traces and
        writes the files (``bayespsf.analysis.molecule_tasks``).
    progress : bool, optional
        Progress bars on stderr (default: when stderr is a terminal).
    provenance : dict, optional
        What made the run (the camera file's text, the command), recorded in ``locs.yaml``
        and, where a value has no line break, in the report. The run adds the
        goodness-of-fit discrepancy (when not the default) and the z calibration (when
        given).
    z_calibration : DefocusCalibration, optional
        Defocus curves (``bayespsf.axial.calibrate``): every frame also gets its z posterior
        (``bayespsf.axial.z_posteriors``), whose summary goes into the localisation tables
        and whose calibration into ``locs.yaml``.
    z_range : (float, float), default (-800.0, 800.0)
        With ``z_calibration``: the support ``(low, high)`` of z's uniform prior, nm.
    files : dict of str to Path, optional
        Files the caller put into ``out`` (the camera file), by name: listed in the report
        beside the run's own, and in ``paths``.
    gof_discrepancy : {"likelihood", "pearson"}, default "likelihood"
        The goodness-of-fit test's discrepancy (``bayespsf.inference.gof.DISCREPANCIES``;
        ``"pearson"`` is calibrated at a background of a few photons per pixel, where the
        default is conservative).
    force : bool, default False
        Replace another run's results in ``out``: the files this run writes
        (``ANALYSIS_FILES``), ``posteriors/`` and the files the folder's record lists are
        removed before writing (nothing else in the folder); the same run starts afresh.
    copies : dict of str to path, optional
        Files to copy verbatim into ``out`` by their name there (the command's camera file,
        as ``camera.toml``): part of the run's record, listed with ``files``.

    Returns
    -------
    Analysis
        The tables, photons in the model's photon unit (``photon_unit``):

        - ``frames``: one row per analysed (molecule, frame): ``molecule``, ``frame``,
          ``row``, ``col`` (the movie pixel at the ROI's centre); ``sample_many``'s summary
          (``seed``, ``converged``, ``status``, ``message``, ``method``, ``why``, ``steps``,
          ``draws``, ``acceptance``, ``seconds``; per parameter ``<p>`` of ``x0 y0 s_x s_y N
          b`` ``<p>_mean``, ``<p>_sd``, the quantiles ``<p>_q0025`` to ``<p>_q0975``,
          ``<p>_tau``, ``<p>_ess``; ``gof_p``, ``gof_discrepancy``, ``gof_replicates``,
          ``photon_unit``); the MLE ``<p>_mle`` with its Cramér-Rao bound ``crlb_<p>`` and
          the paper's least squares ``<p>_lsq`` (NaN where it did not converge),
          ``mle_converged``, ``mle_status``, ``mle_message``; ``selected``; with
          ``z_calibration`` ``z_mean``, ``z_sd``, ``z_q0025``, ``z_q0975`` (nm), ``z_khat``,
          ``z_converged``, ``z_why`` (and ``z_above_plane`` on a symmetric curve). x0 and y0
          are nm from the ROI's centre.
        - ``molecules``: ``found.molecules``' columns; per parameter ``<p>`` of ``x0 y0 s_x
          s_y`` the check's ``<p>_combined``, ``<p>_combined_se``, ``<p>_p_value``,
          ``<p>_p_two_sided``, ``<p>_z_sd``, ``<p>_coverage``; and the joint posterior's
          columns (``joint_posteriors``: ``<p>_frame_sd``, ``<p>_joint_mean``,
          ``<p>_joint_sd``, its quantiles and ``<p>_joint_mle``, ``joint_frames``,
          ``joint_method``, ``joint_khat``, ...). NaN for molecules not analysed.
        - ``consistency``: per parameter ``parameter``, ``frames``, ``molecules``,
          ``z_sd``, ``z_sd_se``, ``chi2``, ``dof``, ``p_value``, ``p_two_sided``,
          ``coverage``, ``coverage_se``, ``expected_coverage``.
        - ``width_spread``: ``width_spread``'s columns for s_x, in detected photoelectrons.
        - ``width_by_window``: ``molecule``, ``window``, ``frames``, ``s_x``, ``s_x_se``,
          ``s_y``, ``s_y_se`` for windows of 7, 11 and 15 pixels (those within ``fit``).
        - ``paths``: the files written into ``out``, by name: ``candidates.csv``,
          ``molecules.csv``, ``frames.csv``, ``selection.md`` (the selection), ``locs.hdf5``
          and ``locs.yaml`` (picasso), ``locs.csv`` (ThunderSTORM), ``locs.parquet``
          (``bayespsf.analysis.localizations``' table), ``consistency.csv``,
          ``width_spread.csv``, ``width_by_window.csv``, the figures ``detections.png``,
          ``traces.png``, ``zscores.png``, ``width_precision.png``, ``gof_p.png``,
          ``residuals.png`` and ``report.md``, with ``files``.

    Raises
    ------
    BayespsfInputError
        ``out`` is or lies under a file; ``out`` holds another run's results
        (``bayespsf.io.run_record.RunConflict``, naming what differs); an unknown
        ``gof_discrepancy``; no molecule passing the selection rules (naming
        ``selection.md``), or any error of the stages (``find_molecules``, ``sample_many``:
        sampler options, executor; ``z_posteriors``).

    See Also
    --------
    find_molecules : stage 1, the selection alone.
    bayespsf.sample_many : the per-ROI posteriors.
    bayespsf.parallel.joint_posteriors : each molecule's joint posterior over its frames.
    frame_consistency : the calibration check without ground truth.
    width_spread : the paper's experimental width precision.
    localizations : the localisation table.

    Notes
    -----
    The stages, in order (module docstring): the selection (``find_molecules``, in detected
    photoelectrons); the central ``fit`` x ``fit`` ROI of every valid frame of every selected
    molecule; a posterior per ROI with its bootstrap goodness-of-fit p-value, the MLE with its
    Cramér-Rao bound and the paper's least squares, in the camera file's photon unit; per
    selected molecule the joint posterior of its frames (one position and width, N and b per
    frame); then the tables, figures and report. Delta s is compared with Eq. sigma2dp3 of
    DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), which is stated in detected photons.

    Examples
    --------
    A 20-frame simulated movie of one molecule that bleaches; the rules' 75 valid frames are
    relaxed to 8 for so short a movie:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> from bayespsf.movie import Rules
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 20, "height": 48, "width": 48, "molecules": 1, "dark_frames": 0,
    ...            "bleach_mean": 12.0, "two_fluorophores": 0.0, "moving": 0.0}
    ... )
    >>> folder = Path(tempfile.mkdtemp())
    >>> made = bayespsf.simulate_movie(scene, seed=0, out=folder / "m")
    >>> result = bayespsf.analyze(
    ...     made.files["movie"], bayespsf.Model.from_scene(scene), s0=120.0,
    ...     out=folder / "out", rules=Rules(min_valid_frames=8), workers=1, progress=False,
    ... )
    >>> result.found.molecules[["molecule", "selected", "valid_frames"]]
       molecule  selected  valid_frames
    0         0      True            15
    >>> result.frames["status"].value_counts().to_dict()
    {'converged': 15}
    >>> result.consistency[["parameter", "frames", "molecules"]]
      parameter  frames  molecules
    0        x0      15          1
    1        y0      15          1
    2       s_x      15          1
    3       s_y      15          1
    >>> (folder / "out" / "locs.hdf5").exists()
    True
    """
    check_discrepancy("gof_discrepancy", gof_discrepancy)
    check_backend(backend)  # a backend that cannot run is refused before any work
    budget = _check_sampler(method, ess, seed, max_seconds)
    if gof_discrepancy != "likelihood":
        provenance = {**(provenance or {}), "goodness-of-fit discrepancy": gof_discrepancy}
    movie, out, copied = open_movie(movie), Path(out), read_copies(copies)
    run = {
        **selection_run(movie, model, s0=s0, roi=roi, fit=fit, rules=rules),
        "command": "analyze",
    }
    run.update(method=method, ess=ess, seed=seed, **{"model check": gof_discrepancy})
    run.update({"max seconds": budget["max_seconds"]} if budget else {})  # only where given
    if z_calibration is not None:  # its terms, not the file it came from
        check_calibration(z_calibration, model)  # before any work: its pixels are the model's
        z_range = check_z_range(z_range)
        terms = {k: v for k, v in z_calibration.record().items() if k != "source"}
        run.update({"z calibration": terms, "z range": list(z_range)})
    check_folder(out, run, ANALYSIS_FILES, force=force, copies=copied)  # before the work
    about = {"movie": str(movie.path)}  # recorded, not compared: a moved movie is the same
    with task_runner(executor, workers) as runner:  # one set of workers for every stage
        where = {"workers": 1} if runner is None else {"executor": runner}
        found = find_molecules(
            movie, model, s0=s0, roi=roi, fit=fit, rules=rules, progress=progress, executor=runner
        )
        about["psf sd"] = found.psf_width.record()  # a result: recorded, not compared
        about["geometry"] = found.geometry
        roi, fit = found.geometry["roi"], found.geometry["fit"]
        provenance = {**(provenance or {}), "psf sd": found.psf_width.summary()}
        claimed = claim_folder(out, run, ANALYSIS_FILES, force=force, copies=copied, about=about)
        paths = {**(files or {}), **claimed}
        paths.update(write_tables(found, out, runner))
        if not found.molecules["selected"].any():
            raise BayespsfInputError(
                "no molecule passed the selection rules: nothing to analyse (see "
                f"{paths['selection.md']})"
            )
        counts, place = valid_rois(movie, found, fit)
        fitting = model.for_roi(fit)
        effective = {} if ess is None else {"ess": ess}  # else each sampler's default
        beside = send_estimates(counts, fitting, place["molecule"].to_numpy(), runner)
        posteriors = sample_many(
            counts,
            fitting,
            seed=seed,
            store=out / "posteriors",
            progress=progress,
            check=gof_discrepancy,
            method=method,
            backend=backend,
            **where,
            **effective,
            **budget,
        )
        fits, windows = beside()
        frames = pd.concat([place, posteriors.drop(columns="molecule"), fits], axis=1)
        frames["selected"] = True
        if z_calibration is not None:
            from bayespsf.axial import z_posteriors

            z_rows = z_posteriors(
                counts,
                fitting,
                z_calibration,
                seed=seed,
                z_range=z_range,
                progress=progress,
                **where,
                **effective,
            )
            frames = pd.concat([frames, z_rows], axis=1)
            provenance = {**(provenance or {}), "z calibration": z_calibration.record()}
        frame_z, per_molecule, overall = frame_consistency(frames, PARAMETERS)
        scale = fitting.photoelectrons_per_photon  # Eq. sigma2dp3 is stated in detected photons
        detected = frames.assign(
            N_mean=frames["N_mean"] * scale,
            b_mean=frames["b_mean"] * scale,
            photon_unit="photoelectrons",
        )
        spread = width_spread(detected, fitting.pixel_size)
        mle = frames[[f"{p}_mle" for p in PARAMETER_NAMES]].where(frames["mle_converged"], axis=0)
        residuals = mean_residuals(counts, fitting, mle.to_numpy(float), frames["molecule"])
        image = project(movie, "mean")
        figures = send_figures(runner, image, found, frame_z, spread, frames["gof_p"], residuals)
        settings = {"method": method, "roi": roi, "fit": fit, **(provenance or {})}
        info = locs_info(movie, fitting, "bayespsf analyze", settings)
        paths.update(write_locs(localizations(frames, fitting.pixel_size), out, info, runner))
        joint = joint_posteriors(
            counts, frames, fitting, seed=seed, progress=progress, **where, **effective
        )
        paths.update(figures(out))
    molecules = _per_molecule(found, per_molecule).merge(joint, on="molecule", how="left")
    tables = {
        "molecules.csv": molecules,
        "consistency.csv": overall,
        "width_spread.csv": spread,
        "width_by_window.csv": windows,
    }
    for name, table in tables.items():
        paths[name] = out / name
        table.to_csv(paths[name], index=False)
    result = Analysis(found, frames, molecules, overall, spread, windows, paths)
    paths["report.md"] = out / "report.md"
    paths["report.md"].write_text(report_markdown(result, provenance))
    return result


__all__ = ["ANALYSIS_FILES", "Analysis", "analyze", "valid_rois"]
