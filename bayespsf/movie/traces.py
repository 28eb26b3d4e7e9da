"""Molecules over time: per-frame photons, background and centroid of every molecule, its
photobleaching steps and its drift.

The paper selected streptavidin-Cy3 monomers "by examining the fluorescence time traces of the
molecules for a single bleaching step" and required "no stage drift detected by using
centroid vs time measurements" (criterion 1): DeSantis, DeCenzo, Li & Wang, Opt. Express 18
(2010), section "Data acquisition and selection".

``traces`` gives two fast per-frame photon estimates (not fits: the maximum likelihood path
is ``bayespsf.fit_mle`` on ``cut_rois(...).central()``): an aperture sum, and the PSF-weighted
sum (the matched filter), whose noise is the least where the background dominates and whose
trace ``molecules_over_time`` searches for steps. ``bleach_steps`` finds the steps of one trace
with PELT (Killick, Fearnhead & Eckley, J. Am. Stat. Assoc. 107, 1590 (2012)) from
``ruptures`` (Truong, Oudre & Vayatis, Signal Process. 167, 107299 (2020)), then places each
step inside its frame by the exact least-squares scan.
"""

from __future__ import annotations

from concurrent.futures import Executor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf import psf
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.movie._metadata import resolve_pixel_size
from bayespsf.movie.extract import iter_rois, molecule_pixels, open_movie, photon_model
from bayespsf.movie.geometry import periphery_background
from bayespsf.movie.steps import PENALTY
from bayespsf.movie.tasks import movie_runner, trace_steps

if TYPE_CHECKING:
    from bayespsf.cameras import Camera
    from bayespsf.movie.read import Movie

COLUMNS = (  # traces's, then its order
    *("photons", "photons_se", "photons_psf", "photons_psf_se", "b", "b_se", "x", "y", "_order"),
)
MOLECULE_COLUMNS = (
    *("molecule", "x", "y", "steps", "bleach_frame", "frames_before", "multiple_steps"),
    *("photons_mean", "drift_x", "drift_x_se", "drift_y", "drift_y_se"),
)


def traces(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    camera: Camera | Model,
    *,
    s0: float,
    pixel_size: float | None = None,
    roi: int = 25,
    fit: int = 15,
    aperture: float = 2.5,
    frames: slice | range | None = None,
    block: int = 64,
    progress: bool | None = None,
    periphery: np.ndarray | None = None,
) -> pd.DataFrame:
    """Photons, background and centroid of every molecule in every frame.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU).
    molecules : pandas.DataFrame
        ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention), as ``cut_rois``.
    camera : Camera or Model
        Converts counts to photons (``Model.to_photons``) and gives their variance.
    s0 : float
        The spot's width (nm): sets the aperture and its enclosed fraction.
    pixel_size : float, optional
        nm; default the Model's, else the movie's metadata.
    roi, fit : int, default 25 and 15
        The ROI geometry of ``cut_rois`` (the periphery outside ``fit`` gives the background).
    aperture : float, default 2.5
        Radius of the photon aperture in units of ``s0`` (2.5: 95.6% of the spot).
    frames : slice or range, optional
        Consecutive frames (default all), as ``cut_rois``.
    block : int, default 64
        Frames read at a time.
    progress : bool, optional
        A progress bar on stderr (default: when it is a terminal).
    periphery : numpy.ndarray of bool, shape (molecules, roi, roi), optional
        Each molecule's periphery pixels for the background, its neighbours' light masked out
        (``geometry.periphery_masks``); default the whole ring outside ``fit``.

    Returns
    -------
    pandas.DataFrame
        One row per (molecule, frame), ordered by molecule (as given), then frame:
        ``molecule``, ``frame``, ``photons`` (aperture estimate of N, photons),
        ``photons_se``, ``photons_psf`` (PSF-weighted estimate of N, photons) and
        ``photons_psf_se``, ``b`` and ``b_se`` (background photons per pixel from the
        periphery), ``x`` and ``y`` (centroid, camera pixels in picasso's convention; NaN
        where the net signal is <= 0).

    Raises
    ------
    BayespsfInputError
        No pixel size, an aperture smaller than half a pixel or beyond the central ``fit``
        pixels, or any error of ``cut_rois`` (sizes, molecule table, ROIs off the frame).

    See Also
    --------
    molecules_over_time : the traces with each molecule's bleaching steps and drift.
    cut_rois : the ROI geometry.

    Notes
    -----
    ``photons`` is the sum of the background-subtracted photons over the pixels whose centres
    lie within ``aperture * s0`` of the molecule's pixel centre, divided by the fraction of a
    pixel-integrated Gaussian of width ``s0`` at the molecule's sub-pixel position
    (``molecules.x, y``) that falls on those pixels. Its SE adds the camera variance of each
    aperture pixel, at the plug-in expected photons, and the aperture's share of the
    background's SE. ``photons_psf`` weights the background-subtracted photons of the central
    ``fit`` × ``fit`` pixels by the matched filter ``g / Σ g²``, ``g`` that same Gaussian on
    those pixels: the least-variance linear estimate of N when every pixel's noise is the
    background's, as for a dim spot, whose step is the one that can hide. Its variance is
    ``Σ g² v / (Σ g²)²`` against the aperture's ``n v / f²`` (``n`` pixels enclosing ``f``): at
    s0 = 120 nm on 79 nm pixels and the default aperture, 30 v against 50 v, a 1.29 times
    larger step in units of the noise (a bright spot, whose noise is its own shot noise, pays
    about 27% more variance than in the aperture, at a step of tens of SDs). Its SE adds the
    camera variance of each pixel at the plug-in expected photons, times its weight squared,
    and the weights' sum times the background's SE. The centroid is the first moment of the
    background-subtracted central ``fit`` × ``fit`` photons.
    """
    movie = open_movie(movie)
    model = photon_model(camera)
    a = _pixel_size(camera, pixel_size, movie)
    ids, rows, cols = molecule_pixels(molecules)
    dx = molecules["x"].to_numpy(float) - cols
    dy = molecules["y"].to_numpy(float) - rows
    radius = aperture * s0 / a
    if not (np.isfinite(radius) and 0.5 <= radius <= (fit - 1) / 2):
        raise BayespsfInputError(
            f"aperture * s0 ({aperture:g} * {s0:g} nm = {radius:.3g} pixels) must be at least "
            f"half a pixel and lie within the central {fit}x{fit} pixels"
        )
    offsets = np.arange(fit) - (fit - 1) / 2
    disc = offsets[:, None] ** 2 + offsets[None, :] ** 2 <= radius**2
    unit = np.column_stack([dx * a, dy * a, np.full((len(ids), 2), s0), np.ones(len(ids))])
    shape = psf.expected_counts(np.column_stack([unit, np.zeros(len(ids))]), fit, a)
    spot = shape[:, disc]
    enclosed = spot.sum(axis=1)
    weights = shape / (shape**2).sum(axis=(1, 2))[:, None, None]  # the matched filter's
    parts = []
    for stack in iter_rois(
        movie,
        molecules,
        roi=roi,
        fit=fit,
        frames=frames,
        block=block,
        progress=progress,
        desc="traces",
    ):
        m = np.repeat(np.arange(len(ids)), len(stack) // len(ids))
        background = periphery_background(stack, model, periphery, m)
        b, b_se = background["b"].to_numpy(), background["b_se"].to_numpy()
        net = model.to_photons(stack.central()) - b[:, None, None]
        photons = net[:, disc].sum(axis=1) / enclosed[m]
        lam = np.clip(b, 0, None)[:, None] + np.clip(photons, 0, None)[:, None] * spot[m]
        variance = model.photon_variance(lam).sum(axis=1) + (disc.sum() * b_se) ** 2
        w = weights[m]  # the PSF-weighted photons and their SE
        weighted = (w * net).sum(axis=(1, 2))
        level = np.clip(weighted, 0, None)[:, None, None] * shape[m]
        lam = np.clip(b, 0, None)[:, None, None] + level
        weighted_variance = (w**2 * model.photon_variance(lam)).sum(axis=(1, 2))
        weighted_variance += (w.sum(axis=(1, 2)) * b_se) ** 2
        total = net.sum(axis=(1, 2))
        safe = np.where(total > 0, total, np.nan)  # no net signal: no centroid
        centre = (roi - 1) / 2
        x = stack.table["col0"] + centre + (net * offsets[None, None, :]).sum(axis=(1, 2)) / safe
        y = stack.table["row0"] + centre + (net * offsets[None, :, None]).sum(axis=(1, 2)) / safe
        values = [photons, np.sqrt(variance) / enclosed[m], weighted, np.sqrt(weighted_variance)]
        values += [b, b_se, x, y, m]
        parts.append(
            stack.table[["molecule", "frame"]].assign(**dict(zip(COLUMNS, values, strict=True)))
        )
    out = pd.concat(parts, ignore_index=True).sort_values(["_order", "frame"], kind="stable")
    return out.drop(columns="_order").reset_index(drop=True)


def _pixel_size(camera, pixel_size, movie) -> float:
    return resolve_pixel_size(pixel_size, camera if isinstance(camera, Model) else None, movie)


def drift(frames, position) -> tuple[float, float]:
    """Least-squares slope of ``position`` against ``frames`` and its SE (from the residual
    variance, n - 2 degrees of freedom); NaN with fewer than 3 finite points."""
    t, p = np.asarray(frames, dtype=np.float64), np.asarray(position, dtype=np.float64)
    ok = np.isfinite(p)
    t, p = t[ok], p[ok]
    if len(t) < 3:
        return np.nan, np.nan
    t = t - t.mean()
    sxx = float(t @ t)
    slope = float(t @ (p - p.mean())) / sxx
    residual = p - p.mean() - slope * t
    return slope, float(np.sqrt(residual @ residual / (len(t) - 2) / sxx))


def molecules_over_time(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    model: Model | Camera,
    *,
    s0: float,
    penalty: float = PENALTY,
    executor: Executor | None = None,
    **options,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``traces`` and, per molecule, its bleaching steps and drift.

    Parameters
    ----------
    movie, molecules, model, s0
        As ``traces`` (``model`` a Model or Camera).
    penalty : float, default ``PENALTY`` (4.0)
        ``bleach_steps``'s ``c``.
    executor : concurrent.futures.Executor, optional
        Where the steps are found (``bayespsf.parallel.task_runner``'s runner, a
        ``local_executor()`` or a Dask ``Client``'s executor); default this process.
    **options
        Go to ``traces``: ``pixel_size``, ``roi``, ``fit``, ``aperture``, ``frames``,
        ``block``, ``progress``, ``periphery``.

    Returns
    -------
    per_molecule : pandas.DataFrame
        One row per molecule: ``molecule``, ``x``, ``y`` (as given), ``steps`` (of the
        ``photons_psf`` trace),
        ``bleach_frame`` (nullable integer: first frame without signal, NA if none),
        ``frames_before``, ``multiple_steps``, ``photons_mean`` (photons per frame before
        bleaching), ``drift_x``, ``drift_x_se``, ``drift_y``, ``drift_y_se`` (centroid slopes
        before bleaching, nm per frame: the paper's criterion 1).
    per_frame : pandas.DataFrame
        ``traces``'s table.

    Raises
    ------
    BayespsfInputError
        As ``traces``.

    See Also
    --------
    traces : the per-frame table.
    bleach_steps : the steps of one trace.
    select : the selection rules that use both tables.
    """
    movie = open_movie(movie)
    per_frame = traces(movie, molecules, model, s0=s0, **options)
    a = _pixel_size(model, options.get("pixel_size"), movie)
    rows = []
    each = [one for _, one in per_frame.groupby("molecule", sort=False)]
    with movie_runner(executor) as runner:
        traced = [(one["photons_psf"].to_numpy(), one["frame"].to_numpy()) for one in each]
        steps = list(trace_steps(traced, penalty, runner))
    for (molecule, x, y), one, found in zip(
        molecules[["molecule", "x", "y"]].itertuples(index=False), each, steps, strict=True
    ):
        before = one.iloc[: found.frames_before]
        slope_x, se_x = drift(before["frame"], before["x"] * a)
        slope_y, se_y = drift(before["frame"], before["y"] * a)
        found_row = (found.steps, found.bleach_frame, found.frames_before, found.multiple_steps)
        mean = float(before["photons"].mean())
        rows.append((molecule, x, y, *found_row, mean, slope_x, se_x, slope_y, se_y))
    per_molecule = pd.DataFrame(rows, columns=MOLECULE_COLUMNS)
    per_molecule["bleach_frame"] = per_molecule["bleach_frame"].astype("Int64")
    return per_molecule, per_frame
