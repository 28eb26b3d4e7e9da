"""``localize_frames``' work as tasks: detection on blocks of frames, and the localisation of
chunks of windows, run in this process, on local worker processes or on a Dask cluster alike.

This process reads the frames (the cheap part: ~0.15 ms per 512 x 512 frame), sends each block
of frames to be detected (``block_spots``: each frame's candidates and the windows of the
accepted ones, returned as one table and one array per block, which this process folds with a
few array operations), folds the blocks' windows in frame order into chunks of ``CHUNK`` windows and
sends each chunk to be localised (``localize_chunk``: the MLE and, for the posterior, the least
squares and ``sample_many`` in the worker, one process per chunk). Detection of later frames
runs beside the localisation of earlier chunks, and at most ``WAITING`` tasks per worker are
sent ahead (a chunk before a block of frames), so memory holds a few blocks and chunks
whatever the movie's length. Where the posterior runs on a device (``backend="jax"``), the
chunks are localised here, in the process that holds the device, while the workers detect.

A chunk's windows, its seed and its store depend on the movie and the run's seed only, and
every chunk is sampled by ``sample_many`` in one process (the same stacks whatever runs it),
so the results do not depend on the workers, to the last bit.
"""

from __future__ import annotations

import concurrent.futures as cf
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.analysis.localizations import PLACE_COLUMNS
from bayespsf.analysis.molecule_tasks import estimates
from bayespsf.model import Model
from bayespsf.movie import detect_frame
from bayespsf.parallel import molecule_seed, parallelism, sample_many

#: Windows per chunk: one ``sample_many`` call, one store folder (the seeds depend on it).
CHUNK = 512
#: Tasks sent ahead per worker (it starts the next one at once; memory: a few blocks).
WAITING = 2
#: Pixels per block of frames sent to be detected (8 MiB of uint16): 64 frames of 256 x 256.
BLOCK_PIXELS = 2**22
#: Fewest blocks of frames per worker, where a movie is short enough to be cut finer.
BLOCKS_PER_WORKER = 2


def block_frames(shape: tuple[int, int], frames: int | None = None, workers: int = 1) -> int:
    """Frames per detection task for frames of ``shape``: ``BLOCK_PIXELS`` of them, 1 to 64,
    and no more than gives each of ``workers`` ``BLOCKS_PER_WORKER`` blocks of a movie of
    ``frames`` frames. A block is detected in one worker (64 frames of 256 x 256: ~3.5 s), so
    a short movie in blocks of 64 would leave most of 16 workers without detection to do."""
    most = int(min(64, max(1, BLOCK_PIXELS // (shape[0] * shape[1]))))
    if frames is None:
        return most
    return max(1, min(most, int(frames) // (BLOCKS_PER_WORKER * max(1, int(workers)))))


def block_spots(first: int, frames: np.ndarray, settings: dict) -> list:
    """Each frame's candidates (``detect_frame``, numbered from ``first``) and the ``fit`` x
    ``fit`` windows (float64, ADU) of its accepted ones, centred on their peak pixels; the
    task of a worker. ``settings``: ``detect_frame``'s keywords, with ``fit``."""
    half = settings["fit"] // 2
    out = []
    for i, frame in enumerate(frames):
        table = detect_frame(frame, first + i, **settings)
        accepted = table[table["status"] == "accepted"]
        windows = np.empty((len(accepted), 2 * half + 1, 2 * half + 1))
        for j, (r, c) in enumerate(zip(accepted["row"], accepted["col"], strict=True)):
            windows[j] = frame[r - half : r + half + 1, c - half : c + half + 1]
        out.append((table, windows))
    return out


@dataclass(frozen=True)
class ChunkWork:
    """What every chunk's localisation shares: the windows' model, the run's seed, whether
    to sample the posterior, the output folder (its ``posteriors`` hold the stores) and
    ``sample_many``'s keywords."""

    fitting: Model
    seed: int
    posterior: bool
    out: Path
    sampler: dict


def localize_chunk(k: int, place: pd.DataFrame, counts: np.ndarray, work: ChunkWork):
    """Chunk ``k``'s rows: ``place``, the MLE with its Cramér-Rao bound and, with the
    posterior, ``sample_many``'s summary (seed ``molecule_seed(seed, k)``, store
    ``posteriors/chunk-k``) and the least squares; the task of a worker."""
    parts = [place, estimates(counts, work.fitting, lsq=work.posterior)]
    if work.posterior:
        store = work.out / "posteriors" / f"chunk-{k:05d}"
        seed = molecule_seed(work.seed, k)
        summary = sample_many(counts, work.fitting, seed=seed, store=store, **work.sampler)
        parts.insert(1, summary.drop(columns="molecule"))
    return k, pd.concat(parts, axis=1)


class _Here(cf.Executor):
    """Runs each task in this process when it is submitted (``run_frames``' one-process
    runner, and the device's chunks)."""

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as error:  # raised by the caller's result(), as a pool does
            future.set_exception(error)
        return future


def run_frames(
    blocks: Iterable[tuple[int, np.ndarray]],
    settings: dict,
    work: ChunkWork,
    runner: cf.Executor | None,
    *,
    chunks_here: bool = False,
    done: Callable[[int], object] = lambda n: None,
) -> tuple[pd.DataFrame, list[pd.DataFrame]]:
    """Detect ``blocks`` (``(first frame, frames)``, in order) and localise their windows.

    Parameters
    ----------
    blocks : iterable of (int, ndarray)
        Consecutive blocks of frames in counts, read lazily.
    settings : dict
        ``block_spots``' settings.
    work : ChunkWork
        ``localize_chunk``'s settings.
    runner : concurrent.futures.Executor or None
        Where the tasks run (``task_runner``); None: in this process.
    chunks_here : bool
        Localise the chunks in this process, detection on ``runner``.
    done : callable
        Called with the number of windows of each chunk localised (a progress bar).

    Returns
    -------
    candidates : pandas.DataFrame
        Every frame's candidates, in frame order, ``molecule`` numbering them over all frames.
    rows : list of pandas.DataFrame
        Each chunk's rows, in chunk order.
    """
    here = _Here()
    detector = runner or here
    localizer = here if chunks_here else detector
    limit = WAITING * parallelism(runner) if runner is not None else 1
    blocks = iter(blocks)
    futures: dict[cf.Future, tuple[str, int]] = {}
    found: dict[int, tuple] = {}  # blocks detected, not yet folded (they finish out of order)
    ready: deque = deque()  # chunks formed, not yet sent
    tables, rows, pending = [], {}, []
    sent = folded = waiting = formed = 0  # blocks sent and folded; windows pending; chunks
    numbered = 0  # candidates numbered over the whole movie
    exhausted = False
    while True:
        while len(futures) < limit or (ready and chunks_here):
            if ready:
                k, chunk = ready.popleft()
                place = pd.concat([p for p, _ in chunk], ignore_index=True)
                counts = np.concatenate([w for _, w in chunk])
                futures[localizer.submit(localize_chunk, k, place, counts, work)] = ("chunk", k)
            elif not exhausted and sent - folded < limit:
                try:
                    first, frames = next(blocks)
                except StopIteration:
                    exhausted = True
                    continue
                futures[detector.submit(_block_found, first, frames, settings)] = ("block", sent)
                sent += 1
            elif exhausted and folded == sent and waiting:  # the last chunk, shorter
                ready.append((formed, pending))
                pending, waiting, formed = [], 0, formed + 1
            else:
                break
        if not futures:
            break
        finished, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
        for future in finished:
            kind, key = futures.pop(future)
            if kind == "block":
                found[key] = future.result()  # a worker's error is raised here
            else:
                k, table = future.result()
                rows[k] = table
                done(len(table))
        while folded in found:
            table, windows = found.pop(folded)
            tables.append(table)  # numbered over the movie at the end, in one column
            pending.append((_accepted_places(table, numbered), windows))
            numbered += len(table)
            waiting += len(windows)
            while waiting >= CHUNK:
                chunk, pending = _split(pending, CHUNK)
                ready.append((formed, chunk))
                formed, waiting = formed + 1, waiting - CHUNK
            folded += 1
    candidates = pd.concat(tables, ignore_index=True)
    candidates["molecule"] = np.arange(len(candidates))
    return candidates, [rows[k] for k in sorted(rows)]


def _block_found(first: int, frames: np.ndarray, settings: dict):
    """``block_spots`` as one table of the block's candidates and one array of its windows,
    in frame order: the task of a worker, whose result the calling process folds with a few
    array operations per block rather than per frame."""
    found = block_spots(first, frames, settings)
    windows = [w for _, w in found]
    return pd.concat([t for t, _ in found], ignore_index=True), np.concatenate(windows)


def _accepted_places(table: pd.DataFrame, first: int) -> pd.DataFrame:
    """The ``PLACE_COLUMNS`` of the accepted candidates of a block's table, indexed from 0,
    the candidates numbered from ``first`` (``molecule``): from the columns' arrays (``.loc``
    and setting the column in the table cost ~0.5 and ~1 ms per frame)."""
    accepted = (table["status"] == "accepted").to_numpy()
    numbers = first + np.flatnonzero(accepted)
    return pd.DataFrame(
        {c: numbers if c == "molecule" else table[c].to_numpy()[accepted] for c in PLACE_COLUMNS}
    )


def _split(pending, size):
    """The first ``size`` windows of ``pending`` (a list of (place, windows)) and the rest."""
    taken, rest, need = [], [], size
    for place, windows in pending:
        if need <= 0:
            rest.append((place, windows))
        elif len(windows) <= need:
            taken.append((place, windows))
            need -= len(windows)
        else:
            taken.append((place.iloc[:need].reset_index(drop=True), windows[:need]))
            rest.append((place.iloc[need:].reset_index(drop=True), windows[need:]))
            need = 0
    return taken, rest
