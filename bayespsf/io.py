"""Reading ROI stacks: NumPy (.npy) and TIFF (.tif/.tiff, via tifffile, page by page)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from bayespsf._checks import finite_array
from bayespsf.errors import BayespsfInputError


def read_rois(path) -> np.ndarray:
    """A stack of square ROIs ``(n, roi, roi)`` (a single 2-D ROI becomes ``(1, roi, roi)``).

    Errors name the file and the problem: missing, a directory, unreadable or damaged, unknown
    extension, no images, TIFF pages of different shapes (named), wrong number of dimensions,
    non-square or even-sized ROIs, complex, boolean or non-finite values.
    """
    path = Path(path)
    if not path.exists():
        raise BayespsfInputError(f"{path}: no such file")
    if path.is_dir():
        raise BayespsfInputError(f"{path} is a directory, not a ROI stack (.npy or .tif)")
    suffix = path.suffix.lower()
    if suffix not in (".npy", ".tif", ".tiff"):
        raise BayespsfInputError(f"{path}: unknown file type {suffix!r} (use .npy or .tif)")
    try:
        data = np.load(path, allow_pickle=False) if suffix == ".npy" else _read_tiff(path)
    except BayespsfInputError:
        raise
    except Exception as exc:  # the readers raise many kinds for a damaged file
        raise BayespsfInputError(f"{path}: cannot read it, damaged or truncated ({exc})") from exc
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


def _read_tiff(path: Path) -> np.ndarray:
    """Every page of a TIFF, read page by page; pages of different shapes are an error that
    names them (reading the first page's series alone analysed only part of such a file)."""
    import tifffile

    complaints = _TiffComplaints()
    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.addHandler(complaints)
    logger.setLevel(logging.WARNING)  # another library may have raised it (picasso: CRITICAL)
    try:
        with tifffile.TiffFile(path) as tif:
            return _tiff_pages(path, tif, complaints)
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


def _tiff_pages(path: Path, tif, complaints: _TiffComplaints) -> np.ndarray:
    """The pages of an open TIFF as one array. Only what tifffile logs while walking the chain
    of pages marks a file as truncated: a tag it cannot read (logged on opening) leaves the
    image readable, as ``tifffile.imread`` reads it."""
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
            f"{' ...' if len(odd) > 5 else ''}); a ROI stack has pages of one shape"
        )
    if first == () or 0 in first:  # an image directory without (or with empty) image data
        raise BayespsfInputError(f"{path}: no ROIs, its pages hold no image data (shape {first})")
    if count == 1:
        return pages[0].asarray()
    return np.stack([page.asarray() for page in pages])
