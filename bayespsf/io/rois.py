"""Reading ROI stacks: NumPy (.npy) and TIFF (.tif/.tiff, via tifffile, page by page).

The checks of a file (it exists, is not a directory, has a known extension, is a TIFF whose
chain of pages is whole and whose pages share one shape) are shared with
``bayespsf.movie.read_movie``.
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError


def read_rois(path: str | os.PathLike) -> np.ndarray:
    """Read a stack of square ROIs from a NumPy or TIFF file.

    Parameters
    ----------
    path : str or path-like
        A ``.npy`` file, or a ``.tif``/``.tiff`` file read page by page (one ROI per page).

    Returns
    -------
    ndarray, shape (n, roi, roi)
        The counts in ADU, as stored (a single 2-D ROI becomes ``(1, roi, roi)``); ``roi``
        is odd.

    Raises
    ------
    BayespsfInputError
        Naming the file and the problem: missing, a directory, not a regular file (a named
        pipe, socket or device: refused before it is opened), unreadable or damaged, unknown
        extension, no images, TIFF pages of different shapes (named), wrong number of
        dimensions, non-square or even-sized ROIs, complex, boolean or non-finite values.

    See Also
    --------
    bayespsf.movie.read_movie : reads a whole movie (the file checks are shared).
    bayespsf.fit_mle, bayespsf.sample_many : analyse the stack.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> import bayespsf
    >>> counts, truth = bayespsf.simulate(bayespsf.load_scene("paper-fig3"), 2, seed=1)
    >>> path = Path(tempfile.mkdtemp()) / "rois.npy"
    >>> np.save(path, counts)
    >>> bayespsf.read_rois(path).shape
    (2, 19, 19)
    """
    path = checked_path(path, (".npy", ".tif", ".tiff"), "a ROI stack", ".npy or .tif")
    with named_read_errors(path):
        npy = path.suffix.lower() == ".npy"
        data = np.load(path, allow_pickle=False) if npy else _read_tiff(path)
    try:
        data = finite_array("counts", data)
    except BayespsfInputError as exc:
        raise BayespsfInputError(f"{path}: {exc}") from None
    if data.size == 0:
        raise BayespsfInputError(f"{path}: no ROIs (the stack's shape is {data.shape})")
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3 or data.shape[1] != data.shape[2] or data.shape[1] % 2 == 0:
        raise BayespsfInputError(
            f"{path}: expected square ROIs of odd size, shape (n, roi, roi); got {data.shape}"
        )
    return data


def checked_path(path, suffixes: tuple[str, ...], what: str, extensions: str) -> Path:
    """``path`` as a ``Path`` that exists, is a regular file and ends in one of ``suffixes``;
    ``what`` and ``extensions`` name the expected kind of file in the messages.

    Anything else is refused before it is opened: opening a named pipe that nobody writes to
    waits forever, and a device or socket is no stored file either."""
    path = Path(path)
    if not path.exists():
        raise BayespsfInputError(f"{path}: no such file")
    if path.is_dir():
        raise BayespsfInputError(f"{path} is a directory, not {what} ({extensions})")
    if not path.is_file():
        raise BayespsfInputError(
            f"{path} is {special_file_kind(path)}, not a regular file: {what} is read from a "
            f"file on disk ({extensions}); copy the data to one and give its path"
        )
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise BayespsfInputError(f"{path}: unknown file type {suffix!r} (use {extensions})")
    return path


def special_file_kind(path: Path) -> str:
    """What a path that exists but is neither a directory nor a regular file is, in words.

    Parameters
    ----------
    path : pathlib.Path
        An existing path.

    Returns
    -------
    str
        ``"a named pipe (FIFO)"``, ``"a socket"``, ``"a character device"``,
        ``"a block device"`` or ``"a special file"``.
    """
    mode = path.stat().st_mode
    kinds = (
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    )
    return next((words for test, words in kinds if test(mode)), "a special file")


@contextmanager
def named_read_errors(path: Path) -> Iterator[None]:
    """Turn whatever a reader raises for a damaged file into a ``BayespsfInputError`` naming
    ``path`` (the readers raise many kinds); our own errors pass through."""
    try:
        yield
    except BayespsfInputError:
        raise
    except Exception as exc:
        raise BayespsfInputError(f"{path}: cannot read it, damaged or truncated ({exc})") from exc


def _read_tiff(path: Path) -> np.ndarray:
    """Every page of a TIFF, read page by page; pages of different shapes are an error that
    names them (reading the first page's series alone analysed only part of such a file)."""
    with open_tiff(path) as (tif, complaints):
        return _tiff_pages(path, tif, complaints)


@contextmanager
def open_tiff(path: Path):
    """An open ``tifffile.TiffFile`` and the ``_TiffComplaints`` that collect what tifffile
    logs while it is open (``tiff_page_shape`` judges them)."""
    import tifffile

    complaints = _TiffComplaints()
    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.addHandler(complaints)
    logger.setLevel(logging.WARNING)  # another library may have raised it (picasso: CRITICAL)
    try:
        with tifffile.TiffFile(path) as tif:
            yield tif, complaints
    finally:
        logger.setLevel(level)
        logger.removeHandler(complaints)


class _TiffComplaints(logging.Handler):
    """tifffile's logged warnings while a file is read: it logs, and stops, where a truncated
    file's chain of pages breaks ("invalid page offset"), returning the pages before it; it also
    logs, and reads on, for a file without pages or with an unreadable tag."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def tiff_page_shape(
    path: Path, tif, complaints: _TiffComplaints, what: str = "a ROI stack", items: str = "ROIs"
) -> tuple[int, ...]:
    """The one shape of every page of an open TIFF, after checking the file: no pages, a broken
    chain of pages (truncated), pages of different shapes (named) and pages without image data
    are errors naming ``path``; ``what`` and ``items`` name what the file should hold.

    Only what tifffile logs while walking the chain of pages marks a file as truncated: a tag it
    cannot read (logged on opening) leaves the image readable, as ``tifffile.imread`` reads it.
    """
    opening = list(complaints.messages)
    complaints.messages.clear()
    pages = tif.pages
    count = len(pages)  # walks the chain of pages: a break is logged here
    if count == 0:
        why = f" ({opening[0]})" if opening else ""
        raise BayespsfInputError(f"{path}: a TIFF with no images, only a header{why}")
    if complaints.messages:
        raise BayespsfInputError(f"{path}: damaged or truncated TIFF ({complaints.messages[0]})")
    shapes = [page.shape for page in pages]
    first = shapes[0]
    if len(set(shapes)) > 1:
        odd = [i for i, shape in enumerate(shapes) if shape != first]
        listed = ", ".join(f"page {i} {shapes[i]}" for i in odd[:5])
        raise BayespsfInputError(
            f"{path}: its pages differ in shape (page 0 {first}; {listed}"
            f"{' ...' if len(odd) > 5 else ''}); {what} has pages of one shape"
        )
    if first == () or 0 in first:  # an image directory without (or with empty) image data
        raise BayespsfInputError(
            f"{path}: no {items}, its pages hold no image data (shape {first})"
        )
    return first


def _tiff_pages(path: Path, tif, complaints: _TiffComplaints) -> np.ndarray:
    """The pages of an open TIFF as one array (checked by ``tiff_page_shape``)."""
    tiff_page_shape(path, tif, complaints)
    pages = tif.pages
    if len(pages) == 1:
        return pages[0].asarray()
    return np.stack([page.asarray() for page in pages])
