"""Localisation tables in the files that the field's tools open.

One row per analysed (molecule, frame), as ``bayespsf.analysis.localizations`` makes it:
picasso's columns followed by bayespsf's own. The writers put it into

* ``locs.hdf5`` + ``locs.yaml``: picasso's format (``picasso.io.load_locs`` opens it): an HDF5
  compound dataset ``locs`` with ``frame`` (uint32), ``x``, ``y``, ``photons``, ``sx``, ``sy``,
  ``bg``, ``lpx``, ``lpy`` (float32; positions and widths in camera pixels with the centre of
  pixel (row 0, column 0) at (0, 0), as picasso's Localize writes them; ``photons`` net, ``bg``
  per pixel; ``lpx``, ``lpy`` the posterior SDs of the position), then every one of
  bayespsf's columns for every row. picasso's loader drops any row with a NaN or an infinity
  in any column, so a value of bayespsf's that is not finite (a Cramér-Rao bound where the
  MLE did not converge, ``gof_p`` without a converged refit, ``acceptance`` of a posterior
  made without a chain) is written as ``FILL_VALUE`` (9.969209968386869e36, netCDF's
  default fill value for doubles: finite, so picasso keeps the row, and far beyond any value
  the columns hold); the table's ``missing`` column says which values of a row are missing
  and why, and ``locs.parquet`` keeps them as NaN. picasso's own columns are never filled:
  a row without a position (a refused or failed ROI, or, with a z calibration, no z) keeps
  NaN there and picasso leaves it out. The YAML holds ``Width``, ``Height``, ``Frames``,
  ``Pixelsize`` (nm), bayespsf's provenance, the fill value, the columns that hold it and
  the count of rows without a position;
* ``locs.csv``: ThunderSTORM's results table (``id``, ``frame`` from 1, ``x [nm]``, ``y [nm]``,
  ``sigma1 [nm]``, ``sigma2 [nm]``, ``sigma [nm]``, ``intensity [photon]``, ``offset
  [photon]``, ``uncertainty_xy [nm]``). ThunderSTORM, as ImageJ, puts the top-left corner of
  pixel (0, 0) at the origin, so its ``x [nm]`` is ``(x + 0.5) pixel_size``. ``sigma [nm]``,
  the geometric mean of the two widths, is what ThunderSTORM's symmetric-Gaussian tables carry
  and what picasso's ``import_ts`` requires; ``uncertainty_xy`` is the root mean square of the
  two position SDs;
* ``locs.parquet``: the whole table.

With a z calibration (``bayespsf.axial``), picasso's ``z`` and ``lpz`` follow ``lpy`` (nm:
the z posterior's mean and SD) and ThunderSTORM's table has ``z [nm]`` and ``uncertainty_z
[nm]``; the z posterior's interval, k-hat and verdict are among bayespsf's columns.

Photons are in the model's ``photon_unit`` (a column of every table; picasso's and
ThunderSTORM's ``photon`` columns hold the same numbers).
"""

from __future__ import annotations

import concurrent.futures
import os
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.io.z_calibration import plain_values

PICASSO_COLUMNS = ("frame", "x", "y", "photons", "sx", "sy", "bg", "lpx", "lpy")
PICASSO_Z_COLUMNS = ("z", "lpz")  # picasso's columns of a 3D localisation (nm)
# what locs.hdf5 holds for a value of bayespsf's that is not finite (netCDF's NC_FILL_DOUBLE)
FILL_VALUE = 9.969209968386869e36


def _structured(locs: pd.DataFrame) -> np.ndarray:
    """The table as a numpy structured array that HDF5 stores as one compound dataset
    (strings as fixed-width bytes, which h5py and picasso read)."""
    fields, columns = [], []
    for name in locs.columns:
        values = locs[name]
        if values.dtype == object or pd.api.types.is_string_dtype(values):
            data = values.fillna("").astype(str).str.encode("utf-8").to_numpy()
            width = max(1, max((len(v) for v in data), default=1))
            fields.append((name, f"S{width}"))
            columns.append(data.astype(f"S{width}"))
        elif pd.api.types.is_bool_dtype(values):
            fields.append((name, np.bool_))
            columns.append(values.to_numpy(bool))
        else:
            data = values.to_numpy(dtype=np.float64 if values.isna().any() else None)
            fields.append((name, data.dtype))
            columns.append(data)
    out = np.empty(len(locs), dtype=fields)
    for (name, _), data in zip(fields, columns, strict=True):
        out[name] = data
    return out


def write_picasso(locs: pd.DataFrame, path: str | os.PathLike, info: dict) -> tuple[Path, Path]:
    """Write picasso's localisation file: ``path`` (``.hdf5``) and its ``.yaml``.

    Parameters
    ----------
    locs : pandas.DataFrame
        ``bayespsf.analysis.localizations``' table: ``PICASSO_COLUMNS`` (positions and
        widths in camera pixels, ``photons`` net, ``bg`` per pixel) then bayespsf's columns.
    path : str or path-like
        The HDF5 file; the YAML is written beside it (same name, ``.yaml``).
    info : dict
        The YAML's content: must hold ``Width``, ``Height``, ``Frames`` (camera pixels,
        frames) and ``Pixelsize`` (nm); any other keys (provenance) are kept.

    Returns
    -------
    tuple of pathlib.Path
        The HDF5 file and the YAML file.

    Raises
    ------
    BayespsfInputError
        If ``info`` lacks one of the four keys picasso needs.

    See Also
    --------
    write_locs : this file, ThunderSTORM's CSV and Parquet at once.

    Notes
    -----
    The HDF5 dataset ``locs`` is one compound dataset, strings as fixed-width bytes, with
    every column of ``locs`` for every row. picasso's loader drops every row with a NaN or an
    infinity in any column (``picasso.lib.ensure_sanity``), so a value of one of bayespsf's
    columns that is not finite is written as ``FILL_VALUE`` (9.969209968386869e36, netCDF's
    default fill value for doubles), which picasso keeps; the dataset's attribute
    ``fill_value`` and the YAML state it, the YAML names the columns that hold it, and
    ``locs.parquet`` keeps the NaN. ``bayespsf.analysis.localizations`` puts the reason for
    each missing value into the ``missing`` column. picasso's own columns (``PICASSO_COLUMNS``,
    ``z`` and ``lpz``) are not filled: a row without a position keeps NaN there, and picasso
    leaves it out; the YAML counts those rows. Format details: module docstring.
    """
    import h5py
    import yaml

    missing = [k for k in ("Width", "Height", "Frames", "Pixelsize") if k not in info]
    if missing:
        raise BayespsfInputError(f"info: picasso needs {', '.join(missing)}")
    path = Path(path)
    filled, columns = _filled(locs)
    own = [c for c in (*PICASSO_COLUMNS, *PICASSO_Z_COLUMNS) if c in locs]
    unplaced = int((~np.isfinite(locs[own].to_numpy(float))).any(axis=1).sum())
    info = {
        **info,
        "bayespsf fill value": FILL_VALUE,
        "bayespsf columns with filled values (see the missing column)": columns,
        "rows without a position (NaN; picasso leaves them out)": unplaced,
    }
    with h5py.File(path, "w") as f:
        dataset = f.create_dataset("locs", data=_structured(filled))
        dataset.attrs["fill_value"] = FILL_VALUE
    sidecar = path.with_suffix(".yaml")
    sidecar.write_text(yaml.safe_dump_all([plain_values(info)], sort_keys=False))
    return path, sidecar


def _filled(locs: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """``locs`` with every value of bayespsf's numeric columns that is not finite (NaN,
    infinity) replaced by ``FILL_VALUE``, and the names of the columns that hold it. picasso's
    own columns are left as they are: a row without a position is one picasso cannot show."""
    out, columns = locs.copy(), []
    for name in locs.columns:
        values = locs[name]
        numeric = pd.api.types.is_numeric_dtype(values) and not pd.api.types.is_bool_dtype(values)
        if name in (*PICASSO_COLUMNS, *PICASSO_Z_COLUMNS) or not numeric:
            continue
        data = values.to_numpy(dtype=np.float64 if values.isna().any() else None)
        if data.dtype.kind != "f":  # integers: always finite
            continue
        bad = ~np.isfinite(data)
        if bad.any():
            out[name] = np.where(bad, FILL_VALUE, data)
            columns.append(name)
    return out, columns


def thunderstorm_table(locs: pd.DataFrame, pixel_size: float) -> pd.DataFrame:
    """ThunderSTORM's results table of a localisation table.

    Parameters
    ----------
    locs : pandas.DataFrame
        ``bayespsf.analysis.localizations``' table (picasso's columns, in camera pixels).
    pixel_size : float
        Camera pixel size in nm.

    Returns
    -------
    pandas.DataFrame
        Columns ``id`` (from 1), ``frame`` (from 1), ``x [nm]``, ``y [nm]`` (from the
        top-left corner of pixel (0, 0)), ``z [nm]`` (with a z calibration), ``sigma1 [nm]``,
        ``sigma2 [nm]``, ``sigma [nm]`` (their geometric mean), ``intensity [photon]``,
        ``offset [photon]`` (per pixel), ``uncertainty_xy [nm]`` (root mean square of the
        two position SDs), ``uncertainty_z [nm]`` (with z) and ``molecule`` (where ``locs``
        has it).

    See Also
    --------
    write_locs : writes it as ``locs.csv``.

    Notes
    -----
    The conventions (ImageJ's origin, ``sigma [nm]`` as picasso's ``import_ts`` requires)
    are in the module docstring.
    """
    a = float(pixel_size)
    sx, sy = locs["sx"].astype(float) * a, locs["sy"].astype(float) * a
    table = pd.DataFrame(
        {
            "id": np.arange(1, len(locs) + 1),
            "frame": locs["frame"].astype(np.int64) + 1,
            "x [nm]": (locs["x"].astype(float) + 0.5) * a,
            "y [nm]": (locs["y"].astype(float) + 0.5) * a,
            "sigma1 [nm]": sx,
            "sigma2 [nm]": sy,
            "sigma [nm]": np.sqrt(sx * sy),
            "intensity [photon]": locs["photons"].astype(float),
            "offset [photon]": locs["bg"].astype(float),
            "uncertainty_xy [nm]": np.sqrt(
                0.5 * (locs["lpx"].astype(float) ** 2 + locs["lpy"].astype(float) ** 2)
            )
            * a,
        }
    )
    if "z" in locs:
        table.insert(4, "z [nm]", locs["z"].astype(float))
        table["uncertainty_z [nm]"] = locs["lpz"].astype(float)
    if "molecule" in locs:
        table["molecule"] = locs["molecule"].to_numpy()
    return table


def write_locs(
    locs: pd.DataFrame,
    folder: str | os.PathLike,
    info: dict,
    runner: concurrent.futures.Executor | None = None,
) -> dict[str, Path]:
    """Write a localisation table in the files the field's tools open.

    Parameters
    ----------
    locs : pandas.DataFrame
        ``bayespsf.analysis.localizations``' table: one row per analysed (molecule, frame),
        picasso's columns (``PICASSO_COLUMNS``: camera pixels, photons) then bayespsf's.
    folder : str or path-like
        Made if missing.
    info : dict
        picasso's YAML content: ``Width``, ``Height``, ``Frames`` (camera pixels, frames),
        ``Pixelsize`` (nm; also ThunderSTORM's scale) and any provenance.
    runner : concurrent.futures.Executor, optional
        Workers that format the rows of ``locs.csv`` (``bayespsf.parallel.tables.write_csv``);
        default this process.

    Returns
    -------
    dict of str to pathlib.Path
        The paths by name: ``locs.hdf5``, ``locs.yaml`` (picasso), ``locs.csv``
        (ThunderSTORM) and ``locs.parquet`` (the whole table).

    Raises
    ------
    BayespsfInputError
        If ``info`` lacks one of the keys picasso needs.

    See Also
    --------
    write_picasso, thunderstorm_table
    bayespsf.analyze : writes these files for a movie's molecules.

    Notes
    -----
    The formats, their coordinate conventions and the columns are described in the module
    docstring. ``locs.hdf5`` holds every column for every row; a value of bayespsf's columns
    that is not finite is ``FILL_VALUE`` there (9.969209968386869e36, which picasso's loader
    keeps where it would drop the row of a NaN) and NaN in ``locs.parquet``, and the
    table's ``missing`` column (``bayespsf.analysis.localizations``) says why.

    Examples
    --------
    >>> import tempfile
    >>> import pandas as pd
    >>> from bayespsf.io import write_locs
    >>> locs = pd.DataFrame({"frame": [0, 1], "x": [10.2, 10.3], "y": [5.1, 5.0],
    ...                      "photons": [900.0, 950.0], "sx": [1.2, 1.2], "sy": [1.3, 1.2],
    ...                      "bg": [10.0, 11.0], "lpx": [0.02, 0.02], "lpy": [0.02, 0.03]})
    >>> info = {"Width": 64, "Height": 64, "Frames": 2, "Pixelsize": 79.0}
    >>> sorted(write_locs(locs, tempfile.mkdtemp(), info))
    ['locs.csv', 'locs.hdf5', 'locs.parquet', 'locs.yaml']
    """
    from bayespsf.parallel.tables import write_csv  # here: bayespsf.parallel imports xarray

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hdf5, yaml_path = write_picasso(locs, folder / "locs.hdf5", info)
    csv = folder / "locs.csv"
    write_csv(thunderstorm_table(locs, info["Pixelsize"]), csv, runner)
    parquet = folder / "locs.parquet"
    locs.to_parquet(parquet, index=False)
    return {"locs.hdf5": hdf5, "locs.yaml": yaml_path, "locs.csv": csv, "locs.parquet": parquet}


__all__ = [
    "FILL_VALUE",
    "PICASSO_COLUMNS",
    "PICASSO_Z_COLUMNS",
    "thunderstorm_table",
    "write_locs",
    "write_picasso",
]
