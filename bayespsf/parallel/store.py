"""A result folder that a run writes as it goes and a rerun resumes: ``manifest.json`` (what
the store was made for: a rerun with other data or settings is refused by name), the
posteriors of the finished molecules, many to a NetCDF file (``posteriors-FIRST-LAST.nc``,
written atomically: a killed run leaves no half-written file), ``summary.csv``, and a lock that
refuses a second run on the same folder.

A file holds the molecules of one task (up to ``FILE_MOLECULES``): its ``posterior`` group the
draws with dims ``(molecule, chain, draw)``, each molecule's draws followed by NaN up to the
file's longest (none in a store that keeps no draws, ``NO_DRAWS``), ``observed_data`` the
counts ``(molecule, row, column)``, ``molecules`` the number of chains and draws of each and
its attributes as JSON (the sampler's record, the autocorrelation time, the truth, the summary
row: ``MOLECULE_ATTRIBUTES``), and as root attributes what the molecules share (camera,
geometry, photon unit, scene).
``Store.posterior`` gives back one molecule's ``Posterior``, as ``Posterior.save`` would have
written it. Writing many molecules to a file costs ~0.5 ms per molecule, where a file per
molecule cost ~70 ms (h5netcdf writes each variable's dimensions one by one), and a dataset of
10^6 molecules is ~4 000 files (``sample_many``'s tasks hold up to 256), not 10^6.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import numbers
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.result_file import (
    MOLECULE_ATTRIBUTES,
    MissingGroup,
    json_attribute,
    open_result_file,
    result_attributes,
)
from bayespsf.parallel.tables import write_csv
from bayespsf.psf import PARAMETER_NAMES

if TYPE_CHECKING:
    import xarray as xr

    from bayespsf.inference import Posterior
    from bayespsf.model import Model
    from bayespsf.scene import Scene

#: The ``store`` entry of a store's manifest: what its files are.
STORE_FORMAT = "bayespsf store 2: posteriors-FIRST-LAST.nc, many molecules to a file"
#: Most molecules to a file (a larger write is split).
FILE_MOLECULES = 4096
#: The manifest's entry for a store that keeps no draws (``sample_many(keep_draws=False)``).
NO_DRAWS = {"draws": "not kept: each molecule's summary row, sampler record and counts only"}
_NAME = re.compile(r"posteriors-(\d+)-(\d+)\.nc")
# a detect or analyze run's record (bayespsf.io.run_record.RECORD_NAME, a layer above this)
RUN_RECORD = "run.json"


class Store:
    """A result folder: manifest, the posteriors many molecules to a file, summary.csv.

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
    sample_many : writes one as it goes, and resumes from it.

    Notes
    -----
    The folder holds ``manifest.json``, ``posteriors-000000-000255.nc`` and so on (the
    molecules of one task, named by the first and last of them; see the module docstring
    for what a file holds), ``summary.csv`` and ``.lock``. Files are written to a
    ``.partial`` name and renamed, so a killed run leaves no half-written file.

    Examples
    --------
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("ideal")
    >>> counts, truth = bayespsf.simulate(scene, n=2, seed=1)
    >>> model = bayespsf.Model.from_scene(scene)
    >>> table = bayespsf.sample_many(counts, model, seed=7, workers=1, store="run-1")
    >>> post = bayespsf.parallel.Store("run-1").posterior(1)
    >>> post.method
    'importance'
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._lock = None

    def lock(self) -> None:
        """Hold the store's lock for this run.

        Raises
        ------
        BayespsfInputError
            If another run holds it, naming the process that does, or the folder holds a
            detect or analyze run's results (``run.json``; nothing is written then).

        Notes
        -----
        The lock (``fcntl.flock`` on ``.lock``, which holds this process's id) is released
        when the run ends or its process dies: a second run on the same store is refused at
        once, naming the process that holds it, instead of doing all the work again beside
        the first.
        """
        import fcntl

        self._refuse_a_run()
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

    def open(self, manifest: dict) -> None:
        """Create the store, or check that an existing one was made for this run.

        Parameters
        ----------
        manifest : dict
            What the run is (JSON-serialisable: data digest, settings, model, ...), written
            to ``manifest.json`` in a new store with ``store``: ``STORE_FORMAT``.

        Raises
        ------
        BayespsfInputError
            If the store's ``manifest.json`` differs, naming the keys that differ, or the
            folder holds a store of an earlier layout (a file per molecule) or a detect or
            analyze run's results (``run.json``).

        Notes
        -----
        With the lock held (``lock``), the ``.partial`` files of a killed run are removed.
        """
        manifest = {"store": STORE_FORMAT, **manifest}
        self._refuse_a_run()
        self.path.mkdir(parents=True, exist_ok=True)
        file = self.path / "manifest.json"
        if file.exists():
            old = json.loads(file.read_text())
            if old.get("store") != STORE_FORMAT:
                raise BayespsfInputError(
                    f"store {self.path} was written by an earlier bayespsf, one file per "
                    "molecule (molecule-000000.nc, ...); its files still open with "
                    "Posterior.load, but a run cannot continue there: use a new store folder"
                )
            keys = [*manifest, *(k for k in old if k not in manifest)]  # either side's
            differ = [k for k in keys if old.get(k) != manifest.get(k)]
            if differ:
                raise BayespsfInputError(
                    f"store {self.path} was made for another run: {', '.join(differ)} differ "
                    "(use a new store folder, or delete this one)"
                )
        else:
            _atomic_write_text(file, json.dumps(manifest, indent=1))
        if self._lock is not None:
            for partial in self.path.glob("posteriors-*.nc.partial"):
                partial.unlink()

    def _refuse_a_run(self) -> None:
        if (self.path / RUN_RECORD).is_file():  # a detect or analyze run's folder
            raise BayespsfInputError(
                f"store {self.path} holds the results of a `bayespsf detect` or `analyze` run "
                f"({RUN_RECORD}); use a new store folder"
            )

    def files(self) -> list[Path]:
        """The store's result files, in the order of their first molecule.

        Returns
        -------
        list of pathlib.Path
            Each ``posteriors-FIRST-LAST.nc``.
        """
        named = [(_span(p), p) for p in self.path.glob("posteriors-*.nc")]
        return [p for span, p in sorted(named, key=lambda item: item[0]) if span is not None]

    def finished(self, n: int) -> dict[int, dict]:
        """Summary rows of the molecules already in the store.

        Parameters
        ----------
        n : int
            The molecules of the run: indices 0 to ``n - 1`` are looked for.

        Returns
        -------
        dict of int to dict
            The summary row of each molecule in a result file, by index (read from the
            files' ``molecules`` groups, without their draws).

        Raises
        ------
        BayespsfInputError
            Naming a file that is damaged, or that does not hold a store's molecules.
        """
        rows = {}
        for path in self.files():
            table = self._read(path, "molecules")  # not the draws
            texts = table["summary_row"].values
            for index, row in zip(_molecules(table, path), texts, strict=True):
                if 0 <= index < n:
                    rows[index] = json_attribute(
                        {"summary_row": row}, "summary_row", f"{path}, molecule {index}"
                    )
        return rows

    def keeps_draws(self) -> bool:
        """Whether the store's files hold the molecules' draws.

        Returns
        -------
        bool
            False where its manifest says ``NO_DRAWS`` (``sample_many(keep_draws=False)``):
            its files hold each molecule's summary row, sampler record and counts only.
        """
        file = self.path / "manifest.json"
        return not (file.exists() and "draws" in json.loads(file.read_text()))

    def posterior(self, index: int) -> Posterior:
        """The posterior of molecule ``index``.

        Parameters
        ----------
        index : int
            The molecule's index in the stack.

        Returns
        -------
        Posterior
            Its draws, counts and attributes, as ``Posterior.save`` writes them for one
            molecule (with its ``summary_row``).

        Raises
        ------
        BayespsfInputError
            If ``index`` is not a whole number, the store keeps no draws, no file of the store
            holds the molecule, or the file that does is damaged.
        """
        if isinstance(index, bool) or not isinstance(index, numbers.Integral):
            raise BayespsfInputError(
                f"index must be a molecule's number (an integer), got {index!r}"
            )
        index = int(index)
        if not self.keeps_draws():
            raise BayespsfInputError(
                f"store {self.path} keeps no draws (sampled with keep_draws=False, "
                "--no-draws): its summary.csv holds each molecule's summary; sample again "
                "into a new store with the draws kept to read a posterior"
            )
        for path in self.files():
            first, last = _span(path)
            if not first <= index <= last:
                continue
            tree = self._read(path)
            where = np.flatnonzero(_molecules(tree["molecules"], path) == index)
            if where.size:
                return _one(tree, int(where[0]))
        raise BayespsfInputError(
            f"store {self.path} holds no posterior of molecule {index} (not sampled yet, "
            "refused or failed: see summary.csv's status)"
        )

    def write(
        self,
        molecules: Sequence[int],
        draws: Sequence[np.ndarray],
        counts: ArrayLike,
        attributes: Mapping[str, str],
        per_molecule: Sequence[Mapping[str, str]],
    ) -> None:
        """Write the posteriors of some molecules, ``FILE_MOLECULES`` at most to a file.

        Parameters
        ----------
        molecules : sequence of int
            The molecules' indices in the stack.
        draws : sequence of ndarray, each shape (chains, draws, 6)
            Each molecule's draws of ``x0 y0 s_x s_y N b``.
        counts : array_like, shape (m, roi, roi)
            Their ROIs.
        attributes : mapping of str to str
            What the molecules share (``result_file.result_attributes``).
        per_molecule : sequence of mapping of str to str
            Each molecule's JSON attributes, of ``MOLECULE_ATTRIBUTES`` (absent ones are
            stored empty).
        """
        counts = np.asarray(counts)
        if not self.keeps_draws():  # a draw axis of length 0: the files keep the rest
            draws = [np.asarray(d)[:, :0] for d in draws]
        for first in range(0, len(molecules), FILE_MOLECULES):
            part = slice(first, first + FILE_MOLECULES)
            tree = _tree(molecules[part], draws[part], counts[part], attributes, per_molecule[part])
            span = [int(m) for m in molecules[part]]
            path = self.path / f"posteriors-{min(span):06d}-{max(span):06d}.nc"
            partial = path.with_name(path.name + ".partial")
            tree.to_netcdf(partial, engine="h5netcdf")
            os.replace(partial, path)

    def write_outcomes(
        self,
        molecules: Sequence[int],
        outcomes: Sequence[dict],
        counts: ArrayLike,
        rows: Sequence[dict],
        model: Model,
        scene: Scene | None = None,
        truths: ArrayLike | None = None,
    ) -> None:
        """Write the batched engine's posteriors (``bayespsf.inference.batched``).

        Parameters
        ----------
        molecules : sequence of int
            The molecules' indices in the stack.
        outcomes : sequence of dict
            Each molecule's ``draws`` (independent, shape (n, 6)) and ``info`` (the
            sampler's record).
        counts : array_like, shape (m, roi, roi)
            Their ROIs.
        rows : sequence of dict
            Their summary rows.
        model : Model
            The inference model (camera, geometry and photon unit are recorded).
        scene : Scene, optional
            Recorded as TOML.
        truths : array_like, shape (m, 6), optional
            True parameters.
        """
        from bayespsf.inference.batched import as_stored

        stored = [
            as_stored(outcome, None if truths is None else truths[k], row)
            for k, (outcome, row) in enumerate(zip(outcomes, rows, strict=True))
        ]
        self.write(
            molecules,
            [draws for draws, _ in stored],
            counts,
            result_attributes(model, scene),
            [attrs for _, attrs in stored],
        )

    def write_posterior(self, index: int, posterior: Posterior) -> None:
        """Write one molecule's posterior (a file of its own).

        Parameters
        ----------
        index : int
            The molecule's index in the stack.
        posterior : Posterior
            Its posterior, with its counts (group ``observed_data``).
        """
        tree = posterior.tree
        post = tree["posterior"]
        draws = np.stack([post[name].values for name in PARAMETER_NAMES], axis=-1)
        attrs = dict(tree.attrs)
        own = {key: attrs.pop(key) for key in MOLECULE_ATTRIBUTES if key in attrs}
        counts = tree["observed_data"]["counts"].values[None]
        self.write([index], [draws], counts, attrs, [own])

    def write_summary(self, table: pd.DataFrame, runner: cf.Executor | None = None) -> None:
        """Write ``summary.csv`` atomically.

        Parameters
        ----------
        table : pandas.DataFrame
            ``sample_many``'s summary table.
        runner : concurrent.futures.Executor, optional
            Workers that format its rows (``write_csv``); default this process.
        """
        partial = self.path / "summary.csv.partial"
        write_csv(table, partial, runner)
        os.replace(partial, self.path / "summary.csv")

    def _read(self, path: Path, group: str | None = None) -> xr.DataTree:
        """A result file of the store, whole or one ``group``, or an error naming it and the
        way on."""
        again = "delete it and rerun to sample its molecules again"
        needed = {"posterior", "observed_data", "molecules"} if group is None else {group}
        try:
            tree = open_result_file(path, group)
        except MissingGroup:
            tree = None
        except BayespsfInputError as exc:
            raise BayespsfInputError(f"{exc}; {again}") from None
        if tree is None or (group is None and not needed <= set(tree.children)):
            raise BayespsfInputError(
                f"{path}: not a file of a bayespsf store (it needs the groups posterior, "
                f"observed_data and molecules); {again}"
            )
        return tree


def _span(path: Path) -> tuple[int, int] | None:
    """The first and last molecule a file's name gives (None for another name)."""
    match = _NAME.fullmatch(path.name)
    return None if match is None else (int(match[1]), int(match[2]))


def _molecules(molecules, path: Path) -> np.ndarray:
    """The molecule indices of a store file's ``molecules`` group."""
    if "molecule" not in molecules.coords or "summary_row" not in molecules.data_vars:
        raise BayespsfInputError(
            f"{path}: its molecules group has no molecule coordinate or summary_row; delete "
            "it and rerun to sample its molecules again"
        )
    return np.asarray(molecules["molecule"].values, dtype=np.int64)


def _tree(molecules, draws, counts, attributes, per_molecule):
    """A store file's tree: draws padded with NaN to the longest chain and run."""
    import xarray as xr

    chains = max(d.shape[0] for d in draws)
    longest = max(d.shape[1] for d in draws)
    padded = np.full((len(draws), chains, longest, len(PARAMETER_NAMES)), np.nan)
    for k, d in enumerate(draws):
        padded[k, : d.shape[0], : d.shape[1]] = d
    coords = {"molecule": np.asarray(molecules, dtype=np.int64)}
    axes = ("molecule", "chain", "draw")
    posterior = xr.Dataset(
        {name: (axes, padded[..., k]) for k, name in enumerate(PARAMETER_NAMES)},
        coords=coords | {"chain": np.arange(chains), "draw": np.arange(longest)},
    )
    observed = xr.Dataset({"counts": (("molecule", "row", "column"), counts)}, coords=coords)
    table = {
        "chains": ("molecule", np.array([d.shape[0] for d in draws])),
        "draws": ("molecule", np.array([d.shape[1] for d in draws])),
    }
    for key in MOLECULE_ATTRIBUTES:
        text = np.array([own.get(key, "") for own in per_molecule], dtype=object)
        table[key] = ("molecule", text)
    tree = xr.DataTree.from_dict(
        {
            "posterior": posterior,
            "observed_data": observed,
            "molecules": xr.Dataset(table, coords=coords),
        }
    )
    tree.attrs.update(attributes)
    return tree


def _one(tree, k: int):
    """Molecule ``k`` of a store file's tree as a ``Posterior``."""
    from bayespsf.inference import Posterior

    table = tree["molecules"]
    chains, draws = int(table["chains"].values[k]), int(table["draws"].values[k])
    post = tree["posterior"]
    values = np.stack([post[name].values[k, :chains, :draws] for name in PARAMETER_NAMES], -1)
    result = Posterior.from_draws(values, counts=tree["observed_data"]["counts"].values[k])
    result.tree.attrs.update(tree.attrs)
    for key in MOLECULE_ATTRIBUTES:
        text = str(table[key].values[k])
        if text:
            result.tree.attrs[key] = text
    return result


def _atomic_write_text(path: Path, text: str) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    os.replace(partial, path)


__all__ = ["FILE_MOLECULES", "NO_DRAWS", "STORE_FORMAT", "Store"]
