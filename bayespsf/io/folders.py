"""Output folders: where a command or a function may write its results.

``output_folder`` checks a folder (or a path stem) before any work: no file stands where a
folder must be, and the folder, or the nearest of its parents that exists, can be written.
What a folder holds, and whether another run's results are in it, is ``run_record``'s.
"""

from __future__ import annotations

import os
from pathlib import Path

from bayespsf.errors import BayespsfInputError


def _named(option: str, folder: Path) -> str:
    """``--out FOLDER`` for a command's flag, ``out='FOLDER'`` for a Python argument."""
    return f"{option} {folder}" if option.startswith("-") else f"{option}={str(folder)!r}"


def output_folder(folder: str | os.PathLike, option: str = "out", stem: bool = False) -> Path:
    """``folder`` as a folder to write into: no file may stand at it or at any of its parents.

    Parameters
    ----------
    folder : str or path-like
        The output folder (it need not exist), or with ``stem`` a path stem (``OUT`` of
        ``OUT.npy``, ``OUT.truth.csv``) whose folder is made.
    option : str, default "out"
        What names it in messages: a flag (``--out``) or a Python argument (``out``).
    stem : bool, default False
        Whether ``folder`` is a path stem rather than a folder.

    Returns
    -------
    pathlib.Path
        ``folder``.

    Raises
    ------
    BayespsfInputError
        If a file stands at ``folder`` or at one of its parents, a stem is a folder, or the
        nearest of them that exists cannot be written (its permissions, or a read-only file
        system): before any work, not when the first file is written.
    """
    folder = Path(folder)
    if stem and folder.is_dir():
        raise BayespsfInputError(
            f"{_named(option, folder)} is a folder; give a path stem such as {folder}/sim"
        )
    places = folder.parents if stem else (folder, *folder.parents)
    for place in places:
        if place.exists() and not place.is_dir():
            what = "is" if place == folder else f"lies under {place}, which is"
            raise BayespsfInputError(
                f"{_named(option, folder)} {what} a file, not a folder; give {option} a "
                "folder to write into"
            )
    existing = next((place for place in places if place.exists()), None)
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise BayespsfInputError(
            f"{_named(option, folder)} cannot be written: {existing} is not writable (its "
            f"permissions, or a read-only file system); give {option} a folder that can be "
            "written"
        )
    return folder


__all__ = ["output_folder"]
