"""One TIFF file as frames: plain multi-page TIFF, OME-TIFF or ImageJ hyperstack.

The file is checked by the same code as ``bayespsf.io.read_rois`` (``tiff_page_shape``: no
pages, a broken chain of pages, pages of different shapes), then every frame's image data is
located without being read: at fixed byte offsets where it is stored uncompressed (read through
a memory map), as page numbers otherwise (decoded by tifffile, page by page).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bayespsf.errors import BayespsfInputError
from bayespsf.io.rois import named_read_errors, open_tiff, tiff_page_shape
from bayespsf.movie._frames import DecodedPages, MappedPages
from bayespsf.movie._metadata import FileMetadata, from_imagej, from_ome


def tiff_frames(path: Path, channel: int | None):
    """``(reader, calibration)`` of the TIFF at ``path``: T and Z (and any other axis but
    C) of an OME or ImageJ file become frames in the file's order; C picks ``channel``."""
    with named_read_errors(path), open_tiff(path) as (tif, complaints):
        page_shape = tiff_page_shape(path, tif, complaints, "a movie", "frames")
        if tif.is_ome or tif.is_imagej:
            return _series_frames(path, tif, channel)
        if len(page_shape) != 2:
            raise BayespsfInputError(
                f"{path}: its pages are {page_shape}, not 2-D images (colour or multi-sample "
                "pages are not movie frames)"
            )
        check_channel(path, channel, 1, [])
        dtype = checked_dtype(path, tif.pages[0].dtype)
        reader = _reader(path, tif, tif.pages, page_shape, dtype)
        return reader, FileMetadata()


def _series_frames(path: Path, tif, channel: int | None):
    if len(tif.series) > 1:
        raise BayespsfInputError(
            f"{path}: it holds {len(tif.series)} image series (positions or acquisitions); "
            "a movie file holds one"
        )
    series = tif.series[0]
    axes, shape = series.axes, series.shape
    if not axes.endswith("YX") or len(axes) < 2 or "S" in axes:
        raise BayespsfInputError(
            f"{path}: its images have axes {axes!r} (shape {shape}): a movie's frames are 2-D "
            "(YX) with T, Z and C around them; colour samples (S) are not movie frames"
        )
    dtype = checked_dtype(path, series.dtype)
    calibration = from_ome(tif.ome_metadata, channel) if tif.is_ome else from_imagej(tif)
    lead_axes, lead = axes[:-2], shape[:-2]
    planes = np.arange(int(np.prod(lead, dtype=np.int64))).reshape(lead)
    if "C" in lead_axes:
        where = lead_axes.index("C")
        check_channel(path, channel, lead[where], calibration.channel_names)
        planes = np.take(planes, channel, axis=where)
    else:
        check_channel(path, channel, 1, [])
    frames = planes.reshape(-1)
    frame_shape = shape[-2:]
    pages = series.pages
    if len(pages) == np.prod(lead):
        reader = _reader(path, tif, (pages[int(p)] for p in frames), frame_shape, dtype)
    elif series.dataoffset is not None:  # ImageJ's > 4 GB files: one page, data contiguous
        plane_bytes = int(np.prod(frame_shape)) * dtype.itemsize
        offsets = series.dataoffset + frames * plane_bytes
        _check_end(path, 0, int(offsets.max()) + plane_bytes, tif.filehandle.size)
        reader = MappedPages(path, offsets, frame_shape, dtype, tif.byteorder)
    else:
        raise BayespsfInputError(
            f"{path}: {len(pages)} pages for {np.prod(lead)} planes of axes {axes!r}; the "
            "metadata and the pages disagree"
        )
    calibration.metadata.update(axes=axes, channel=channel)
    return reader, calibration


def _reader(path: Path, tif, pages, frame_shape, dtype):
    """A reader of ``pages`` (one per frame): memory-mapped if every page is stored
    uncompressed in final form, decoded page by page otherwise."""
    size = tif.filehandle.size
    rows, columns = (int(n) for n in frame_shape)
    offsets, numbers, final = [], [], True
    for j, page in enumerate(pages):
        if page is None:
            raise BayespsfInputError(f"{path}: frame {j} is missing from the file")
        if np.dtype(page.dtype).str[1:] != np.dtype(dtype).str[1:]:  # byte order aside
            raise BayespsfInputError(
                f"{path}: page {page.index} holds {np.dtype(page.dtype)}, the first page "
                f"{np.dtype(dtype)}; a movie's pages must share one data type"
            )
        if page.parent is not tif:
            raise BayespsfInputError(
                f"{path}: its metadata place frame {j} in another file "
                f"({page.parent.filename}); multi-file OME datasets are not read yet"
            )
        ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts, strict=True)]
        _check_end(path, j, max(ends, default=0), size)
        bits = page.keyframe.bitspersample  # a TiffFrame reads its tags from its key page
        need = -(-columns * bits // 8) * rows  # rows of whole bytes, packed
        if page.compression == 1 and sum(page.databytecounts) < need:  # stored uncompressed
            raise BayespsfInputError(
                f"{path}: damaged or truncated TIFF (frame {j}'s page holds "
                f"{sum(page.databytecounts)} bytes of image data, where its {rows} x {columns} "
                f"pixels of {bits} bits need {need})"
            )
        numbers.append(page.index)
        final = final and page.is_final
        if final:
            offsets.append(page.dataoffsets[0])
    if final:
        return MappedPages(path, offsets, frame_shape, dtype, tif.byteorder)
    return DecodedPages(path, numbers, frame_shape, dtype)


def _check_end(path: Path, frame: int, end: int, size: int) -> None:
    if end > size:
        raise BayespsfInputError(
            f"{path}: damaged or truncated TIFF (frame {frame}'s image data end at byte {end}, "
            f"past the end of the file at {size})"
        )


class ChannelsError(BayespsfInputError):
    """A file of several channels read without choosing one (``channel=k``, ``--channel k``)."""


def check_channel(path: Path, channel, count: int, names: list[str]) -> None:
    """``channel`` must pick one of ``count`` channels; several channels need one picked."""
    if channel is None:
        if count > 1:
            listed = ", ".join(
                f"{k} ({names[k]!r})" if k < len(names) and names[k] else str(k)
                for k in range(count)
            )
            raise ChannelsError(
                f"{path}: it has {count} channels ({listed}); pick one with channel=k "
                "(--channel k on the command line)"
            )
        return
    if isinstance(channel, bool) or not isinstance(channel, int | np.integer):
        raise BayespsfInputError(f"{path}: channel must be an integer, got {channel!r}")
    if not 0 <= channel < count:
        raise BayespsfInputError(
            f"{path}: channel={channel}, but it has {count} channel(s): 0 to {count - 1}"
        )


def checked_dtype(path: Path, dtype) -> np.dtype:
    """Movies hold real numbers: boolean, complex and unknown sample formats are errors."""
    if dtype is None:
        raise BayespsfInputError(f"{path}: its sample format cannot be read as numbers")
    dtype = np.dtype(dtype)
    if dtype.kind not in "iuf":
        what = {"c": "complex", "b": "boolean"}.get(dtype.kind, dtype.name)
        raise BayespsfInputError(
            f"{path}: {what} values (dtype {dtype}); a movie holds real numbers"
        )
    return dtype
