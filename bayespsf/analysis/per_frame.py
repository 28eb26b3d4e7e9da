"""Per-frame localisation: every spot of every frame, localised in its own frame.

Blinking (dSTORM, PAINT) and moving molecules are not one spot over many frames, so the
projection, the traces and the paper's selection rules (which need a trace) do not apply.
``localize_frames``, the library side of ``bayespsf detect --per-frame`` and ``bayespsf analyze
--per-frame``, runs instead:

1. detection on every frame (``bayespsf.movie.detect_frame``: the matched filter with each
   frame's local background, its threshold from the camera law's exact tail for one frame;
   the cut is the fitted window, so a candidate whose window crosses the frame's edge, or
   that has a neighbour as ``detect`` defines one, is rejected);
2. the ``fit`` x ``fit`` window of each accepted candidate, cut from its own frame;
3. per window the MLE with its Cramér-Rao bound (``fit_mle``) and, with ``posterior``, the
   paper's least squares and the posterior (``sample_many``, with its goodness-of-fit test),
   in chunks of ``frame_tasks.CHUNK`` (512) windows in detection order;
4. the files: ``candidates.csv`` (every frame's candidates), ``locs.hdf5`` + ``locs.yaml``
   (picasso), ``locs.csv`` (ThunderSTORM), ``locs.parquet`` (every column), one row per
   localisation, and ``report.md``.

Steps 1 to 3 run as tasks on the workers (``bayespsf.analysis.frame_tasks``): blocks of frames
to detect and chunks of windows to localise, later frames detected while earlier chunks are
localised; this process reads the frames and folds the windows into chunks, and memory holds a
few blocks and chunks whatever the movie's length.

Seeds: window ``j`` of chunk ``k`` is sampled with ``molecule_seed(molecule_seed(seed, k), j)``
(``sample_many``'s rule within a chunk whose seed is the chunk's), and each chunk is sampled
in one process, so results depend on the seed and the movie only, not on the workers (to the
last bit). The store of chunk ``k`` is ``OUT/posteriors/chunk-0000k``: a rerun of the same
run continues.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf._runtime import progress_bar
from bayespsf.analysis.frame_tasks import CHUNK, ChunkWork, block_frames, block_spots, run_frames
from bayespsf.analysis.localizations import localizations, locs_info
from bayespsf.analysis.pipeline import _check_sampler
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.gof import check_discrepancy
from bayespsf.inference.summary import concat_tables
from bayespsf.io import write_locs
from bayespsf.io.run_record import check_folder, claim_folder, read_copies
from bayespsf.model import Model
from bayespsf.movie import Movie, frame_settings, geometry_for_psf
from bayespsf.movie.extract import check_sizes, frame_span, open_movie
from bayespsf.movie.pipeline import selection_run
from bayespsf.movie.psf_width import PsfWidth, resolve_psf_sd
from bayespsf.parallel import parallelism, task_runner
from bayespsf.parallel.tables import write_csv

if TYPE_CHECKING:
    from distributed import Client

#: What ``localize_frames`` writes with ``posterior`` (and ``run.json``, the copies).
PER_FRAME_FILES = (
    *("candidates.csv", "locs.hdf5", "locs.yaml", "locs.csv", "locs.parquet", "report.md"),
    "posteriors",
)


@dataclass
class FrameLocalizations:
    """What ``localize_frames`` made: its tables, and the files it wrote.

    Attributes
    ----------
    candidates : pandas.DataFrame
        Every frame's candidates: ``frame``, then ``detect``'s columns (``molecule`` numbers
        the rows of the whole table; ``status`` says which were localised: ``accepted``).
    locs : pandas.DataFrame
        One row per localisation (``localizations``' table): picasso's columns, from the
        posterior (``posterior=True``) or from the MLE and its Cramér-Rao bound, then every
        other column. Its ``molecule`` is the candidate's ``molecule`` in ``candidates``.
    psf_width : PsfWidth
        The spot's SD used: given, or estimated with its error.
    paths : dict of str to Path
        The files written into the output folder, by name.
    """

    candidates: pd.DataFrame
    locs: pd.DataFrame
    psf_width: PsfWidth
    paths: dict[str, Path] = field(default_factory=dict)


def frame_spots(
    movie: Movie | str | Path,
    model: Model,
    *,
    psf_sd: float,
    fit: int = 15,
    false_positives: float = 0.01,
    frames: slice | range | None = None,
    block: int = 16,
) -> Iterator[tuple[pd.DataFrame, np.ndarray]]:
    """Each frame's candidates and the ``fit`` x ``fit`` windows of the accepted ones.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU).
    model : Model
        The camera (ADU to photons, its law for the threshold) and pixel size.
    psf_sd : float
        The spot's SD in nm (the detector's template).
    fit : int, default 15
        Odd side in pixels of the window cut around each accepted candidate; detection's
        ``roi`` (edge and neighbour rules).
    false_positives : float, default 0.01
        Expected false candidates per frame (``detect``).
    frames : slice or range, optional
        Consecutive frames (default all).
    block : int, default 16
        Frames read at a time.

    Yields
    ------
    table : pandas.DataFrame
        One frame's candidates (``iter_detect_frames``: ``frame``, then ``detect``'s columns).
    windows : numpy.ndarray, shape (n, fit, fit)
        The accepted candidates' windows in ADU (float64), in the table's order, centred on
        their peak pixels.
    """
    movie = open_movie(movie)
    check_sizes(fit, fit, names=("fit", "fit"))
    span = frame_span(movie, frames)
    settings = _detection(movie, model, psf_sd, fit, false_positives)
    for first, data in movie.blocks(block, span.start, span.stop):
        yield from block_spots(first, data, settings)


def _detection(movie, model, psf_sd, fit, false_positives) -> dict:
    """``block_spots``' settings for ``movie``: ``detect_frame``'s keywords and ``fit``."""
    options = dict(roi=fit, fit=fit, false_positives=false_positives)
    return frame_settings(movie, psf_sd=psf_sd, camera=model, **options)


def localize_frames(
    movie: Movie | str | Path,
    model: Model,
    *,
    out: str | Path,
    s0: float | None = None,
    fit: int | None = None,
    false_positives: float = 0.01,
    posterior: bool = True,
    method: str = "auto",
    backend: str = "numpy",
    ess: float | None = None,
    max_seconds: float | None = None,
    seed: int = 0,
    workers: int | None = None,
    executor: Executor | Client | str | None = None,
    progress: bool | None = None,
    provenance: dict | None = None,
    gof_discrepancy: str = "likelihood",
    keep_draws: bool = True,
    force: bool = False,
    copies: dict[str, str | Path] | None = None,
) -> FrameLocalizations:
    """Localise every spot of every frame in its own frame (blinking or moving molecules).

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU), from ``read_movie`` or a path it opens.
    model : Model
        A camera file's model (camera law, pixel size, prior, photon unit); the windows use
        ``model.for_roi(fit)``.
    out : str or Path
        The folder every file goes into (made if missing), with the run record ``run.json``;
        a folder that holds another run's results is refused before anything is computed.
    s0 : float, optional
        The spot's SD in nm; default estimated from the movie (``estimate_psf_sd``).
    fit : int, optional
        Odd side in pixels of the window localised around each spot (and detection's ROI);
        default from the spot's SD (``bayespsf.movie.geometry_for_psf``: the paper's 15 at
        s0 = 120 nm, 79 nm pixels).
    false_positives : float, default 0.01
        Expected false candidates per frame.
    posterior : bool, default True
        Also sample each window's posterior (``bayespsf analyze --per-frame``); False: the MLE
        and its Cramér-Rao bound only (``bayespsf detect --per-frame``).
    method, backend, ess, max_seconds, seed, gof_discrepancy
        As ``analyze`` (the posterior's sampler; seeds as the module docstring says).
    workers, executor
        Where detection, the fits and the posteriors run, as ``analyze``: local worker
        processes (default one per core; 1: this process) or a Dask cluster. With
        ``backend="jax"`` the posteriors run here, on the device, the workers detect and
        take the ROIs left to the chain.
    progress : bool, optional
        A bar of the windows localised (default: when stderr is a terminal).
    keep_draws : bool, default True
        Whether the chunks' stores (``OUT/posteriors``) keep each window's draws
        (``sample_many``'s ``keep_draws``: False keeps the summaries only, a quarter of the
        disk; ``bayespsf analyze --per-frame --no-draws``).
    provenance : dict, optional
        What made the run, recorded in ``locs.yaml`` and the report.
    force : bool, default False
        Replace another run's results in ``out`` (``PER_FRAME_FILES`` and the files its record
        lists; nothing else).
    copies : dict of str to path, optional
        Files to copy verbatim into ``out`` (the command's camera file as ``camera.toml``).

    Returns
    -------
    FrameLocalizations
        ``candidates``, ``locs`` (photons in the model's photon unit; picasso's ``x``, ``y``,
        ``photons``, ``sx``, ``sy``, ``bg``, ``lpx``, ``lpy`` from the posterior's means and
        SDs, or from the MLE and its Cramér-Rao bound without ``posterior``, NaN where that
        fit did not converge; then ``molecule`` (the candidate), the MLE ``<p>_mle`` and
        ``crlb_<p>``, ``mle_converged``, ``mle_status``, ``mle_message`` and, with
        ``posterior``, ``sample_many``'s summary and the least squares ``<p>_lsq``),
        ``psf_width`` and ``paths``.

    Raises
    ------
    BayespsfInputError
        ``out`` holds another run's results; a ``fit`` that is even or larger than the
        frames; an unknown ``gof_discrepancy``; no spot accepted in any frame; or any error of
        detection (``detect``) or of ``sample_many``.

    See Also
    --------
    analyze : immobile molecules: detection on the projection, traces and selection rules.
    frame_spots : steps 1 and 2 alone.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> from bayespsf.analysis import localize_frames
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 3, "height": 64, "width": 64, "molecules": 2, "dark_frames": 0,
    ...            "two_fluorophores": 0.0, "moving": 0.0}
    ... )
    >>> folder = Path(tempfile.mkdtemp())
    >>> made = bayespsf.simulate_movie(scene, seed=1, out=folder / "m")
    >>> found = localize_frames(made.files["movie"], bayespsf.Model.from_scene(scene),
    ...                         s0=120.0, out=folder / "out", posterior=False)
    >>> found.locs.groupby("frame").size().to_dict()
    {0: 2, 1: 2, 2: 2}
    """
    check_discrepancy("gof_discrepancy", gof_discrepancy)
    if not isinstance(keep_draws, bool | np.bool_) or not (keep_draws or posterior):
        raise BayespsfInputError(
            f"keep_draws must be True or False, and False only with posterior=True (the MLE "
            f"keeps no draws); got {keep_draws!r}"
        )
    movie, out, copied = open_movie(movie), Path(out), read_copies(copies)
    check_sizes(None, fit, missing_ok=True)
    run = selection_run(movie, model, s0=s0, roi=fit, fit=fit, false_positives=false_positives)
    run = {k: v for k, v in run.items() if k not in ("roi", "geometry", "projection", "rules")}
    run.update(command="analyze" if posterior else "detect", **{"per frame": True})
    run["windows per chunk"] = CHUNK  # the seeds and stores depend on it
    budget = {}  # the chain's budget (sample_many's max_seconds), where given
    if posterior:
        budget = _check_sampler(method, ess, seed, max_seconds)
        run.update(method=method, ess=ess, seed=seed, **{"model check": gof_discrepancy})
        run.update({"max seconds": budget["max_seconds"]} if budget else {})
        run.update({} if keep_draws else {"draws": "not kept"})
    files = PER_FRAME_FILES if posterior else PER_FRAME_FILES[:-1]
    check_folder(out, run, files, force=force, copies=copied)  # before the work
    width = resolve_psf_sd(movie, model, s0, fit=fit or 15, false_positives=false_positives)
    source = "given"
    if fit is None:
        fit, source = geometry_for_psf(width.sd, model.pixel_size)[1], "from s0"
    if fit > min(movie.shape[1:]):
        raise BayespsfInputError(
            f"fit ({fit}, {source}) is larger than the movie's frames ({movie.shape[1]} x "
            f"{movie.shape[2]}): give a smaller --fit"
        )
    about = {"movie": str(movie.path), "psf sd": width.record()}
    about["geometry"] = {"fit": fit, "source": source}
    provenance = {**(provenance or {}), "psf sd": width.summary()}
    provenance["window"] = f"{fit} x {fit} pixels ({source})"
    if gof_discrepancy != "likelihood":
        provenance["goodness-of-fit discrepancy"] = gof_discrepancy
    paths = claim_folder(out, run, files, force=force, copies=copied, about=about)
    fitting = model.for_roi(fit)
    sampler = dict(method=method, backend=backend, check=gof_discrepancy, progress=False)
    sampler.update({} if keep_draws else {"keep_draws": False})
    sampler.update(budget, **({} if ess is None else {"ess": ess}))
    settings = _detection(movie, fitting, width.sd, fit, false_positives)
    device = posterior and backend == "jax"  # its chunks here, beside the device
    with (
        task_runner(executor, workers) as runner,
        progress_bar(None, progress, unit="window") as bar,
    ):
        block = block_frames(movie.shape[1:], len(movie), parallelism(runner))
        frames = movie.blocks(block, 0, len(movie))
        if device and runner is not None:  # the device's chunks send their chains there
            sampler["executor"] = runner
        else:  # a worker's chunk runs in it alone
            sampler["workers"] = 1
        work = ChunkWork(fitting, seed, posterior, out, sampler)
        candidates, rows = run_frames(
            frames, settings, work, runner, chunks_here=device, done=bar.update
        )
        paths["candidates.csv"] = out / "candidates.csv"
        write_csv(candidates, paths["candidates.csv"], runner)  # rows formatted on the workers
        if not rows:
            raise BayespsfInputError(
                f"no spot was accepted in any of the {len(movie)} frames: nothing to localise "
                f"(see {paths['candidates.csv']}; --false-positives raises the detector's rate, "
                "--fit changes its window)"
            )
        table = concat_tables(rows)  # seeds kept whole
        kind = "posterior" if posterior else "mle"
        locs = localizations(table, fitting.pixel_size, estimate=kind)
        estimate = f"posterior ({method})" if posterior else "MLE, Cramér-Rao bound"
        settings = {"estimate": estimate, "fit": fit, **provenance}
        info = locs_info(movie, fitting, f"bayespsf {run['command']} --per-frame", settings)
        paths.update(write_locs(locs, out, info, runner))
    result = FrameLocalizations(candidates, locs, width, paths)
    paths["report.md"] = out / "report.md"
    paths["report.md"].write_text(_report(result, len(movie), posterior, provenance))
    return result


def _report(result: FrameLocalizations, frames: int, posterior: bool, provenance) -> str:
    """``report.md``: what was detected and localised, and how."""
    status = result.candidates["status"].value_counts()
    counts = ", ".join(f"{k}: {v}" for k, v in status.items()) or "none"
    locs = result.locs
    per_frame = locs.groupby("frame").size().reindex(range(frames), fill_value=0)
    lines = [
        "# Per-frame localisation",
        "",
        f"Detection ran on each of {frames} frame(s); every accepted spot was localised in its "
        "own frame. The selection rules, which need a molecule's trace over frames, do not "
        "apply.",
        "",
        f"- The {result.psf_width.summary()}.",
        f"- Candidates: {counts}.",
        f"- Localisations: {len(locs)} (per frame: median {per_frame.median():g}, "
        f"max {per_frame.max():g}).",
        f"- Maximum-likelihood fits converged: {int(locs['mle_converged'].sum())} of {len(locs)}.",
    ]
    if not posterior and not locs["mle_converged"].all():
        refused = int((locs["mle_status"] == "refused").sum())
        failed = int((~locs["mle_converged"].astype(bool)).sum()) - refused
        lines.append(
            f"- Without a position in picasso's columns (NaN: picasso leaves them out; "
            f"`mle_message` says why): {failed} fit(s) that did not converge (their last iterate "
            f"is kept in `<p>_mle`) and {refused} window(s) refused before fitting."
        )
    a = "posterior means and SDs" if posterior else "the MLE and its Cramér-Rao bound"
    lines.append(f"- picasso's x, y, photons, sx, sy, bg, lpx, lpy are {a}.")
    if posterior:
        methods = locs["method"].value_counts()
        lines.append("- Posterior methods: " + ", ".join(f"{k}: {v}" for k, v in methods.items()))
        states = locs["status"].value_counts()
        lines.append("- Posterior status: " + ", ".join(f"{k}: {v}" for k, v in states.items()))
        p = locs["gof_p"].dropna()
        if len(p):
            flagged = float((p <= 0.02).mean())
            lines.append(
                f"- Goodness of fit: {flagged:.3f} of {len(p)} windows have p <= 0.02 "
                "(0.02 expected when the model holds)."
            )
        ratio = (locs["x0_sd"] / locs["crlb_x0"]).replace([np.inf, -np.inf], np.nan).dropna()
        if len(ratio):
            lines.append(
                f"- Posterior SD of x over its Cramér-Rao bound: median {ratio.median():.3g}."
            )
    lines += ["", "## Provenance", ""]
    lines += [f"- {k}: {v}" for k, v in provenance.items() if "\n" not in str(v)]
    lines += ["", "## Files", ""]
    lines += [f"- `{name}`" for name in sorted(result.paths) if name != "report.md"]
    return "\n".join(lines) + "\n"
