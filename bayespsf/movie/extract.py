"""ROI geometry as the paper used it: a square cut around each molecule in every frame, its
central part fitted and its periphery kept for a background estimate.

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), section "Data acquisition and
selection": "the intensity values for 25 × 25 pixels centered at the molecule were recorded.
The center 15 × 15 pixels of the PSF were used for 2D Gaussian fitting with peripheral pixels
used for background analysis." Any odd sizes are allowed here.

Molecule positions are camera pixels in picasso's convention (as its Localize writes them,
``picasso.gausslq.locs_from_fits``: the box's integer centre plus the fitted offset): the
centre of column ``j`` is ``x = j`` and of row ``i`` is ``y = i``. A ROI is centred on the
molecule's nearest pixel, ``(round(y), round(x))`` (halves rounded up), so its central pixel
holds the molecule and bayespsf's ROI convention applies to it: ``(0, 0)`` nm at the centre of
that pixel, the molecule at ``((x - round(x)) a, (y - round(y)) a)``.

Memory: ``cut_rois`` returns ``M * F * roi**2`` values in the movie's data type for ``M``
molecules and ``F`` frames (100 molecules, 2 000 frames and 25 × 25 ROIs of uint16: 250 MB);
``iter_rois`` yields the same ROIs one block of frames at a time, and reads only the rows the
ROIs span.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf._runtime import progress_bar
from bayespsf._validate import finite_array
from bayespsf.cameras import Camera
from bayespsf.errors import BayespsfInputError
from bayespsf.model import MIN_ROI, Model
from bayespsf.movie.read import Movie, read_movie

ROI_COLUMNS = ("molecule", "frame", "row0", "col0")


@dataclass
class RoiStack:
    """ROIs cut from a movie, one per (molecule, frame).

    Attributes
    ----------
    counts : numpy.ndarray, shape (n, roi, roi)
        The movie's pixels, in its data type and units (ADU).
    table : pandas.DataFrame
        One row per ROI: ``molecule``, ``frame``, ``row0``, ``col0`` (the movie pixel of the
        ROI's top-left corner: ``counts[k] == movie.frame(frame)[row0:row0 + roi,
        col0:col0 + roi]``).
    fit : int, default 15
        Side of the central part that the model fits (odd, at most ``roi``).

    See Also
    --------
    cut_rois, iter_rois : make one.
    """

    counts: np.ndarray
    table: pd.DataFrame
    fit: int = 15

    @property
    def roi(self) -> int:
        """Side of the ROIs in pixels."""
        return int(self.counts.shape[-1])

    def __len__(self) -> int:
        return len(self.counts)

    def central(self, fit: int | None = None) -> np.ndarray:
        """The central ``fit`` × ``fit`` counts ``(n, fit, fit)`` (a view): what the model
        fits, with ``(0, 0)`` nm at the centre of its central pixel (the molecule's pixel).

        Parameters
        ----------
        fit : int, optional
            The odd side of the centre, at most the cut's; default the stack's ``fit``.

        Returns
        -------
        ndarray, shape (n, fit, fit)
        """
        fit = self.fit if fit is None else fit
        check_sizes(self.roi, fit)
        k = (self.roi - fit) // 2
        return self.counts[:, k : k + fit, k : k + fit]

    def periphery_background(self, camera: Camera | Model, fit: int | None = None) -> pd.DataFrame:
        """Background photons per pixel of each ROI from its periphery.

        The mean of the ring outside the central ``fit`` × ``fit`` pixels, converted to
        photons with the camera's mean conversion (``Model.to_photons``: offset removed, times
        photons per ADU; the paper's Eq. photonConv), and its standard error (the ring's SD
        over the square root of its pixel count). The mean, not the median, because EMCCD
        counts are skewed: their mean is unbiased for the expected background. The whole ring
        is used: where neighbours' light reaches it, ``bayespsf.movie.geometry``'s
        ``periphery_background`` masks it out (``find_molecules`` does).

        Parameters
        ----------
        camera : Camera or Model
            Converts the counts (ADU) to photons; one gain and offset (not per-pixel maps).
        fit : int, optional
            Side of the central part left out; default the stack's ``fit``; must be smaller
            than ``roi``.

        Returns
        -------
        pandas.DataFrame
            ``b`` and ``b_se`` (photons per pixel), indexed like ``table``; usable as an
            informative prior on b, e.g. ``{"b": {"kind": "normal", "mean": b, "sd": b_se}}``.
        """
        fit = self.fit if fit is None else fit
        check_sizes(self.roi, fit)
        if fit == self.roi:
            raise BayespsfInputError(
                f"fit ({fit}) must be smaller than roi ({self.roi}) for a periphery to exist"
            )
        ring = np.ones((self.roi, self.roi), dtype=bool)
        k = (self.roi - fit) // 2
        ring[k : k + fit, k : k + fit] = False
        photons = photon_model(camera).to_photons(self.counts[:, ring])
        se = photons.std(axis=1, ddof=1) / np.sqrt(ring.sum())
        return pd.DataFrame({"b": photons.mean(axis=1), "b_se": se}, index=self.table.index)


def photon_model(camera) -> Model:
    """``camera`` (a Model, or a Camera with one scalar conversion) as a Model whose
    ``to_photons`` and ``photon_variance`` convert counts to detected photoelectrons (whatever
    the given Model's photon unit: the movie path's tables and selection rules, the SNR among
    them, are in detected photoelectrons); its geometry is unused."""
    if isinstance(camera, Model):
        model = (
            camera
            if camera.photoelectrons_per_photon == 1.0
            else camera.for_roi(MIN_ROI, detected=True)
        )
    elif isinstance(camera, Camera):
        model = Model(MIN_ROI, 1.0, camera)  # only the camera's conversion is used
    else:
        raise BayespsfInputError(f"camera must be a bayespsf camera or Model, got {camera!r}")
    per_adu, offset = model.camera.photons_per_adu()
    if np.ndim(per_adu) or np.ndim(offset):
        raise BayespsfInputError(
            "a camera with per-pixel gain or offset maps cannot convert ROIs cut from a movie: "
            "give one gain and offset (the common camera)"
        )
    return model


def check_sizes(
    roi, fit, missing_ok: bool = False, *, names=("roi", "fit"), smallest: int = 1
) -> None:
    """``roi`` and ``fit`` odd whole numbers >= ``smallest`` with ``fit <= roi``, else an error
    naming them by ``names`` (the command line passes its flags, ``--roi`` and ``--fit``, and
    the model's least side); with ``missing_ok`` a side that is None is left out (it follows
    the spot's SD)."""
    for name, value in zip(names, (roi, fit), strict=True):
        if missing_ok and value is None:
            continue
        if (
            isinstance(value, bool)
            or not isinstance(value, int | np.integer)
            or value < smallest
            or value % 2 == 0
        ):
            border = ", and the fit needs a border of background around it" if smallest > 1 else ""
            raise BayespsfInputError(
                f"{name} must be an odd number of pixels >= {smallest} (a central pixel holds "
                f"the molecule{border}), got {value!r}"
            )
    if roi is not None and fit is not None and fit > roi:
        raise BayespsfInputError(f"{names[1]} ({fit}) must be at most {names[0]} ({roi})")


def molecule_pixels(molecules) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ids, rows, cols)``: each molecule's id and nearest pixel (halves rounded up)."""
    if not isinstance(molecules, pd.DataFrame):
        raise BayespsfInputError(
            f"molecules must be a DataFrame with columns molecule, x, y; got {type(molecules)}"
        )
    missing = [c for c in ("molecule", "x", "y") if c not in molecules.columns]
    if missing:
        raise BayespsfInputError(f"molecules: missing column(s) {', '.join(missing)}")
    ids = molecules["molecule"].to_numpy()
    if len(ids) == 0:
        raise BayespsfInputError("molecules: the table has no rows")
    if len(np.unique(ids)) != len(ids):
        raise BayespsfInputError("molecules: the molecule ids must be unique")
    x, y = (_numbers(molecules, name) for name in ("x", "y"))
    return ids, np.floor(y + 0.5).astype(np.int64), np.floor(x + 0.5).astype(np.int64)


def _numbers(molecules: pd.DataFrame, name: str) -> np.ndarray:
    """A column of positions as finite floats: text (which NumPy would parse) is refused."""
    values = molecules[name].to_numpy()
    text = [v for v in values if isinstance(v, str | bytes)] if values.dtype.kind in "OSU" else []
    if text:
        raise BayespsfInputError(
            f"molecules.{name}: positions must be numbers (camera pixels), got text such as "
            f"{text[0]!r} in {len(text)} row(s); convert the column (pandas.to_numeric) or "
            "read the table with numeric columns"
        )
    return finite_array(f"molecules.{name}", values)


def open_movie(movie) -> Movie:
    """A Movie, or a path opened with ``read_movie``."""
    if isinstance(movie, Movie):
        return movie
    if isinstance(movie, str | Path):
        return read_movie(movie)
    raise BayespsfInputError(f"movie must be a bayespsf Movie or a path, got {type(movie)}")


def frame_span(movie: Movie, frames) -> range:
    """The frames asked for (None: all; a slice or range of step 1) as a range."""
    if frames is None:
        return range(movie.n_frames)
    if not isinstance(frames, slice | range):
        raise BayespsfInputError(f"frames must be None, a slice or a range, got {frames!r}")
    ends = (frames.start, frames.stop) if isinstance(frames, slice) else ()
    if any(end is not None and not -movie.n_frames <= end <= movie.n_frames for end in ends):
        raise BayespsfInputError(  # a slice would be clipped to the movie without a word
            f"frames {frames!r} reach beyond the movie's {movie.n_frames} frames (0 to "
            f"{movie.n_frames - 1}, or -{movie.n_frames} to -1 from the end)"
        )
    span = range(movie.n_frames)[frames] if isinstance(frames, slice) else frames
    if span.step != 1 or span.start < 0 or span.stop > movie.n_frames or len(span) == 0:
        raise BayespsfInputError(
            f"frames must be consecutive frames within 0..{movie.n_frames - 1}, got {frames!r}"
        )
    return span


def iter_rois(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    *,
    roi: int = 25,
    fit: int = 15,
    frames: slice | range | None = None,
    block: int = 64,
    progress: bool | None = None,
    desc: str | None = None,
) -> Iterator[RoiStack]:
    """ROIs one block of frames at a time.

    Parameters
    ----------
    movie, molecules, roi, fit, frames
        As ``cut_rois``.
    block : int, default 64
        Frames per yielded stack.
    progress : bool, optional
        A progress bar of frames on stderr (default: when stderr is a terminal).
    desc : str, optional
        The progress bar's name.

    Yields
    ------
    RoiStack
        The ROIs of at most ``block`` frames, ordered by molecule, then frame, with their
        table (``molecule``, ``frame``, ``row0``, ``col0``).

    Raises
    ------
    BayespsfInputError
        As ``cut_rois``; a ``block`` that is not a whole number >= 1.

    See Also
    --------
    cut_rois : all the ROIs at once.

    Notes
    -----
    Only one block (``block * M * roi**2`` values for ``M`` molecules, and the rows the ROIs
    span) is in memory.
    """
    plan = _Plan(movie, molecules, roi, fit, frames)
    with progress_bar(len(plan.span), progress, unit="frame", desc=desc) as bar:
        for first, cut in plan.blocks(block):
            table = plan.table(first, first + cut.shape[1])
            yield RoiStack(cut.reshape(-1, roi, roi), table, fit)
            bar.update(cut.shape[1])


def cut_rois(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    *,
    roi: int = 25,
    fit: int = 15,
    frames: slice | range | None = None,
    block: int = 64,
) -> RoiStack:
    """Cut a ``roi`` × ``roi`` ROI around every molecule in every frame.

    Parameters
    ----------
    movie : Movie or path
        Read ``block`` frames at a time (``Movie.frames``), never whole.
    molecules : pandas.DataFrame
        Columns ``molecule`` (unique ids), ``x``, ``y`` (camera pixels, picasso's convention:
        column ``j``'s centre is ``x = j``). Other columns are ignored.
    roi, fit : int, default 25 and 15
        Odd sides in pixels of the cut (the paper's 25) and of its fitted centre (15).
    frames : slice or range, optional
        Consecutive frames to cut (default all).
    block : int, default 64
        Frames read at a time.

    Returns
    -------
    RoiStack
        ``M * F`` ROIs ``(M * F, roi, roi)`` in the movie's data type (ADU), ordered by
        molecule, then frame, with their table: ``molecule``, ``frame``, ``row0``, ``col0``
        (the movie pixel of each ROI's top-left corner).

    Raises
    ------
    BayespsfInputError
        Even sizes, ``fit > roi``, a bad molecule table, or molecules whose ROI would leave
        the frame (named, with their positions).

    See Also
    --------
    iter_rois : the same ROIs one block of frames at a time.
    RoiStack.central : the fitted centre of each ROI.
    RoiStack.periphery_background : the background from each ROI's periphery.

    Notes
    -----
    The result holds ``M * F * roi**2`` values in the movie's data type; use ``iter_rois``
    for movies whose ROIs do not fit in memory.
    """
    plan = _Plan(movie, molecules, roi, fit, frames)
    start = plan.span.start
    counts = np.empty((len(plan.ids), len(plan.span), roi, roi), plan.movie.dtype)
    for first, cut in plan.blocks(block):
        counts[:, first - start : first - start + cut.shape[1]] = cut
    table = plan.table(start, plan.span.stop)
    return RoiStack(counts.reshape(-1, roi, roi), table, fit)


class _Plan:
    """Where the ROIs of a set of molecules lie, checked once; ``blocks`` cuts them."""

    def __init__(self, movie, molecules, roi, fit, frames):
        self.movie = open_movie(movie)
        check_sizes(roi, fit)
        self.ids, rows, cols = molecule_pixels(molecules)
        self.roi = int(roi)
        self.row0, self.col0 = rows - roi // 2, cols - roi // 2
        _, height, width = self.movie.shape
        outside = (self.row0 < 0) | (self.col0 < 0)
        outside |= (self.row0 + roi > height) | (self.col0 + roi > width)
        if outside.any():
            named = ", ".join(
                f"{m} (x={x:g}, y={y:g})"
                for m, x, y in zip(
                    self.ids[outside],
                    molecules["x"][outside],
                    molecules["y"][outside],
                    strict=True,
                )
            )
            raise BayespsfInputError(
                f"molecules: {outside.sum()} ROI(s) of {roi}x{roi} pixels would leave the "
                f"{height}x{width} frame: molecule(s) {named}"
            )
        self.span = frame_span(self.movie, frames)

    def table(self, first: int, last: int) -> pd.DataFrame:
        """The table of frames ``first..last - 1``, ordered by molecule, then frame."""
        k = last - first
        return pd.DataFrame(
            {
                "molecule": np.repeat(self.ids, k),
                "frame": np.tile(np.arange(first, last), len(self.ids)),
                "row0": np.repeat(self.row0, k),
                "col0": np.repeat(self.col0, k),
            }
        )

    def blocks(self, block: int) -> Iterator[tuple[int, np.ndarray]]:
        """``(first frame, ROIs (M, k, roi, roi))`` per block of ``block`` frames, reading
        only the rows the ROIs span."""
        if isinstance(block, bool) or not isinstance(block, int | np.integer) or block < 1:
            raise BayespsfInputError(f"block must be a whole number of frames >= 1, got {block!r}")
        top, bottom = int(self.row0.min()), int(self.row0.max()) + self.roi
        offsets = np.arange(self.roi)
        r = (self.row0 - top)[:, None, None] + offsets[None, :, None]
        c = self.col0[:, None, None] + offsets[None, None, :]
        for first in range(self.span.start, self.span.stop, block):
            data = self.movie.frames(
                first, min(first + block, self.span.stop), rows=slice(top, bottom)
            )
            yield first, data[:, r, c].transpose(1, 0, 2, 3)
