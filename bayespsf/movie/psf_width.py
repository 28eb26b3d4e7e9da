"""The spot's SD (s0) from a movie's own spots, for when the user does not state it.

Detection's matched filter, the traces' aperture and the selection's width range all need the
spot's SD. ``estimate_psf_sd`` measures it from the data:

1. detection (``detect_movie``) on the mean projection of the first frames with a provisional
   SD (``PROVISIONAL_PIXELS`` = 1.3 pixels by default: a matched filter a few tens of percent
   too narrow or too wide still finds the bright spots);
2. the brightest accepted candidates (``accepted``: away from the edges and from the
   light of neighbours in a fitted ROI (``detect``); neither saturated nor elongated);
3. with a camera, every frame of each spot's ROI fitted by maximum likelihood under the camera
   law with both widths free (``bayespsf.fit_mle``), its frames with signal kept (``N`` at
   least half the spot's 90th percentile: before bleaching, not blinked off) and the spot's
   width the median of their ``s_x`` and ``s_y`` pooled; without one, a least-squares
   pixel-integrated Gaussian with a constant background fitted to the spot's ROI of the
   projection (``s_x`` and ``s_y`` pooled);
4. the SD: the median of the spots' widths, its standard error ``1.2533 * 1.4826 MAD /
   sqrt(n)`` (the median's asymptotic SE with the SD from the median absolute deviation), so
   that a few moving, aggregated or overlapping spots do not move it;
5. when the estimate differs from the provisional SD by more than ``REDO`` (20%), steps 1-4
   once more with the estimate as the provisional SD.

``resolve_psf_sd`` returns a stated SD as it is, or the estimate; both as ``PsfWidth``, which
the run's records and the commands' output report.
"""

from __future__ import annotations

import math
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy import optimize

from bayespsf import psf
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.movie._metadata import resolve_pixel_size
from bayespsf.movie.detect import detect_movie
from bayespsf.movie.extract import check_sizes, frame_span, iter_rois, open_movie, photon_model
from bayespsf.movie.project import project
from bayespsf.movie.tasks import fit_stacks, movie_runner

if TYPE_CHECKING:
    from bayespsf.cameras import Camera
    from bayespsf.movie.read import Movie

#: The provisional SD of the first detection, in pixels.
PROVISIONAL_PIXELS = 1.3
#: Relative difference between the estimate and the provisional SD that triggers a second pass.
REDO = 0.2
#: Fewest spots an estimate is made from.
MIN_SPOTS = 5
_SE_MEDIAN = 1.2533 * 1.4826  # SE of a normal sample's median per MAD, times sqrt(n)


@dataclass(frozen=True)
class PsfWidth:
    """The spot's SD a run used, and where it came from.

    Attributes
    ----------
    sd : float
        The SD in nm.
    se : float
        Its standard error in nm (NaN when stated).
    spots : int
        The spots it was measured on (0 when stated).
    source : str
        ``"given"`` or ``"estimated"``.
    provisional : float
        The SD (nm) of the detection the spots were found with (``sd`` when stated).

    See Also
    --------
    estimate_psf_sd : makes an estimated one.
    """

    sd: float
    se: float = math.nan
    spots: int = 0
    source: str = "given"
    provisional: float = math.nan

    def record(self) -> dict:
        """The run record's entry: ``psf sd`` (nm), ``source``, ``se`` and ``spots``.

        Returns
        -------
        dict
        """
        se = None if math.isnan(self.se) else round(self.se, 3)
        return {"psf sd": round(self.sd, 3), "source": self.source, "se": se, "spots": self.spots}

    def summary(self) -> str:
        """One line: the SD, and its error and spots when estimated.

        Returns
        -------
        str
        """
        if self.source == "given":
            return f"spot SD s0 = {self.sd:g} nm, given"
        return f"spot SD s0 = {self.sd:.1f} +- {self.se:.1f} nm, estimated from {self.spots} spots"


def estimate_psf_sd(
    movie: Movie | str | Path,
    camera: Camera | Model | None = None,
    *,
    pixel_size: float | None = None,
    provisional: float | None = None,
    fit: int = 15,
    frames: int = 50,
    spots: int = 30,
    false_positives: float = 0.01,
    executor: Executor | None = None,
) -> PsfWidth:
    """The spot's SD (nm) from the movie's brightest isolated spots, with its standard error.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU), from ``read_movie`` or a path it opens.
    camera : Camera or Model, optional
        The camera law: spots are fitted frame by frame by maximum likelihood under it. Without
        it (before a camera is calibrated) they are fitted by least squares on the mean
        projection, whose counts need not be photons.
    pixel_size : float, optional
        Pixel side in nm; default the Model's, else the movie's metadata.
    provisional : float, optional
        The SD (nm) of the first detection; default ``PROVISIONAL_PIXELS`` pixels.
    fit : int, default 15
        Odd side in pixels of the ROI fitted around each spot; candidates whose ROI crosses
        an edge, or into whose ROI a neighbour puts light (``detect``'s neighbour rule), are
        left out.
    frames : int, default 50
        The first frames used (projected for detection and fitted).
    spots : int, default 30
        The brightest spots fitted.
    false_positives : float, default 0.01
        Expected false detections in the projection (``detect``).
    executor : concurrent.futures.Executor, optional
        Where the fits run (``bayespsf.parallel.task_runner``'s runner, a
        ``local_executor()`` or a Dask ``Client``'s executor); default this process.

    Returns
    -------
    PsfWidth
        ``sd`` and ``se`` in nm, the ``spots`` it came from, ``source`` ``"estimated"`` and
        the ``provisional`` SD of the detection that found them.

    Raises
    ------
    BayespsfInputError
        Fewer than ``MIN_SPOTS`` isolated, unsaturated round spots with signal (state the SD
        instead: ``--psf-sd`` on the command line, ``s0=`` in Python), a bad ``fit``,
        ``frames`` or ``spots``, or any error of ``detect_movie``.

    See Also
    --------
    resolve_psf_sd : a stated SD, or this estimate.
    detect_movie : the detection step.
    bayespsf.fit_mle : the per-frame fits.

    Notes
    -----
    The steps, and why a median, are in the module docstring. On simulated ``paper-movie``
    movies (s0 120 nm, and 160 nm) the estimate is within 0.5% of the truth (docs/movies.md).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> from bayespsf.movie.psf_width import estimate_psf_sd
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 20, "height": 128, "width": 128, "molecules": 12, "dark_frames": 0}
    ... )
    >>> made = bayespsf.simulate_movie(scene, seed=1, out=Path(tempfile.mkdtemp()) / "m")
    >>> width = estimate_psf_sd(made.files["movie"], bayespsf.Model.from_scene(scene))
    >>> abs(width.sd - 120.0) < 6.0, width.spots >= 5
    (True, True)
    """
    movie = open_movie(movie)
    check_sizes(fit, fit, names=("fit", "fit"))
    for name, value in (("frames", frames), ("spots", spots)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise BayespsfInputError(f"{name} must be a whole number >= 1, got {value!r}")
    pixel_size = resolve_pixel_size(pixel_size, camera, movie)
    start = PROVISIONAL_PIXELS * pixel_size if provisional is None else float(provisional)
    span = frame_span(movie, range(0, min(frames, len(movie))))
    with movie_runner(executor) as runner:
        options = (camera, pixel_size, fit, span, spots, false_positives, runner)
        sd, se, n = _one_pass(movie, start, *options)
        if abs(sd / start - 1.0) > REDO:  # far from the provisional SD: detect again with it
            start = sd
            sd, se, n = _one_pass(movie, start, *options)
    return PsfWidth(sd, se, n, "estimated", start)


def resolve_psf_sd(movie: Movie | str | Path, camera, s0: float | None, **options) -> PsfWidth:
    """``s0`` as a ``PsfWidth`` (``"given"``), or, when None, ``estimate_psf_sd(movie,
    camera, **options)``."""
    if s0 is None:
        return estimate_psf_sd(movie, camera, **options)
    return PsfWidth(float(s0), provisional=float(s0))


def _one_pass(movie, provisional, camera, pixel_size, fit, span, spots, false_positives, runner):
    """Steps 1-4 of the module docstring: (SD, its SE, spots) in nm."""
    found = detect_movie(
        movie,
        psf_sd=provisional,
        pixel_size=pixel_size,
        camera=camera,
        frames=span,
        roi=fit,
        false_positives=false_positives,
    )
    usable = found[
        (found["status"] == "accepted") & (found["saturated"] == 0) & ~found["elongated"]
    ]
    chosen = usable.nlargest(spots, "amplitude")
    if chosen.empty:
        widths = np.empty(0)
    elif camera is None:
        widths = _projection_widths(movie, chosen, pixel_size, fit, span, provisional)
    else:
        widths = _frame_widths(movie, chosen, camera, pixel_size, fit, span, runner)
    widths = widths[np.isfinite(widths)]
    if len(widths) < MIN_SPOTS:
        raise BayespsfInputError(
            f"cannot estimate the spot's SD: {len(widths)} isolated, unsaturated round spot(s) "
            f"with signal in the first {len(span)} frame(s) ({len(found)} candidate(s) found "
            f"with a provisional SD of {provisional:.4g} nm), fewer than {MIN_SPOTS}; state it: "
            "--psf-sd NM on the command line ([emitter] s0x and s0y in the camera file), s0= in "
            "Python"
        )
    sd = float(np.median(widths))
    mad = float(np.median(np.abs(widths - sd)))
    return sd, _SE_MEDIAN * mad / math.sqrt(len(widths)), len(widths)


def _frame_widths(movie, chosen, camera, pixel_size, fit, span, runner) -> np.ndarray:
    """Per spot, the median of ``s_x`` and ``s_y`` pooled over its frames with signal (NaN
    where none): maximum-likelihood fits under the camera law."""
    model = photon_model(camera)
    fitting = Model(
        fit,
        pixel_size,
        model.camera,
        None,
        model.clock_induced_charge,
        model.saturation,
        model.pixel_model,
        model.quantum_efficiency,
        model.photon_unit,
    )
    parts = []
    stacks = iter_rois(movie, chosen, roi=fit, fit=fit, frames=span, progress=False)
    for stack, fits in fit_stacks(((s, s.counts) for s in stacks), fitting, runner):
        part = stack.table[["molecule"]].copy()
        part[["s_x", "s_y", "N"]] = fits[["s_x", "s_y", "N"]].to_numpy(float)
        part["ok"] = fits["converged"].to_numpy(bool)
        parts.append(part)
    if not parts:
        return np.empty(0)
    table = pd.concat(parts, ignore_index=True)
    table = table[table["ok"]]
    level = table.groupby("molecule")["N"].transform(lambda n: n.quantile(0.9))
    table = table[table["N"] >= 0.5 * level]
    pooled = pd.DataFrame(
        {
            "molecule": np.concatenate([table["molecule"], table["molecule"]]),
            "s": np.concatenate([table["s_x"], table["s_y"]]),
        }
    )
    return pooled.groupby("molecule")["s"].median().to_numpy(float)


def _projection_widths(movie, chosen, pixel_size, fit, span, provisional) -> np.ndarray:
    """Per spot, the mean of ``s_x`` and ``s_y`` of a least-squares pixel-integrated Gaussian
    with a constant background on the mean projection (NaN where the fit fails)."""
    image = project(movie, "mean", frames=span)
    half = fit // 2
    widths = []
    for row, col in zip(chosen["row"], chosen["col"], strict=True):
        roi = image[row - half : row + half + 1, col - half : col + half + 1]
        back = float(np.median(np.concatenate([roi[0], roi[-1], roi[:, 0], roi[:, -1]])))
        spot = float(roi.sum() - back * roi.size)
        if not spot > 0 or not back >= 0:  # no light above its edges: no spot to measure
            widths.append(np.nan)
            continue
        start = [0.0, 0.0, np.log(provisional), np.log(provisional), np.log(spot), back]

        def residual(p, roi=roi):
            params = [p[0], p[1], np.exp(p[2]), np.exp(p[3]), np.exp(p[4]), p[5]]
            return (psf.expected_counts(params, fit, pixel_size) - roi).ravel()

        # the background (an image's counts, >= 0) is bounded below by 0; the rest is free
        low = [-np.inf] * 5 + [0.0]
        result = optimize.least_squares(residual, start, x_scale="jac", bounds=(low, np.inf))
        s_x, s_y = np.exp(result.x[2:4])
        good = result.success and max(s_x, s_y) < fit * pixel_size / 2
        widths.append(0.5 * (s_x + s_y) if good else np.nan)
    return np.asarray(widths, float)


__all__ = ["MIN_SPOTS", "PROVISIONAL_PIXELS", "REDO", "PsfWidth", "estimate_psf_sd"]
