"""What a result file holds besides the draws, and how one is opened.

A result file (``Posterior.save``, and each molecule of a ``sample_many`` store) keeps, as
attributes, what made its draws: the camera, geometry, photon unit and scene, which a run's
molecules share (``result_attributes``), and per molecule the sampler's record, the
autocorrelation time and the truth (``molecule_attributes``), each a JSON table.
``open_result_file`` reads an HDF5/NetCDF4 file whole, or names the file and what it is
instead.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES

if TYPE_CHECKING:
    import xarray as xr

    from bayespsf.model import Model
    from bayespsf.scene import Scene

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"  # NetCDF4 files are HDF5 files
# the attributes a result file holds as JSON tables (``from_draws``; ``sample_many`` adds
# ``summary_row``); ``tau`` and ``truth`` map parameters to numbers
JSON_ATTRIBUTES = ("tau", "sampler", "camera", "geometry", "truth", "summary_row")
#: The attributes that differ between the molecules of one run (the rest they share).
MOLECULE_ATTRIBUTES = ("tau", "sampler", "truth", "summary_row")


class MissingGroup(BayespsfInputError):
    """A file that ``open_result_file`` was asked one group of does not have it."""


def result_attributes(model: Model | None = None, scene: Scene | None = None) -> dict[str, str]:
    """The attributes that the result files of one model and scene share.

    Parameters
    ----------
    model : Model, optional
        Its camera, geometry and photon unit are recorded.
    scene : Scene, optional
        Recorded as TOML.

    Returns
    -------
    dict of str to str
        ``bayespsf`` (what the draws are, in which units), and where given ``camera`` and
        ``geometry`` (JSON), ``photon_unit`` and ``scene`` (TOML).
    """
    unit = getattr(model, "photon_unit_label", "photons")
    attrs = {"bayespsf": f"posterior of x0 y0 s_x s_y N b (nm, {unit})"}
    if getattr(model, "camera", None) is not None:
        attrs["camera"] = json.dumps(model.camera.to_dict(), default=_jsonable)
        attrs["geometry"] = json.dumps({"roi": model.roi, "pixel_size": model.pixel_size})
        attrs["photon_unit"] = unit
    if scene is not None:
        attrs["scene"] = scene.dumps()
    return attrs


def molecule_attributes(
    tau: ArrayLike | None = None, info: dict | None = None, truth: ArrayLike | None = None
) -> dict[str, str]:
    """The attributes of one molecule's result, as JSON tables.

    Parameters
    ----------
    tau : array_like, shape (6,), optional
        Integrated autocorrelation time per parameter, in steps.
    info : dict, optional
        Sampler settings and run facts (JSON-serialisable).
    truth : array_like, shape (6,), optional
        True parameters.

    Returns
    -------
    dict of str to str
        ``tau`` and ``truth`` (parameter -> number) and ``sampler`` (``info``), those given.
    """
    attrs = {}
    if tau is not None:
        attrs["tau"] = json.dumps(dict(zip(PARAMETER_NAMES, map(float, tau), strict=True)))
    if info is not None:
        attrs["sampler"] = json.dumps(info)
    if truth is not None:
        attrs["truth"] = json.dumps(dict(zip(PARAMETER_NAMES, map(float, truth), strict=True)))
    return attrs


def open_result_file(path: str | os.PathLike, group: str | None = None) -> xr.DataTree:
    """Read an HDF5/NetCDF4 file whole into a tree, or say what it is instead.

    Parameters
    ----------
    path : str or path-like
        The file.
    group : str, optional
        Read only this group (and the groups under it); default the whole file.

    Returns
    -------
    xarray.DataTree
        Its groups (``group``'s as the root), loaded into memory (the file is closed).

    Raises
    ------
    BayespsfInputError
        Naming the file: missing, a directory, a named pipe, socket or device (refused before
        it is opened), empty, NetCDF3, not HDF5, or damaged or truncated; ``MissingGroup``
        (a subclass) where it has no ``group``.
    """
    import xarray as xr

    path = Path(path)
    what = _not_a_result_file(path)
    if what:
        raise BayespsfInputError(f"{path}: {what}")
    try:
        if not _readable_hdf5(path, group):  # before xarray: h5netcdf leaves a broken file
            raise MissingGroup(f"{path}: has no group {group!r}")
        # h5netcdf: the engine result files are written with; phony_dims names the dims of
        # a plain HDF5 file's datasets (it warns when left to its default)
        options = {"engine": "h5netcdf", "phony_dims": "access"}
        with xr.open_datatree(path, group=group, **options) as tree:
            return tree.load()
    except BayespsfInputError:
        raise
    except Exception as exc:  # h5py and xarray raise many kinds for a damaged file
        raise BayespsfInputError(
            f"{path}: a damaged or truncated result file ({type(exc).__name__}: {exc})"
        ) from None


def json_attribute(attrs, key: str, where: str) -> dict | None:
    """The JSON table stored in the attribute ``key`` of a result file (None where absent).

    Parameters
    ----------
    attrs : Mapping
        A result file's root attributes (``Posterior.tree.attrs``).
    key : str
        The attribute, one of ``JSON_ATTRIBUTES``.
    where : str
        What the attributes belong to (a file's path), for the message.

    Returns
    -------
    dict or None
        The decoded table; None where the attribute is absent.

    Raises
    ------
    BayespsfInputError
        Naming ``where`` and ``key``: the attribute is not a JSON table (a file truncated or
        edited after it was written), or ``tau`` or ``truth`` holds something other than
        numbers.
    """
    value = attrs.get(key)
    if value is None:
        return None
    try:
        table = json.loads(value)
    except (TypeError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
        why = f"not valid JSON ({exc})"
    else:
        numbers = key not in ("tau", "truth") or (
            isinstance(table, dict)
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in table.values())
        )
        if isinstance(table, dict) and numbers:
            return table
        what = "a table of numbers per parameter" if key in ("tau", "truth") else "a JSON table"
        why = f"not {what} (got {str(value)[:60]!r})"
    raise BayespsfInputError(
        f"{where}: its attribute {key!r} is damaged: {why}. The file was changed after "
        "bayespsf wrote it; sample this molecule again (in a store, delete the file and rerun: "
        "the run resumes and samples it again)"
    )


def _not_a_result_file(path: Path) -> str:
    """What ``path`` is instead of a result file, judged from its first bytes ('' if it may be
    one)."""
    if not path.exists():
        return "no such result file"
    if path.is_dir():
        return "is a directory, not a result file (.nc)"
    if not path.is_file():  # opening a named pipe nobody writes to would wait forever
        return "not a regular file (a named pipe, socket or device), not a result file (.nc)"
    with path.open("rb") as file:
        head = file.read(8)
    if not head:
        return "an empty file, not a result file"
    if head[:3] == b"CDF":
        return "a NetCDF3 file; bayespsf result files are NetCDF4 (HDF5)"
    if head != HDF5_SIGNATURE:
        return "not a bayespsf result file (NetCDF4/HDF5): its first bytes are not HDF5's"
    return ""


def _readable_hdf5(path: Path, group: str | None = None) -> bool:
    """Open ``path`` with h5py and read every dataset, or those under ``group`` (raises for a
    damaged file); False where there is no ``group``."""
    import h5py

    def read(_name, item):
        if isinstance(item, h5py.Dataset):
            item[()]

    with h5py.File(path, "r") as file:
        if group is not None and not isinstance(file.get(group), h5py.Group):
            return False
        (file if group is None else file[group]).visititems(read)
    return True


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in a result file")


__all__ = [
    "HDF5_SIGNATURE",
    "JSON_ATTRIBUTES",
    "MOLECULE_ATTRIBUTES",
    "MissingGroup",
    "json_attribute",
    "molecule_attributes",
    "open_result_file",
    "result_attributes",
]
