"""Run-time helpers shared by every stage: BLAS threads, progress bars, timing.

**One BLAS thread** for the small dense algebra of one molecule. A 6-parameter fit calls BLAS on
vectors of length 6 (L-BFGS-B's updates, 6x6 solves). OpenBLAS then wakes its thread pool for no
gain; on a machine whose cores are busy (a batch run, a shared server) the handoffs made one
maximum-likelihood fit 2-20x slower (5 ms idle, 9-100 ms with both cores loaded; measured with
scipy 1.18 / OpenBLAS 0.3.34 on 2 cores). Limiting BLAS to one thread while a molecule is fitted
or sampled removes that cost; it is restored after.

**Progress bars** on stderr, shown only where a person watches (a terminal) unless asked.

**Timing** for the self-check and the benchmarks (never for tests): the best of a few calls, and
the machine a result was measured on.

**Memory** a run's arrays need, checked against the machine's before they are allocated: a size
that cannot fit (an ensemble of 10^12 walkers, 10^9 images of 401 x 401 pixels) is refused by
name with the size it asks for, instead of ending in NumPy's ``MemoryError`` or the system's
out-of-memory killer after part of the work. The estimates are lower bounds from the arrays'
shapes (8 bytes per value); the limit is the machine's physical memory.
"""

from __future__ import annotations

import functools
import os
import platform
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from threadpoolctl import ThreadpoolController

from bayespsf.errors import BayespsfInputError


@functools.cache
def _controller() -> ThreadpoolController:
    return ThreadpoolController()  # inspects the loaded libraries once (~1 ms)


def single_blas_thread():
    """Context manager: BLAS limited to one thread inside it (~20 us to enter and leave)."""
    return _controller().limit(limits=1, user_api="blas")


def one_blas_thread(function):
    """Decorator: ``function`` runs with BLAS limited to one thread when called from the main
    thread. The limit is process-wide, so calls from other threads (a threaded Dask worker)
    leave it alone rather than race each other's enter and exit."""

    @functools.wraps(function)
    def limited(*args, **kwargs):
        if threading.current_thread() is not threading.main_thread():
            return function(*args, **kwargs)
        with single_blas_thread():
            return function(*args, **kwargs)

    return limited


def progress_bar(
    total: int,
    progress: bool | None = None,
    *,
    initial: int = 0,
    unit: str = "it",
    desc: str | None = None,
):
    """A ``tqdm`` bar over ``total`` steps: shown when ``progress`` is True, or when it is None
    and stderr is a terminal (never in log files)."""
    from tqdm import tqdm

    show = progress or (progress is None and sys.stderr.isatty())

    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: a later run may still fork its workers

    return Bar(
        total=total, initial=initial, disable=not show, unit=unit, desc=desc, file=sys.stderr
    )


def best_time(fn: Callable[[], object], repeat: int = 3) -> float:
    """The fastest of ``repeat`` calls of ``fn``, in seconds (the least disturbed by load)."""
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def cache_folder():
    """The folder of the machine's on-disk caches (the EMCCD tables, JAX's compiled programs):
    ``$BAYESPSF_CACHE`` (``off``: ``None``, no cache), else ``$XDG_CACHE_HOME/bayespsf``, else
    ``~/.cache/bayespsf``."""
    from pathlib import Path

    chosen = os.environ.get("BAYESPSF_CACHE")
    if chosen is not None:
        return None if chosen.strip().lower() == "off" else Path(chosen)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "bayespsf"


def machine() -> str:
    """The machine a result was measured on, as one line: the architecture and processor's
    name, the cores, the physical cores where fewer (a core's hardware threads share its
    arithmetic units, so workers beyond the physical cores add little), the cores this process
    may use where fewer, Python and numpy."""
    name = _cpu_name()
    cores = os.cpu_count()
    physical = physical_cores()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores
    return (
        f"{platform.machine()}{f' ({name})' if name else ''}, {cores} cores"
        f"{f' ({physical} physical)' if physical and cores and physical < cores else ''}"
        f"{f', {usable} usable' if cores and usable < cores else ''}, "
        f"Python {platform.python_version()}, numpy {np.__version__}"
    )


def physical_cores(cpus: str | os.PathLike = "/sys/devices/system/cpu") -> int | None:
    """The physical cores of the machine (hardware threads of one core counted once), from
    Linux's CPU topology under ``cpus``: the distinct sets of hardware threads that share a
    core (``core_cpus_list``, older kernels' ``thread_siblings_list``; ``core_id`` repeats
    across a package's dies on some machines); None where it is not there to read."""
    found = set()
    for folder in Path(cpus).glob("cpu[0-9]*/topology"):
        for name in ("core_cpus_list", "thread_siblings_list"):
            try:
                found.add((folder / name).read_text().strip())
                break
            except OSError:
                continue
        else:
            return None
    return len(found) or None


def _cpu_name(info: str | os.PathLike = "/proc/cpuinfo") -> str | None:
    """The processor's model name from Linux's ``/proc/cpuinfo`` (None where not there)."""
    try:
        with open(info) as lines:
            for line in lines:
                if line.startswith("model name") and ":" in line:
                    return line.split(":", 1)[1].strip() or None
    except OSError:
        return None
    return None


def physical_memory() -> int | None:
    """The machine's physical memory in bytes (None where the system does not report it).

    Returns
    -------
    int or None
        ``SC_PAGE_SIZE * SC_PHYS_PAGES`` (``os.sysconf``).
    """
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # not a POSIX system, or it does not say
        return None


def refuse_beyond_memory(needed: float, what: str, fix: str) -> None:
    """Refuse, before allocating, work whose arrays need more than the machine's memory.

    Parameters
    ----------
    needed : float
        A lower bound on the bytes the work holds at once (estimated from its shapes).
    what : str
        The setting and what it asks for, e.g. ``"walkers = 10000000"``.
    fix : str
        What to do instead, naming the option.

    Raises
    ------
    BayespsfInputError
        If ``needed`` exceeds ``physical_memory()``: such arrays cannot be held, and NumPy
        would end the run in ``MemoryError`` (or the system's out-of-memory killer).
    """
    memory = physical_memory()
    if memory is not None and needed > memory:
        raise BayespsfInputError(
            f"{what} needs at least {in_bytes(needed)} of memory at once, more than this "
            f"machine's {in_bytes(memory)}: {fix}"
        )


def in_bytes(size: float) -> str:
    """A number of bytes in words, to three figures.

    Parameters
    ----------
    size : float
        Bytes (>= 0).

    Returns
    -------
    str
        E.g. ``"512 bytes"``, ``"1.29 GB"``, ``"14.4 PB"`` (decimal units).
    """
    units = ("bytes", "kB", "MB", "GB", "TB", "PB", "EB")
    k = 0
    while size >= 999.5 and k < len(units) - 1:
        size, k = size / 1000.0, k + 1
    return f"{size:.3g} {units[k]}"


__all__ = ["in_bytes", "machine", "physical_cores", "physical_memory", "refuse_beyond_memory"]
