"""Reading ROI stacks: NumPy (.npy) and TIFF (.tif/.tiff, via tifffile)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayespsf.errors import BayespsfInputError


def read_rois(path) -> np.ndarray:
    """A stack of square ROIs ``(n, roi, roi)`` (a single 2-D ROI becomes ``(1, roi, roi)``).

    Errors name the file and the problem: missing, unreadable, unknown extension, wrong
    number of dimensions, non-square or even-sized ROIs, non-finite values.
    """
    path = Path(path)
    if not path.exists():
        raise BayespsfInputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
        else:
            raise BayespsfInputError(f"{path}: unknown file type {suffix!r} (use .npy or .tif)")
    except BayespsfInputError:
        raise
    except Exception as exc:  # the readers raise many kinds for a damaged file
        raise BayespsfInputError(f"{path}: cannot read it ({exc})") from exc
    data = np.asarray(data, dtype=np.float64)
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3 or data.shape[1] != data.shape[2] or data.shape[1] % 2 == 0:
        raise BayespsfInputError(
            f"{path}: expected square ROIs of odd size, shape (n, roi, roi); got {data.shape}"
        )
    if not np.all(np.isfinite(data)):
        raise BayespsfInputError(f"{path}: contains NaN or infinite counts")
    return data
