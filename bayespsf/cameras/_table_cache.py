"""An on-disk cache of arrays that take seconds to compute (the EMCCD ``table`` tier), shared by
every process of a machine.

Files live in ``$BAYESPSF_CACHE`` (``off`` disables the cache), else
``$XDG_CACHE_HOME/bayespsf``, else ``~/.cache/bayespsf``. A name carries a digest of the source
files that computed it, so a changed law never reads a stale table. Writers write a temporary
file in the same folder and rename it into place (atomic on POSIX), so concurrent writers and
readers only ever see whole files; a file that cannot be read is computed again and replaced.
Where the folder cannot be written, arrays are computed as if there were no cache.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np

from bayespsf._runtime import cache_folder


def folder() -> Path | None:
    """The cache folder, or ``None`` when caching is off (``bayespsf._runtime.cache_folder``)."""
    return cache_folder()


def digest(*sources: str | Path) -> str:
    """16 hex digits of the SHA-256 of the given source files."""
    h = hashlib.sha256()
    for source in sources:
        h.update(Path(source).read_bytes())
    return h.hexdigest()[:16]


def load_or_compute(name: str, compute, shape: tuple[int, ...], mapped: bool = False) -> np.ndarray:
    """The array cached as ``name`` if it is there, whole and of ``shape``; else ``compute()``,
    stored for the next process.

    ``mapped``: the cached file is mapped into memory read-only rather than read, so that every
    process of the machine (a pool's workers) shares one copy of it in the page cache and reads
    only the pages it touches; the array is read-only however it was made (one type for
    compiled code that takes it)."""
    where = folder()
    path = None if where is None else where / f"{name}.npy"
    # a folder whose files cannot be mapped (some network file systems) is read instead
    for mode in ("r", None) if mapped else (None,):
        if path is None or not path.exists():
            break
        try:
            array = np.load(path, mmap_mode=mode, allow_pickle=False)
        except (OSError, ValueError, EOFError):  # damaged: computed and replaced below
            continue
        if array.shape != shape:
            break
        if mapped:
            array.flags.writeable = False
        return array
    array = compute()
    if path is not None:
        _store(path, array)
    if mapped:
        array.flags.writeable = False
    return array


def _store(path: Path, array: np.ndarray) -> None:
    """Write ``array`` to ``path`` atomically; a folder that cannot be written keeps nothing."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".partial")
    except OSError:
        return
    try:
        with os.fdopen(handle, "wb") as file:
            np.save(file, array)
        os.replace(temporary, path)
    except OSError:  # a full disk: the array is still returned, just not kept
        with contextlib.suppress(OSError):
            os.unlink(temporary)
