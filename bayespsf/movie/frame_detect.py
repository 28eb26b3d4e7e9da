"""Detection frame by frame (blinking data): ``detect`` on every frame of a movie, each
frame's noise and threshold from the camera law for one frame (``bayespsf.movie.detect``
states the test). ``detect_frame`` is one frame already read, so that frames can be detected
wherever they are sent (``bayespsf.analysis.localize_frames``' workers)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf.movie._metadata import resolve_pixel_size
from bayespsf.movie._noise import saturation_level
from bayespsf.movie._peaks import STATUSES
from bayespsf.movie.detect import _detect_photons
from bayespsf.movie.extract import frame_span, open_movie

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from bayespsf.cameras import Camera
    from bayespsf.model import Model
    from bayespsf.movie.read import Movie

__all__ = ["detect_frame", "detect_frames", "frame_settings", "iter_detect_frames"]


def frame_settings(
    movie: Movie | str | Path,
    *,
    psf_sd: float,
    pixel_size: float | None = None,
    camera: Camera | Model | None = None,
    **options,
) -> dict:
    """``detect_frame``'s keywords for the frames of ``movie``, as ``iter_detect_frames``
    takes them.

    Parameters
    ----------
    movie : Movie or path
        From ``read_movie`` (or a path it opens).
    psf_sd, pixel_size, camera, **options
        As ``iter_detect_frames``.

    Returns
    -------
    dict
        ``psf_sd``, ``pixel_size`` (given, the Model's or the movie's metadata's),
        ``camera``, ``saturation`` (the camera's or the data type's full scale),
        ``source`` (the movie's path) and ``options``.

    Raises
    ------
    BayespsfInputError
        A movie that ``read_movie`` refuses; no pixel size from the arguments or the movie,
        or one outside 1 nm to 10 µm.
    """
    movie = open_movie(movie)
    return dict(
        psf_sd=psf_sd,
        pixel_size=resolve_pixel_size(pixel_size, camera, movie),
        camera=camera,
        saturation=saturation_level(movie.dtype, camera),
        source=str(movie.path),
        **options,
    )


def detect_frame(
    frame: ArrayLike,
    index: int,
    *,
    psf_sd: float,
    pixel_size: float,
    camera: Camera | Model | None = None,
    saturation: float | None = None,
    source: str = "movie",
    **options,
) -> pd.DataFrame:
    """``detect`` on one frame of a movie in counts (ADU), as ``iter_detect_frames`` does.

    Parameters
    ----------
    frame : array_like, shape (h, w)
        The frame in counts (ADU).
    index : int
        Its number in the movie: the table's ``frame`` column, and named in errors.
    psf_sd : float
        SD of the spot's Gaussian in nm, as ``detect``.
    pixel_size : float
        Pixel side in nm.
    camera : Camera or Model, optional
        As ``detect_movie``, for one frame: counts to photons, the noise from the camera law
        at each pixel's background, the threshold from its exact tail.
    saturation : float, optional
        The count at which the movie saturates (``saturated`` flags the pixels at or above
        it); None: no pixel is flagged.
    source : str, default "movie"
        The movie's name in errors (``"<source>: frame <index>"``).
    **options
        ``false_positives``, ``roi``, ``fit``, ``min_distance``: as ``detect``.

    Returns
    -------
    pandas.DataFrame
        A ``frame`` column, then ``detect``'s ``COLUMNS``.

    Raises
    ------
    BayespsfInputError
        As ``detect_movie``, naming the frame.

    See Also
    --------
    iter_detect_frames : every frame of a movie, read in blocks.
    """
    mask = None if saturation is None else np.asarray(frame) >= saturation
    what = f"{source}: frame {index}"
    table = _detect_photons(frame, 1, psf_sd, pixel_size, camera, options, mask, what)
    table.insert(0, "frame", index)
    return table


def iter_detect_frames(
    movie: Movie | str | Path,
    *,
    psf_sd: float,
    pixel_size: float | None = None,
    camera: Camera | Model | None = None,
    frames: slice | range | None = None,
    block: int = 16,
    **options,
) -> Iterator[pd.DataFrame]:
    """``detect`` on each frame in turn, one table per frame.

    Parameters
    ----------
    movie, psf_sd, pixel_size, camera, frames, **options
        As ``detect_movie`` (without ``projection``).
    block : int, default 16
        Frames read at a time.

    Yields
    ------
    pandas.DataFrame
        One frame's candidates: a ``frame`` column first, then ``detect``'s ``COLUMNS``
        (``molecule`` numbers the rows of that frame).

    See Also
    --------
    detect_frames : the same, concatenated into one table.
    """
    movie = open_movie(movie)
    span = frame_span(movie, frames)
    settings = frame_settings(movie, psf_sd=psf_sd, pixel_size=pixel_size, camera=camera, **options)
    for first, data in movie.blocks(block, span.start, span.stop):
        for i, frame in enumerate(data):
            yield detect_frame(frame, first + i, **settings)


def detect_frames(movie: Movie | str | Path, **options) -> pd.DataFrame:
    """Candidates frame by frame (blinking data): ``detect`` on every frame.

    Parameters
    ----------
    movie : Movie or path
        From ``read_movie`` (or a path it opens); counts in ADU.
    **options
        Keywords as ``detect_movie`` (``psf_sd`` required; ``pixel_size``, ``camera``,
        ``frames`` and ``detect``'s options), without ``projection``, plus ``block`` (frames
        read at a time, default 16).

    Returns
    -------
    pandas.DataFrame
        One table with a ``frame`` column before ``detect``'s ``COLUMNS``; ``molecule``
        numbers the rows of the whole table. ``attrs["detection"]`` holds the first frame's
        settings, the median ``noise_var`` over frames, the number of ``frames`` and the
        counts by status.

    Raises
    ------
    BayespsfInputError
        As ``detect_movie``.

    See Also
    --------
    iter_detect_frames : yields the per-frame tables instead.
    detect_movie : on a temporal projection (immobile molecules).

    Notes
    -----
    Memory: one block of frames and the table. With a camera, each frame's noise is the
    camera law's at its background (one frame).
    """
    tables = list(iter_detect_frames(movie, **options))
    settings = [t.attrs["detection"] for t in tables]
    table = pd.concat([t for t in tables if len(t)] or tables[:1], ignore_index=True)
    table["molecule"] = np.arange(len(table))
    table.attrs["detection"] = settings[0] | {
        "noise_var": float(np.median([s["noise_var"] for s in settings])),  # over frames
        "frames": len(tables),
        "counts": {s: int(np.count_nonzero(table["status"] == s)) for s in STATUSES},
    }
    return table
