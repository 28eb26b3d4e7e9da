"""Temporal projections of a movie (mean, median, max, standard deviation over frames), with
peak memory bounded independently of the number of frames."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from bayespsf.errors import BayespsfInputError

if TYPE_CHECKING:
    from bayespsf.movie.read import Movie

KINDS = ("mean", "median", "max", "std")
MERGED = 16  # frames merged at a time into the mean and the squared deviations


def project(
    movie: Movie,
    kind: str = "mean",
    frames: slice | range | None = None,
    block: int | None = None,
    budget: int = 256 * 2**20,
) -> np.ndarray:
    """One image ``(h, w)`` (float64) summarising the movie's frames pixel by pixel.

    Parameters
    ----------
    movie : Movie
        From ``read_movie`` (or any object with ``shape``, ``dtype`` and ``frames(start,
        stop, rows=...)``).
    kind : {"mean", "median", "max", "std"}
        ``mean``: the average count per pixel over the frames; ``median``: the median over the
        frames (the mean of the two middle values for an even number of frames, as
        ``numpy.median``); ``max``: the largest count; ``std``: the population standard
        deviation over the frames (``ddof=0``, as ``numpy.std``), in the movie's counts.
    frames : slice or range, optional
        Which frames (by default all of them); a step skips frames.
    block : int, optional
        Frames read at a time by mean, max and std (by default as many as fit ``budget``).
    budget : int
        Bytes of working memory to aim for (default 256 MiB): it sets ``block`` and, for the
        median, the height of the band of rows whose frames are held at a time.

    Returns
    -------
    numpy.ndarray
        ``(h, w)``, float64, in the movie's units (ADU for a camera's movie).

    Raises
    ------
    BayespsfInputError
        An unknown ``kind``, a ``budget`` or ``block`` that is not a positive whole number,
        or ``frames`` that select no frame.

    See Also
    --------
    read_movie : the movie.
    detect_movie : detection on a mean or median projection.

    Notes
    -----
    mean, max and std stream blocks of frames. The mean and the variance are combined across
    groups of ``MERGED`` (16) consecutive frames, whatever ``block`` is read at a time (fewer
    when ``block`` is smaller), so the image does not depend on the memory budget while at
    least 16 frames are read at a time, by the
    pairwise update of Chan, Golub & LeVeque, "Algorithms for computing the sample variance:
    analysis and recommendations", Am. Stat. 37 (1983) 242: each group's mean and sum of
    squared deviations (two passes over the group, in float64) merge as
    ``M2 = M2_a + M2_b + δ² n_a n_b / n`` with ``δ`` the difference of the group means, which
    avoids the cancellation of a sum of squares. The median needs every frame of a pixel at
    once: it is taken over tiles of all (selected) frames of a band of rows, the band chosen
    so that a tile (and ``numpy.median``'s working copy) stays under ``budget``; the movie is
    then read once per band (memory-mapped files only the band's rows).

    References
    ----------
    .. [1] T. F. Chan, G. H. Golub and R. J. LeVeque, "Algorithms for computing the sample
       variance: analysis and recommendations", Am. Stat. 37 (1983) 242.
    """
    if kind not in KINDS:
        raise BayespsfInputError(f"kind must be one of {', '.join(KINDS)}; got {kind!r}")
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer) or budget < 1:
        raise BayespsfInputError(f"budget must be a positive number of bytes, got {budget!r}")
    span = _span(movie, frames)
    w = movie.shape[2]
    itemsize = np.dtype(movie.dtype).itemsize
    block = block_frames(movie, block, budget, 16)  # room for float64 working copies
    if kind == "median":
        rows = max(1, budget // (2 * len(span) * w * itemsize))
        return _median(movie, span, int(block), int(rows))
    if kind == "max":
        peak = None
        for data in blocks(movie, span, int(block)):
            top = data.max(axis=0)
            peak = top if peak is None else np.maximum(peak, top)
        return peak.astype(np.float64)
    count, mean, m2 = _moments(movie, span, block)
    return mean if kind == "mean" else np.sqrt(m2 / count)


def mean_and_variance(
    movie: Movie,
    frames: slice | range | None = None,
    block: int | None = None,
    budget: int = 256 * 2**20,
) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's mean and unbiased variance (``ddof=1``) over frames, in one streamed pass
    (as ``project``'s mean and std, which would read the movie twice)."""
    span = _span(movie, frames)
    count, mean, m2 = _moments(movie, span, block_frames(movie, block, budget, 16))
    if count < 2:
        raise BayespsfInputError(f"{count} frame(s); a variance needs at least 2")
    return mean, m2 / (count - 1)


def _moments(movie, span: range, block: int):
    """The count, mean and summed squared deviations of every pixel over ``span``: read
    ``block`` frames at a time, merged ``min(MERGED, block)`` frames at a time through one
    float64 buffer (a fresh float64 copy of each block read costs more in page faults than the
    arithmetic)."""
    h, w = movie.shape[1:]
    count, mean, m2 = 0, np.zeros((h, w)), np.zeros((h, w))
    work = np.empty((min(MERGED, block, len(span)), h, w))
    held = 0
    for data in blocks(movie, span, block):
        done = 0
        while done < len(data):
            part = data[done : done + len(work) - held]
            work[held : held + len(part)] = part
            done, held = done + len(part), held + len(part)
            if held == len(work):
                count, mean, m2 = _merge(count, mean, m2, work)
                held = 0
    if held:
        count, mean, m2 = _merge(count, mean, m2, work[:held])
    return count, mean, m2


def block_frames(movie, block, budget: int, work_bytes: int) -> int:
    """Frames to read at a time: ``block`` (checked), or as many as fit ``budget`` bytes with
    each pixel of a frame taking its file type's size plus ``work_bytes`` of working copies."""
    if block is None:
        h, w = movie.shape[1:]
        return max(1, budget // (h * w * (np.dtype(movie.dtype).itemsize + work_bytes)))
    if isinstance(block, bool) or not isinstance(block, int | np.integer) or block < 1:
        raise BayespsfInputError(f"block must be a whole number of frames >= 1, got {block!r}")
    return int(block)


def _merge(count: int, mean: np.ndarray, m2: np.ndarray, data: np.ndarray):
    """Chan, Golub & LeVeque (1983): the count, mean and sum of squared deviations of the
    frames so far merged with those of a new block ``data`` (k, h, w)."""
    k = data.shape[0]
    block_mean = data.mean(axis=0)
    data -= block_mean
    block_m2 = np.einsum("kij,kij->ij", data, data)
    total = count + k
    delta = block_mean - mean
    mean = mean + delta * (k / total)
    m2 = m2 + block_m2 + delta**2 * (count * k / total)
    return total, mean, m2


def _median(movie, span: range, block: int, rows: int) -> np.ndarray:
    """The median over frames, a band of ``rows`` rows at a time."""
    h, w = movie.shape[1:]
    out = np.empty((h, w))
    tile = np.empty((len(span), min(rows, h), w), movie.dtype)
    for top in range(0, h, rows):
        band = slice(top, min(top + rows, h))
        height = band.stop - band.start
        filled = 0
        for data in blocks(movie, span, block, band):
            tile[filled : filled + len(data), :height] = data
            filled += len(data)
        out[band] = np.median(tile[:, :height], axis=0)
    return out


def _span(movie, frames) -> range:
    """The frames to project, as an increasing range."""
    n = movie.shape[0]
    if frames is None:
        span = range(n)
    elif isinstance(frames, slice | range):
        if isinstance(frames, range):
            frames = slice(frames.start, frames.stop, frames.step)
        span = range(n)[frames]
    else:
        raise BayespsfInputError(f"frames must be a slice or a range, got {frames!r}")
    span = span if span.step > 0 else span[::-1]
    if len(span) == 0:
        raise BayespsfInputError(f"frames={frames!r} selects none of the movie's {n} frames")
    return span


def blocks(
    movie: Movie, span: range, block: int, rows: slice | None = None
) -> Iterator[np.ndarray]:
    """The frames of ``span``, ``block`` of them at a time (read in one call where they are
    consecutive, one by one where the span skips frames)."""
    for i in range(0, len(span), block):
        part = span[i : i + block]
        if part.step == 1:
            yield movie.frames(part.start, part.stop, rows=rows)
        else:
            yield np.stack([movie.frames(f, f + 1, rows=rows)[0] for f in part])


def project_with_saturation(
    movie: Movie, kind: str, level: float | None, frames: slice | range | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """``project(movie, kind, frames)`` and, in the same pass over the frames, the number of
    frames in which each pixel reaches ``level`` (the ADC's full scale).

    Parameters
    ----------
    movie : Movie
        As ``project``.
    kind : {"mean", "median", "max", "std"}
        As ``project``.
    level : float or None
        Counts at or above it are saturated; None: no count (``counts`` is None).
    frames : slice or range, optional
        As ``project``.

    Returns
    -------
    image : numpy.ndarray
        ``(h, w)``, float64: the projection.
    counts : numpy.ndarray or None
        ``(h, w)``, int64: the frames in which each pixel is at or above ``level``.
    """
    if level is None:
        return project(movie, kind, frames), None
    tally = _Tally(movie, level)
    return project(tally, kind, frames), tally.counts


class _Tally:
    """A movie whose reads count, pixel by pixel, the frames at or above ``level``."""

    def __init__(self, movie, level: float):
        self.movie, self.level = movie, level
        self.shape, self.dtype = movie.shape, movie.dtype
        self.counts = np.zeros(movie.shape[1:], dtype=np.int64)

    def frames(self, start: int, stop: int, rows: slice | None = None) -> np.ndarray:
        data = self.movie.frames(start, stop, rows=rows)
        self.counts[slice(None) if rows is None else rows] += np.count_nonzero(
            data >= self.level, axis=0
        )
        return data
