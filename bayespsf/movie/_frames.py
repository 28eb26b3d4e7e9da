"""Frame readers: each reads frames ``[start, stop)`` of one file, and only those.

Every reader has ``path``, ``n`` (frames), ``frame_shape`` (h, w), ``dtype`` (native byte
order) and ``read(start, stop, rows) -> ndarray (k, len(rows), w)``, a new array in memory.
Memory-mapped readers map the file for the duration of one call only, so the pages they touch
leave the process's resident memory when the call returns.
"""

from __future__ import annotations

import threading
import weakref
from pathlib import Path

import numpy as np

from bayespsf.io.rois import named_read_errors


class NpyFrames:
    """A ``.npy`` file, memory-mapped (``np.load(mmap_mode="r")``) for each read; a 2-D array
    is one frame."""

    def __init__(self, path: Path, shape: tuple[int, ...], dtype: np.dtype):
        self.path = path
        self.n = 1 if len(shape) == 2 else shape[0]
        self.frame_shape = tuple(shape[-2:])
        self.dtype = dtype.newbyteorder("=")

    def read(self, start: int, stop: int, rows: slice) -> np.ndarray:
        with named_read_errors(self.path):
            data = np.load(self.path, mmap_mode="r", allow_pickle=False)
            data = data[None] if data.ndim == 2 else data
            return np.array(data[start:stop, rows], dtype=self.dtype)


class MappedPages:
    """Uncompressed TIFF image data at known byte offsets (one per frame), read through a
    memory map of the span of the frames asked for."""

    def __init__(self, path: Path, offsets, frame_shape, dtype: np.dtype, byteorder: str):
        self.path = path
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.n = len(self.offsets)
        self.frame_shape = tuple(frame_shape)
        self.dtype = dtype.newbyteorder("=")
        self._stored = dtype.newbyteorder(byteorder)

    def read(self, start: int, stop: int, rows: slice) -> np.ndarray:
        offsets = self.offsets[start:stop]
        h, w = self.frame_shape
        out = np.empty((len(offsets), len(range(h)[rows]), w), self.dtype)
        if len(offsets) == 0:
            return out
        low = int(offsets.min())
        high = int(offsets.max()) + h * w * self._stored.itemsize
        with named_read_errors(self.path):
            mapped = np.memmap(self.path, np.uint8, "r", offset=low, shape=high - low)
            for j, offset in enumerate(offsets):
                frame = np.ndarray((h, w), self._stored, buffer=mapped, offset=int(offset) - low)
                out[j] = frame[rows]
        return out


class DecodedPages:
    """TIFF pages read and decoded by tifffile one at a time (compressed or scattered data).

    The file is opened on the first read and stays open (closed by ``close`` or when the reader
    is collected); reads from several threads take turns.
    """

    def __init__(self, path: Path, pages, frame_shape, dtype: np.dtype):
        self.path = path
        self.pages = np.asarray(pages, dtype=np.int64)
        self.n = len(self.pages)
        self.frame_shape = tuple(frame_shape)
        self.dtype = dtype.newbyteorder("=")
        self._lock = threading.Lock()
        self._tif = None

    def _file(self):
        if self._tif is None:
            import tifffile

            self._tif = tifffile.TiffFile(self.path)
            self._closer = weakref.finalize(self, self._tif.close)
        return self._tif

    def read(self, start: int, stop: int, rows: slice) -> np.ndarray:
        pages = self.pages[start:stop]
        h, w = self.frame_shape
        out = np.empty((len(pages), len(range(h)[rows]), w), self.dtype)
        with self._lock, named_read_errors(self.path):
            tif = self._file()
            for j, page in enumerate(pages):
                out[j] = tif.pages[int(page)].asarray()[rows]
        return out

    def close(self) -> None:
        """Close the file (a later read opens it again)."""
        with self._lock:
            if self._tif is not None:
                self._closer()
                self._tif = None
