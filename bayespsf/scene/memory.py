"""The memory a run's arrays need, checked against the machine's before they are allocated.

A size that cannot fit (an ensemble of 10^12 walkers, 10^9 images of 401 x 401 pixels) is
refused by name with the size it asks for, instead of ending in NumPy's ``MemoryError`` or the
system's out-of-memory killer after part of the work. The estimates are lower bounds from the
arrays' shapes (8 bytes per value); the limit is the machine's physical memory.
"""

from __future__ import annotations

import os

from bayespsf.errors import BayespsfInputError


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


__all__ = ["in_bytes", "physical_memory", "refuse_beyond_memory"]
