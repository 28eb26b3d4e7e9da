"""Progress bars on stderr, shown only where a person watches (a terminal) unless asked."""

from __future__ import annotations

import sys


def progress_bar(total: int, progress: bool | None = None, *, initial: int = 0,
                 unit: str = "it", desc: str | None = None):  # fmt: skip
    """A ``tqdm`` bar over ``total`` steps: shown when ``progress`` is True, or when it is None
    and stderr is a terminal (never in log files)."""
    from tqdm import tqdm

    show = progress or (progress is None and sys.stderr.isatty())

    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: a later run may still fork its workers

    return Bar(total=total, initial=initial, disable=not show, unit=unit, desc=desc,
               file=sys.stderr)  # fmt: skip
