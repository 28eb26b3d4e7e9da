"""A table written as CSV with its rows formatted on the workers.

pandas formats a float as text at about 1 µs (numpy's shortest round-trip digits), so
``sample_many``'s summary (~94 columns) costs ~90 µs per row to write: more than a posterior
costs per ROI on 16 workers, and all of it in the calling process after the workers are done.
``write_csv`` cuts the table into blocks of rows, has the runner's workers format each block
(``DataFrame.to_csv``, no header) and writes the texts in order after the header. pandas
formats a number, a bool or a string from its column's type and the value alone, and every
block is a slice of the one table, so the file is ``table.to_csv(path, index=False)``'s to the
byte. Dates and durations are the exception (pandas drops a column's time of day or its
sub-second digits where every value of the column allows): a table with such a column, and a
path that pandas would compress (``.gz``, ``.zip``, ...), are written by ``to_csv`` itself.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import os
from pathlib import Path

import pandas as pd

from bayespsf.parallel.executors import parallelism, run_in_order

#: Fewest rows in a block formatted on a worker (a smaller table is written here): 512 rows
#: of a summary take ~45 ms to format, sending them and their text back ~1 ms.
MIN_BLOCK = 512
#: Most rows in a block: the calling process holds a few blocks per worker, as frames and as
#: text (4 096 summary rows: ~3 MB and ~7 MB).
MAX_BLOCK = 4096
#: Endings of a path that pandas writes compressed.
COMPRESSED = (".gz", ".bz2", ".zip", ".xz", ".zst", ".tar")


def write_csv(table: pd.DataFrame, path: str | os.PathLike, runner: cf.Executor | None) -> Path:
    """Write ``table`` to ``path`` as ``table.to_csv(path, index=False)`` does, its rows
    formatted on ``runner``'s workers.

    Parameters
    ----------
    table : pandas.DataFrame
        The table (its index is not written).
    path : str or path-like
        The file, written in UTF-8 (replaced if it exists).
    runner : concurrent.futures.Executor or None
        From ``task_runner``: blocks of ``MIN_BLOCK`` to ``MAX_BLOCK`` rows, about four per
        worker, are formatted there, a few at a time (``run_in_order``); None, one worker, a
        table of fewer than two blocks, a column of dates or durations, or a compressed
        ``path``: all of it here, by ``to_csv``.

    Returns
    -------
    pathlib.Path
        ``path``.

    See Also
    --------
    run_in_order : how the blocks are sent.

    Examples
    --------
    >>> import tempfile
    >>> import pandas as pd
    >>> from pathlib import Path
    >>> from bayespsf.parallel.tables import write_csv
    >>> table = pd.DataFrame({"x": [0.5, float("nan")], "why": ["a, b", None]})
    >>> print(write_csv(table, Path(tempfile.mkdtemp()) / "t.csv", None).read_text(), end="")
    x,why
    0.5,"a, b"
    ,
    """
    path = Path(path)
    workers = 1 if runner is None else parallelism(runner)
    size = min(MAX_BLOCK, max(MIN_BLOCK, math.ceil(len(table) / (4 * workers))))
    whole = workers == 1 or len(table) < 2 * size or path.suffix.lower() in COMPRESSED
    if whole or any(_formatted_as_a_whole(dtype) for dtype in table.dtypes):
        table.to_csv(path, index=False)
        return path
    blocks = (table.iloc[first : first + size] for first in range(0, len(table), size))
    with open(path, "w", encoding="utf-8", newline="") as file:
        file.write(table.iloc[:0].to_csv(index=False))
        for text in run_in_order(_rows_as_text, blocks, runner):
            file.write(text)
    return path


def _formatted_as_a_whole(dtype) -> bool:
    """Whether pandas formats the values of a column of ``dtype`` from all of them: dates and
    durations (also as a categorical's categories)."""
    if isinstance(dtype, pd.CategoricalDtype):
        dtype = dtype.categories.dtype
    return getattr(dtype, "kind", None) in ("M", "m")  # datetime64 (with a zone too), timedelta64


def _rows_as_text(block: pd.DataFrame) -> str:
    """Worker side: a block's rows as CSV text, without the header."""
    return block.to_csv(index=False, header=False)


__all__ = ["COMPRESSED", "MAX_BLOCK", "MIN_BLOCK", "write_csv"]
