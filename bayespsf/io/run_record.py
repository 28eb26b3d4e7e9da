"""An output folder's run record, ``run.json``: which run the folder's results come from, so
that one folder never holds two runs' files.

A command that writes a folder (``bayespsf detect`` and ``bayespsf analyze``, and the Python
functions beneath them, ``bayespsf.movie.found.write`` and ``bayespsf.analyze``) states
what identifies its run as a dict (the command, a fingerprint of its data, the settings that
change its results) and the names of the files and folders it writes. Before it writes
anything, ``check_folder`` compares that dict with the folder's record:

- no record and none of those names in the folder: a new folder, go on;
- the same record: the same run again (a rerun, or a killed run resumed), go on;
- another record, or results without a record (made before runs were recorded, or by hand):
  ``RunConflict``, naming what differs, unless ``force``.

``claim_folder`` then removes, with ``force``, the files of the run the folder held (the names
the command writes and those the old record lists, never anything else), and writes the new
record, so that the folder describes one run. The record holds ``run`` (the dict compared),
``files`` (the names the run writes) and ``about`` (what is recorded but not compared, such as
the data's path: a moved movie is the same movie).

``file_fingerprint`` is the cheap content fingerprint of a data file that a run's dict can
hold: its size and the SHA-256 of 16 evenly spaced blocks of 256 KiB (4 MiB read at most;
the whole file when it is smaller), so a rerun does not read a movie of gigabytes twice.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Iterable, Mapping
from pathlib import Path

from bayespsf.errors import BayespsfInputError
from bayespsf.io.folders import _named, output_folder

#: The record's file name in the output folder.
RECORD_NAME = "run.json"
#: The record's ``format`` entry.
RECORD_FORMAT = "bayespsf run record 1"
#: Blocks hashed by ``file_fingerprint``, and their size in bytes.
FINGERPRINT_BLOCKS = 16
FINGERPRINT_BLOCK_BYTES = 1 << 18


def file_fingerprint(path: str | os.PathLike) -> dict:
    """A cheap fingerprint of a file's content: its size and a hash of sampled blocks.

    Parameters
    ----------
    path : str or path-like
        The file.

    Returns
    -------
    dict
        ``bytes`` (the file's size) and ``sha256`` (the hex digest of ``FINGERPRINT_BLOCKS``
        blocks of ``FINGERPRINT_BLOCK_BYTES`` bytes, evenly spaced from the file's first byte
        to its last, or of the whole file when it is no larger than they are).

    Raises
    ------
    BayespsfInputError
        If the file cannot be read.

    Notes
    -----
    The path and the modification time are not part of it: a movie copied or moved elsewhere
    is the same movie. Two files of one size that differ only between the sampled blocks have
    the same fingerprint; a run's other checks (the posterior store's digest of the ROIs it
    samples) still tell them apart.
    """
    path = Path(path)
    digest = hashlib.sha256()
    try:
        size = path.stat().st_size
        with path.open("rb") as handle:
            if size <= FINGERPRINT_BLOCKS * FINGERPRINT_BLOCK_BYTES:
                digest.update(handle.read())
            else:
                last = size - FINGERPRINT_BLOCK_BYTES
                for k in range(FINGERPRINT_BLOCKS):
                    handle.seek(last * k // (FINGERPRINT_BLOCKS - 1))
                    digest.update(handle.read(FINGERPRINT_BLOCK_BYTES))
    except OSError as exc:
        raise BayespsfInputError(f"{path}: cannot read it ({exc})") from exc
    return {"bytes": size, "sha256": digest.hexdigest()}


def bytes_digest(data: bytes) -> str:
    """The SHA-256 hex digest of ``data`` (a run's dict holds it for a file it copies)."""
    return hashlib.sha256(data).hexdigest()


def read_copies(copies: Mapping[str, str | os.PathLike] | None) -> dict[str, bytes]:
    """The bytes of the files a run copies verbatim into its folder, by the name each takes
    there (read before the folder is claimed: a source inside the folder survives ``force``).

    Parameters
    ----------
    copies : mapping of str to path, or None
        The name in the folder (a plain file name) -> the file to copy.

    Returns
    -------
    dict of str to bytes
        Each file's bytes by its name in the folder (empty for None).

    Raises
    ------
    BayespsfInputError
        If a name is not a plain file name, or a file cannot be read.
    """
    read = {}
    for name, source in (copies or {}).items():
        if _names([name]) != [name]:
            raise BayespsfInputError(f"copies: {name!r} is not a plain file name")
        try:
            read[name] = Path(source).read_bytes()
        except OSError as exc:
            raise BayespsfInputError(f"{source}: cannot read it ({exc})") from exc
    return read


def _plain(value):
    """NumPy values as Python ones, sets as sorted lists, anything else (a path) as text:
    JSON's ``default``."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, set | frozenset):
        return sorted(value, key=str)
    return str(value)


def as_json(run: Mapping) -> dict:
    """``run`` as JSON reads it back (tuples as lists, NumPy scalars as numbers), so that a
    record read from disk compares equal to the dict it was made from.

    Parameters
    ----------
    run : mapping
        What identifies a run.

    Returns
    -------
    dict
        Its JSON round trip.
    """
    return json.loads(json.dumps(dict(run), default=_plain))


def read_run_record(folder: str | os.PathLike) -> dict | None:
    """The run record of an output folder.

    Parameters
    ----------
    folder : str or path-like
        The output folder.

    Returns
    -------
    dict or None
        The record (``format``, ``run``, ``files``, ``about``), or None when the folder has
        no ``run.json``.

    Raises
    ------
    BayespsfInputError
        If ``run.json`` cannot be read as a run record.
    """
    path = Path(folder) / RECORD_NAME
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise BayespsfInputError(f"{path}: cannot read it as a run record ({exc})") from exc
    if not (
        isinstance(record, dict)
        and isinstance(record.get("run"), dict)
        and isinstance(record.get("files", []), list)
    ):
        raise BayespsfInputError(f"{path}: not a run record (no 'run' table)")
    return record


def run_differences(old: Mapping, new: Mapping) -> list[str]:
    """The keys whose values differ between two runs' dicts.

    Parameters
    ----------
    old, new : mapping
        What identifies each run (compared as JSON reads them back: ``as_json``).

    Returns
    -------
    list of str
        The keys present in one and not the other, or with other values: ``new``'s order,
        then ``old``'s own.
    """
    old, new = as_json(old), as_json(new)
    keys = [*new, *(k for k in old if k not in new)]
    return [k for k in keys if k not in old or k not in new or _text(old[k]) != _text(new[k])]


def _text(value) -> str:
    """A value's canonical JSON (NaN equals NaN, a table's key order does not count)."""
    return json.dumps(value, sort_keys=True)


class RunConflict(BayespsfInputError):
    """An output folder holds another run's results.

    Parameters
    ----------
    folder : Path
        The output folder.
    differ : list of str
        What differs between the folder's run and this one, in words (the keys of
        ``run_differences``, with both values where they are short); empty when the
        folder's results have no record or it cannot be read.
    found : list of str
        The other run's files and folders present.
    reason : str, optional
        Why the folder's run is unknown: no record, or an unreadable one.

    Attributes
    ----------
    folder, differ, found, reason
        As given.

    See Also
    --------
    check_folder : raises it.
    """

    def __init__(
        self, folder: Path, differ: list[str], found: list[str], reason: str | None = None
    ) -> None:
        self.folder, self.differ, self.found, self.reason = Path(folder), differ, found, reason
        super().__init__(self.message())

    def message(self, option: str = "out", force: str = "force=True") -> str:
        """The message, naming the folder's option and the way to force.

        Parameters
        ----------
        option : str, default "out"
            What names the folder (``--out`` on the command line).
        force : str, default "force=True"
            What replaces the folder's results (``--force`` on the command line).

        Returns
        -------
        str
            One sentence: what the folder holds, what differs, and the two ways on.
        """
        way = f"give a new {option} folder, or {force} to replace them"
        where = _named(option, self.folder)
        if self.reason is None:
            verb = "differs" if len(self.differ) == 1 else "differ"
            return (
                f"{where} holds the results of another run: {', '.join(self.differ)} {verb}; {way}"
            )
        shown = ", ".join(self.found[:4]) + (", ..." if len(self.found) > 4 else "")
        return f"{where} holds results ({shown}) {self.reason}; {way}"


def _names(names: Iterable[str]) -> list[str]:
    """Plain names of entries of the folder itself (a record edited by hand cannot name a
    path elsewhere)."""
    plain = []
    for name in names:
        if isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name:
            plain.append(name)
    return list(dict.fromkeys(plain))


def _with_copies(run, files, copies) -> tuple[dict, list[str]]:
    """``run`` with the digests of ``copies``, and ``files`` with their names."""
    copies = copies or {}
    digests = {name: bytes_digest(data) for name, data in copies.items()}
    return {**run, **digests}, _names([*files, *copies])


def _described(old: Mapping, new: Mapping) -> list[str]:
    """What differs, in words: a key, with both values where they are short scalars; only
    the command where the commands differ (their other keys differ with them)."""
    old, new = as_json(old), as_json(new)
    differ = run_differences(old, new)
    if "command" in differ:
        differ = ["command"]
    words = []
    for key in differ:
        a, b = old.get(key), new.get(key)
        scalar = all(isinstance(v, str | int | float | None) and len(str(v)) <= 40 for v in (a, b))
        words.append(f"{key} ({a} there, {b} now)" if scalar else key)
    return words


def check_folder(
    folder: str | os.PathLike,
    run: Mapping,
    files: Iterable[str],
    *,
    force: bool = False,
    option: str = "out",
    copies: Mapping[str, bytes] | None = None,
) -> list[str]:
    """Check, before writing anything, that a folder holds no other run's results.

    Parameters
    ----------
    folder : str or path-like
        The output folder (it need not exist).
    run : mapping
        What identifies this run (JSON-serialisable; compared with the folder's record).
    files : iterable of str
        The names of the files and folders this run writes into ``folder``.
    force : bool, default False
        Whether another run's results may be replaced.
    option : str, default "out"
        What names the folder in messages.
    copies : mapping of str to bytes, optional
        Files the run copies into the folder (``read_copies``), by name: their names join
        ``files`` and their SHA-256 digests join ``run``.

    Returns
    -------
    list of str
        The entries ``claim_folder`` removes: with ``force``, every one of ``files`` and of
        the old record's files present, and ``run.json``; otherwise none.

    Raises
    ------
    BayespsfInputError
        If ``folder`` is, or lies under, a file (naming ``option``), or holds a posterior
        store (a ``manifest.json``: ``force`` does not remove another kind of run).
    RunConflict
        Without ``force``, if the folder holds another run's results: its record names
        another run, it cannot be read, or some of ``files`` are there without a record.

    Notes
    -----
    Nothing is read but ``run.json`` and nothing is written. A folder whose record is this
    run's goes on as it is (a rerun, or a killed run resumed).
    """
    folder = output_folder(folder, option)
    if (folder / "manifest.json").is_file():  # not --force's to remove: a store is one whole
        raise BayespsfInputError(
            f"{folder} holds a posterior store (manifest.json: the results of `bayespsf fit` "
            "or sample_many); write this run's results to another folder"
        )
    run, files = _with_copies(run, files, copies)
    try:
        record = read_run_record(folder)
        problem = None
    except BayespsfInputError as exc:
        record, problem = None, f"and a run record that cannot be read ({exc})"
    listed = _names(record.get("files", [])) if record else []
    found = [n for n in dict.fromkeys([*files, *listed]) if (folder / n).exists()]
    if record is not None and not run_differences(record["run"], run):
        return [*found, RECORD_NAME] if force else []
    if record is None and problem is None and not found:
        return []
    if force:
        return [*found, RECORD_NAME]
    if record is not None:
        raise RunConflict(folder, _described(record["run"], run), found)
    if problem is None:
        problem = (
            f"but no run record ({RECORD_NAME}): they were made before bayespsf recorded "
            "its runs, or by hand, and may be another run's"
        )
    raise RunConflict(folder, [], found or [RECORD_NAME], problem)


def claim_folder(
    folder: str | os.PathLike,
    run: Mapping,
    files: Iterable[str],
    *,
    force: bool = False,
    option: str = "out",
    about: Mapping | None = None,
    copies: Mapping[str, bytes] | None = None,
) -> dict[str, Path]:
    """Make ``folder`` this run's: check it, remove another run's files (with ``force``),
    write the run record and the files the run copies.

    Parameters
    ----------
    folder : str or path-like
        The output folder (made if missing).
    run : mapping
        What identifies this run (``check_folder``).
    files : iterable of str
        The names of the files and folders this run writes into ``folder``.
    force : bool, default False
        Whether another run's results may be replaced: its entries (``check_folder``'s
        list) are removed first, files and folders alike, and nothing else in the folder.
    option : str, default "out"
        What names the folder in messages.
    about : mapping, optional
        What the record keeps without comparing it (the data's path, for example).
    copies : mapping of str to bytes, optional
        Files to write into the folder, by name, after the record (``check_folder``).

    Returns
    -------
    dict of str to Path
        The record (``run.json``) and the copies, by name.

    Raises
    ------
    BayespsfInputError, RunConflict
        As ``check_folder``.
    """
    stale = check_folder(folder, run, files, force=force, option=option, copies=copies)
    run, files = _with_copies(run, files, copies)
    folder = Path(folder)
    for name in stale:
        entry = folder / name
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        elif entry.exists() or entry.is_symlink():
            entry.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    old = read_run_record(folder)  # the same run's record, or None
    listed = _names(old.get("files", [])) if old else []
    record = {
        "format": RECORD_FORMAT,
        "run": as_json(run),
        "files": sorted(set(listed) | set(_names(files))),
        "about": as_json(about or {}),
    }
    path = folder / RECORD_NAME
    partial = folder / (RECORD_NAME + ".partial")
    partial.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    os.replace(partial, path)
    paths = {RECORD_NAME: path}
    for name, data in (copies or {}).items():
        paths[name] = folder / name
        paths[name].write_bytes(data)
    return paths


__all__ = [
    "FINGERPRINT_BLOCKS",
    "FINGERPRINT_BLOCK_BYTES",
    "RECORD_FORMAT",
    "RECORD_NAME",
    "RunConflict",
    "as_json",
    "bytes_digest",
    "check_folder",
    "claim_folder",
    "file_fingerprint",
    "read_copies",
    "read_run_record",
    "run_differences",
]
