"""Reading movies: TIFF, OME-TIFF, ImageJ hyperstacks, multi-file series and ``.npy``, frame
by frame, never the whole movie at once."""

from __future__ import annotations

import glob
import re
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from bayespsf.errors import BayespsfInputError
from bayespsf.io.rois import checked_path, named_read_errors
from bayespsf.movie._frames import NpyFrames
from bayespsf.movie._metadata import FileMetadata
from bayespsf.movie._tiff import ChannelsError as ChannelsError  # raised by read_movie
from bayespsf.movie._tiff import check_channel, checked_dtype, tiff_frames
from bayespsf.psf import check_geometry

_TIFF = (".tif", ".tiff")
#: The largest pixel value of a floating-point movie, in ADU: float64 holds whole counts
#: exactly below it (2**53), and their squares without overflow.
MAX_COUNT = 2.0**53


def read_movie(path: str | Path | Sequence[str | Path], *, channel: int | None = None) -> Movie:
    """Open a movie for reading frame by frame.

    Parameters
    ----------
    path : str, Path or list of them
        A ``.tif``/``.tiff`` file (plain multi-page TIFF, OME-TIFF or ImageJ hyperstack), a
        ``.npy`` file of shape ``(frames, height, width)`` (or one 2-D frame), or several TIFF
        files forming one movie: a list (taken in the order given) or a glob pattern such as
        ``"run1_*.tif"`` (matches taken in name order, numbers compared as numbers). The
        frames of a series are concatenated; its files must have frames of one shape and type.
    channel : int, optional
        Which channel of a multi-channel OME or ImageJ file to read (from 0). Required when
        the file has more than one channel.

    Returns
    -------
    Movie
        Frames ``(n_frames, height, width)`` in the file's data type (counts, ADU). Nothing
        is read but the file's structure and metadata. Uncompressed image data are
        memory-mapped, compressed data decoded page by page when frames are asked for.

    Raises
    ------
    BayespsfInputError
        Naming the file and the problem: missing, a directory, unknown extension, unreadable,
        damaged or truncated, no images, pages of different shapes (named), frames that are
        not 2-D, complex or boolean values, no frames, several channels without ``channel``
        (``ChannelsError``, its subclass), files of a series that disagree.

    See Also
    --------
    Movie : the frames on demand, by block, or as a dask array.
    bayespsf.movie.project : a temporal projection with bounded memory.
    bayespsf.movie.find_molecules : detection to selection on a movie.

    Notes
    -----
    T and Z (and any other axis but C) of an OME or ImageJ file become frames, flattened in
    the file's order (``Movie.metadata["axes"]`` says which). ``pixel_size`` (nm) and
    ``exposure`` (s) come from the OME metadata (``PhysicalSizeX`` in its unit; a plane's
    ``ExposureTime``, else ``TimeIncrement``) or the ImageJ metadata (the XResolution tag in
    ``unit``; ``finterval``); ``TimeIncrement`` and ``finterval`` are the frame interval, an
    upper bound on the exposure. Where the file says nothing they are None, and the caller
    takes them from the user's camera file (its ``[geometry] pixel_size``).

    Examples
    --------
    A small simulated OME-TIFF movie (the ``paper-movie`` scene's EMCCD, 79 nm pixels):

    >>> import tempfile
    >>> from pathlib import Path
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 20, "height": 64, "width": 64, "molecules": 3, "dark_frames": 0}
    ... )
    >>> made = bayespsf.simulate_movie(scene, seed=1, out=Path(tempfile.mkdtemp()) / "m")
    >>> movie = bayespsf.read_movie(made.files["movie"])
    >>> movie.shape, movie.dtype.name, movie.pixel_size, movie.metadata["pixel_size"]
    ((20, 64, 64), 'uint16', 79.0, 'OME')
    >>> movie.frames(0, 5).shape  # only these frames are read
    (5, 64, 64)
    """
    paths = _paths(path)
    suffixes = _TIFF if len(paths) > 1 else (*_TIFF, ".npy")
    extensions = "a list of .tif files" if len(paths) > 1 else ".tif, .tiff or .npy"
    readers, calibrations = [], []
    for file in paths:
        file = checked_path(file, suffixes, "a movie", extensions)
        if file.suffix.lower() == ".npy":
            reader, calibration = _npy_frames(file, channel), FileMetadata()
        else:
            reader, calibration = tiff_frames(file, channel)
        readers.append(reader)
        calibrations.append(calibration)
    first = readers[0]
    for reader in readers[1:]:
        if (reader.frame_shape, reader.dtype) != (first.frame_shape, first.dtype):
            raise BayespsfInputError(
                f"{reader.path}: frames {reader.frame_shape} of {reader.dtype}, but {first.path} "
                f"has frames {first.frame_shape} of {first.dtype}; the files of one movie "
                "have frames of one shape and type"
            )
    movie = Movie(readers, calibrations[0], channel)
    if movie.n_frames == 0 or 0 in movie.shape:
        raise BayespsfInputError(f"{movie.path}: an empty movie (shape {movie.shape})")
    return movie


class Movie:
    """A movie on disk: frames ``(n_frames, height, width)`` read on demand.

    Made by ``read_movie``; not constructed directly.

    Parameters
    ----------
    readers : iterable of frame readers
        One per file, in frame order (internal: TIFF page or ``.npy`` readers).
    calibration : FileMetadata
        The pixel size and exposure read from the first file's metadata.
    channel : int or None
        The channel read (for reopening the files).

    Attributes
    ----------
    path : Path or tuple of Path
        The file, or the files of a series in frame order.
    shape : tuple of int
        ``(frames, height, width)``.
    n_frames : int
        Number of frames (also ``len(movie)``).
    dtype : numpy.dtype
        The file's data type (in native byte order).
    pixel_size : float or None
        Pixel size in nm from the file's metadata.
    exposure : float or None
        Exposure (or, where only that is recorded, frame interval) in s from the metadata.
    metadata : dict
        Where each came from: ``metadata["pixel_size"]`` and ``metadata["exposure"]`` are
        ``"OME"``, ``"ImageJ"`` or None; ``exposure_field`` names the field, ``axes`` the
        file's axes and ``channel`` the channel read, where these apply.

    See Also
    --------
    read_movie : opens one.

    Notes
    -----
    Frames are read in the file's data type; a movie used as an array (``movie[10:20]``,
    ``to_dask``) reads only the frames indexed. Files decoded page by page stay open until
    ``close`` (or the end of a ``with`` block, or the movie's collection).
    """

    ndim = 3

    def __init__(self, readers: Iterable, calibration: FileMetadata, channel: int | None) -> None:
        self._readers = list(readers)
        self._starts = np.cumsum([0] + [r.n for r in self._readers])
        self._channel = channel
        paths = tuple(r.path for r in self._readers)
        self.path: Path | tuple[Path, ...] = paths[0] if len(paths) == 1 else paths
        self.n_frames = int(self._starts[-1])
        self.shape: tuple[int, int, int] = (self.n_frames, *self._readers[0].frame_shape)
        self.dtype: np.dtype = self._readers[0].dtype
        self.pixel_size = calibration.pixel_size
        self.exposure = calibration.exposure
        self.metadata = dict(calibration.metadata)

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return self.describe()

    def describe(self, pixel_size: float | None = None) -> str:
        """The movie in one line, as its repr, with a pixel size its metadata do not give.

        Parameters
        ----------
        pixel_size : float, optional
            The pixel side in nm that a run uses (``--pixel-size``, a camera file's, or the
            metadata's); where the metadata give another, both are shown.

        Returns
        -------
        str
        """
        name = self.path
        if isinstance(name, tuple):
            name = f"{name[0]} + {len(name) - 1} files"
        size = time = "None"
        if pixel_size is not None:
            _, a = check_geometry(1, pixel_size)  # a named error for a size that is not one
            size = f"{a:g} nm"
        if self.pixel_size is not None:
            read = f"{self.pixel_size:.4g} nm ({self.metadata['pixel_size']})"
            same = pixel_size is None or np.isclose(a, self.pixel_size, rtol=1e-9, atol=0.0)
            size = read if same else f"{size}, not the metadata's {read}"
        if self.exposure is not None:
            time = f"{self.exposure:.4g} s ({self.metadata['exposure']})"
        return (
            f"Movie('{name}', frames={self.shape[0]}, height={self.shape[1]}, "
            f"width={self.shape[2]}, dtype={self.dtype}, pixel_size={size}, exposure={time})"
        )

    def frames(
        self, start: int = 0, stop: int | None = None, *, rows: slice | None = None
    ) -> np.ndarray:
        """Frames ``start`` to ``stop`` (excluded; Python slice rules) as an array ``(k, h, w)``
        in the file's data type; ``rows`` (a slice) reads only those rows of each frame.

        A floating-point movie's NaN or infinite pixel, or one beyond ``MAX_COUNT`` ADU,
        raises ``BayespsfInputError`` naming the frame and pixel: camera counts are finite
        whole numbers (float64 holds them exactly below 2**53, and their squares without
        overflow), and every analysis reads through here.

        Parameters
        ----------
        start, stop : int, optional
            The first frame and the one after the last (default: all).
        rows : slice, optional
            The rows of each frame to read (default: all).

        Returns
        -------
        ndarray, shape (k, h, w)

        Raises
        ------
        BayespsfInputError
            For a NaN or infinite pixel, or one beyond ``MAX_COUNT``.
        """
        span = range(self.n_frames)[start:stop]
        rows = slice(None) if rows is None else rows
        parts = []
        for offset, reader in zip(self._starts, self._readers, strict=False):
            low, high = max(span.start, offset), min(span.stop, offset + reader.n)
            if low < high:
                parts.append(reader.read(int(low - offset), int(high - offset), rows))
        if not parts:
            return np.empty((0, len(range(self.shape[1])[rows]), self.shape[2]), self.dtype)
        data = parts[0] if len(parts) == 1 else np.concatenate(parts)
        if not np.issubdtype(data.dtype, np.inexact):
            return data
        # a type too narrow to reach MAX_COUNT (float16) is checked for finite values alone;
        # a NaN makes the extremes NaN, which fail both comparisons
        limit = min(MAX_COUNT, float(np.finfo(data.dtype).max))
        if not (data.size == 0 or (data.min() >= -limit and data.max() <= limit)):
            wrong = ~(np.abs(data) <= limit)  # NaN, infinite, or beyond whole counts
            k, r, c = np.argwhere(wrong)[0]
            first = range(self.shape[1])[rows][r]
            bad = int(np.count_nonzero(wrong[k]))
            what = "NaN or infinite" if not np.isfinite(data[k, r, c]) else "beyond +-2**53"
            raise BayespsfInputError(
                f"{self.path}: frame {span.start + k} has {bad} NaN, infinite or vast pixel(s), "
                f"the first {what} at row {first}, column {c} ({data[k, r, c]}); camera counts "
                "are finite and below 2**53 ADU: replace them (with the camera's offset, say) or "
                "crop them out"
            )
        return data

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i``, from 0 to ``n_frames - 1``, as an array ``(h, w)``.

        A negative index is refused, not counted from the end (``movie[-1]`` indexes as an
        array does): ``FrameIndexError``, a ``BayespsfInputError`` and an ``IndexError``,
        naming the index and the movie's frames.

        Parameters
        ----------
        i : int

        Returns
        -------
        ndarray, shape (h, w)
        """
        if isinstance(i, bool) or not isinstance(i, int | np.integer):
            raise FrameIndexError(f"frame index must be a whole number, got {i!r}")
        if not 0 <= i < self.n_frames:
            raise FrameIndexError(
                f"frame {int(i)} is not a frame of {self.path}: its {self.n_frames} frames are "
                f"0 to {self.n_frames - 1}"
                + (" (a negative index is not counted from the end)" if i < 0 else "")
            )
        return self.frames(int(i), int(i) + 1)[0]

    def blocks(
        self, size: int, start: int = 0, stop: int | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        """``(first frame, frames)`` for consecutive blocks of ``size`` frames (the last may
        be shorter) from ``start`` to ``stop``; one block is in memory at a time.

        Parameters
        ----------
        size : int
            Frames per block.
        start, stop : int, optional
            As ``frames``.

        Yields
        ------
        first : int
            The block's first frame.
        frames : ndarray, shape (k, h, w)
        """
        if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 1:
            raise BayespsfInputError(f"size must be a whole number of frames >= 1, got {size!r}")
        span = range(self.n_frames)[start:stop]
        for first in range(span.start, span.stop, size):
            yield first, self.frames(first, min(first + size, span.stop))

    def __getitem__(self, key) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        head, rest = key[0], key[1:]
        if isinstance(head, int | np.integer):  # as an array: negative from the end
            if not -self.n_frames <= head < self.n_frames:
                raise FrameIndexError(
                    f"index {int(head)} is out of range for the {self.n_frames} frames of "
                    f"{self.path} (-{self.n_frames} to {self.n_frames - 1})"
                )
            return self.frame(int(head) % self.n_frames)[rest]
        if not isinstance(head, slice):
            raise TypeError(f"index a movie's frames with an integer or a slice, not {head!r}")
        span = range(self.n_frames)[head]
        if len(span) == 0:
            return self.frames(0, 0)[(slice(None), *rest)]
        low, high = min(span[0], span[-1]), max(span[0], span[-1]) + 1
        return self.frames(low, high)[np.asarray(span) - low][(slice(None), *rest)]

    def to_dask(self, frames_per_chunk: int = 64):
        """A lazy ``dask.array`` of the movie, chunked by ``frames_per_chunk`` frames; frames
        are read when a chunk is computed.

        Parameters
        ----------
        frames_per_chunk : int, optional

        Returns
        -------
        dask.array.Array
            Shape ``(n_frames, h, w)``.
        """
        import dask.array as da
        from dask.base import tokenize

        files = self.path if isinstance(self.path, tuple) else (self.path,)
        stamp = [(str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in files]
        return da.from_array(
            self,
            chunks=(frames_per_chunk, *self.shape[1:]),
            name=f"movie-{tokenize(stamp, self._channel)}",
            meta=np.empty((0, 0, 0), self.dtype),
            lock=False,
            fancy=False,
        )

    def close(self) -> None:
        """Close the files held open (a later read reopens them)."""
        for reader in self._readers:
            getattr(reader, "close", lambda: None)()

    def __enter__(self) -> Movie:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __reduce__(self):  # reopened from the files, not copied (dask's distributed workers)
        files = list(self.path) if isinstance(self.path, tuple) else self.path
        return _reopen, (files, self._channel)


class FrameIndexError(BayespsfInputError, IndexError):
    """A frame index outside the movie (an ``IndexError`` too, so that iterating over a
    movie's frames ends at its last one)."""


def _reopen(path, channel):
    return read_movie(path, channel=channel)


def _paths(path) -> list[Path]:
    """The files of a movie: one path, a list of paths, or a glob pattern's matches in name
    order (numbers compared as numbers: ``frame_2`` before ``frame_10``)."""
    if isinstance(path, list | tuple):
        if not path:
            raise BayespsfInputError("an empty list of movie files")
        return [Path(p) for p in path]
    text = str(path)
    if isinstance(path, str) and any(c in text for c in "*?[") and not Path(text).exists():
        matches = sorted(glob.glob(text), key=_name_order)
        if not matches:
            raise BayespsfInputError(f"{text}: no files match this pattern")
        return [Path(m) for m in matches]
    return [Path(path)]


def _name_order(name: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _npy_frames(path: Path, channel: int | None) -> NpyFrames:
    with named_read_errors(path):
        data = np.load(path, mmap_mode="r", allow_pickle=False)
    check_channel(path, channel, 1, [])
    dtype = checked_dtype(path, data.dtype)
    if data.ndim not in (2, 3):
        raise BayespsfInputError(
            f"{path}: an array of {data.ndim} dimensions {data.shape}; a movie is "
            "(frames, height, width) or one 2-D frame"
        )
    return NpyFrames(path, data.shape, dtype)
