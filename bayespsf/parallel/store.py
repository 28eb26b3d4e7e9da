"""A result folder that a run writes molecule by molecule and a rerun resumes: ``manifest.json``
(what the store was made for: a rerun with other data or settings is refused by name), one
self-describing NetCDF file per finished molecule (written atomically: a killed run leaves no
half-written file), ``summary.csv``, and a lock that refuses a second run on the same folder."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.posterior import json_attribute

if TYPE_CHECKING:
    from bayespsf.inference import Posterior


class Store:
    """A result folder: manifest, one NetCDF file per molecule, summary.csv.

    Parameters
    ----------
    path : str or path-like
        The folder; made on ``lock`` or ``open`` if missing.

    Attributes
    ----------
    path : pathlib.Path
        The folder.

    See Also
    --------
    sample_many : writes one, molecule by molecule, and resumes from it.

    Notes
    -----
    The folder holds ``manifest.json``, ``molecule-000123.nc`` per finished molecule (a
    ``Posterior`` result file whose ``summary_row`` attribute is the molecule's row),
    ``summary.csv`` and ``.lock``. Files are written to a ``.partial`` name and renamed, so a
    killed run leaves no half-written file.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._lock = None

    def lock(self) -> None:
        """Hold the store's lock for this run.

        Raises
        ------
        BayespsfInputError
            If another run holds it, naming the process that does.

        Notes
        -----
        The lock (``fcntl.flock`` on ``.lock``, which holds this process's id) is released
        when the run ends or its process dies: a second run on the same store is refused at
        once, naming the process that holds it, instead of doing all the work again beside
        the first.
        """
        import fcntl

        self.path.mkdir(parents=True, exist_ok=True)
        handle = (self.path / ".lock").open("a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise BayespsfInputError(
                f"store {self.path} is in use by process {holder}; wait for that run to end, "
                "or use another store folder"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self._lock = handle

    def unlock(self) -> None:
        """Release the lock, if this store holds it."""
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def molecule_path(self, index: int) -> Path:
        """The result file of molecule ``index``.

        Parameters
        ----------
        index : int
            The molecule's index in the stack.

        Returns
        -------
        pathlib.Path
            ``path / "molecule-000123.nc"`` (six digits).
        """
        return self.path / f"molecule-{index:06d}.nc"

    def open(self, manifest: dict) -> None:
        """Create the store, or check that an existing one was made for this run.

        Parameters
        ----------
        manifest : dict
            What the run is (JSON-serialisable: data digest, settings, model, ...), written
            to ``manifest.json`` in a new store.

        Raises
        ------
        BayespsfInputError
            If the store's ``manifest.json`` differs, naming the keys that differ.
        """
        self.path.mkdir(parents=True, exist_ok=True)
        file = self.path / "manifest.json"
        if file.exists():
            old = json.loads(file.read_text())
            keys = [*manifest, *(k for k in old if k not in manifest)]  # either side's
            differ = [k for k in keys if old.get(k) != manifest.get(k)]
            if differ:
                raise BayespsfInputError(
                    f"store {self.path} was made for another run: {', '.join(differ)} differ "
                    "(use a new store folder, or delete this one)"
                )
        else:
            _atomic_write_text(file, json.dumps(manifest, indent=1))

    def finished(self, n: int) -> dict[int, dict]:
        """Summary rows of the molecules already in the store.

        Parameters
        ----------
        n : int
            The molecules of the run: indices 0 to ``n - 1`` are looked for.

        Returns
        -------
        dict of int to dict
            The summary row of each molecule with a result file, by index (read from the
            files' attributes, without loading their draws).
        """
        import xarray as xr

        rows = {}
        for index in range(n):
            path = self.molecule_path(index)
            if path.exists():
                tree = xr.open_datatree(path)
                try:
                    rows[index] = json_attribute(tree.attrs, "summary_row", str(path))
                finally:
                    tree.close()
        return rows

    def write(self, index: int, posterior: Posterior) -> None:
        """Write molecule ``index``'s result file atomically.

        Parameters
        ----------
        index : int
            The molecule's index in the stack.
        posterior : Posterior
            Its posterior (``Posterior.save`` writes it).
        """
        path = self.molecule_path(index)
        partial = path.with_suffix(".nc.partial")
        posterior.save(partial)
        os.replace(partial, path)

    def write_summary(self, table: pd.DataFrame) -> None:
        """Write ``summary.csv`` atomically.

        Parameters
        ----------
        table : pandas.DataFrame
            ``sample_many``'s summary table.
        """
        partial = self.path / "summary.csv.partial"
        table.to_csv(partial, index=False)
        os.replace(partial, self.path / "summary.csv")


def _atomic_write_text(path: Path, text: str) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    os.replace(partial, path)


__all__ = ["Store"]
