"""Localisation tables in the files that the field's tools open (issue 14, item 6).

One row per analysed (molecule, frame). ``localizations`` turns posterior summary rows (the
columns of ``bayespsf.posterior_rows.draws_row``: ``x0_mean``, ``x0_sd``, quantiles, ESS, ...)
and each ROI's place in the movie into picasso's columns followed by bayespsf's own; the
writers put it into

* ``locs.hdf5`` + ``locs.yaml``: picasso's format (``picasso.io.load_locs`` opens it): an HDF5
  compound dataset ``locs`` with ``frame`` (uint32), ``x``, ``y``, ``photons``, ``sx``, ``sy``,
  ``bg``, ``lpx``, ``lpy`` (float32; positions and widths in camera pixels with the centre of
  pixel (row 0, column 0) at (0, 0), as picasso's Localize writes them; ``photons`` net, ``bg``
  per pixel; ``lpx``, ``lpy`` the posterior SDs of the position), then bayespsf's columns
  (those finite wherever a position is: picasso's loader drops any row with a NaN); the YAML
  holds ``Width``, ``Height``, ``Frames``, ``Pixelsize`` (nm), bayespsf's provenance and the
  names of the columns left out;
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

from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf._checks import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES

PICASSO_COLUMNS = ("frame", "x", "y", "photons", "sx", "sy", "bg", "lpx", "lpy")
INTERVAL = ("q0025", "q0975")  # the central 95% interval's quantile columns
PLACE_COLUMNS = ("molecule", "frame", "row", "col")  # the ROI centre's movie pixel


def localizations(posteriors: pd.DataFrame, pixel_size: float) -> pd.DataFrame:
    """picasso's columns, then bayespsf's, from posterior summary rows.

    ``posteriors`` has one row per (molecule, frame): ``PLACE_COLUMNS`` (``row``, ``col``: the
    movie pixel at the fitted ROI's centre, which the model's x0 = y0 = 0 is the centre of),
    and for each of x0 y0 s_x s_y N b its ``_mean``, ``_sd`` and 95% interval columns; other
    columns (``selected``, ``method``, ``converged``, ESS, ``photon_unit``, ...) follow.
    """
    a = scalar_in_range("pixel_size", pixel_size, 0.0, low_inclusive=False)
    needed = [*PLACE_COLUMNS] + [
        f"{p}_{stat}" for p in PARAMETER_NAMES for stat in ("mean", "sd", *INTERVAL)
    ]
    missing = [c for c in needed if c not in posteriors.columns]
    if missing:
        raise BayespsfInputError(f"posteriors: no column(s) {', '.join(missing)}")
    t = posteriors
    frame = t["frame"].to_numpy(float)
    if not np.all((frame >= 0) & (frame == np.round(frame))):
        raise BayespsfInputError("posteriors: frame must hold whole numbers >= 0")
    locs = pd.DataFrame(
        {
            "frame": t["frame"].to_numpy(np.uint32),
            "x": (t["col"] + t["x0_mean"] / a).to_numpy(np.float32),
            "y": (t["row"] + t["y0_mean"] / a).to_numpy(np.float32),
            "photons": t["N_mean"].to_numpy(np.float32),
            "sx": (t["s_x_mean"] / a).to_numpy(np.float32),
            "sy": (t["s_y_mean"] / a).to_numpy(np.float32),
            "bg": t["b_mean"].to_numpy(np.float32),
            "lpx": (t["x0_sd"] / a).to_numpy(np.float32),
            "lpy": (t["y0_sd"] / a).to_numpy(np.float32),
        }
    )
    if "z_mean" in t:  # a z calibration was given (bayespsf.axial): picasso's z and lpz, nm
        locs["z"] = t["z_mean"].to_numpy(np.float32)
        locs["lpz"] = t["z_sd"].to_numpy(np.float32)
    rest = [c for c in t.columns if c not in (*PICASSO_COLUMNS, "row", "col")]
    return pd.concat([locs, t[rest].reset_index(drop=True)], axis=1)


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


def write_picasso(locs: pd.DataFrame, path, info: dict) -> tuple[Path, Path]:
    """``path`` (``.hdf5``) and its ``.yaml``: picasso's localisation file. ``info`` must hold
    ``Width``, ``Height``, ``Frames`` (camera pixels, frames) and ``Pixelsize`` (nm)."""
    import h5py
    import yaml

    missing = [k for k in ("Width", "Height", "Frames", "Pixelsize") if k not in info]
    if missing:
        raise BayespsfInputError(f"info: picasso needs {', '.join(missing)}")
    path = Path(path)
    kept, omitted = _picasso_safe_columns(locs)
    info = {**info, "bayespsf columns left out (NaN where a position exists)": omitted}
    with h5py.File(path, "w") as f:
        f.create_dataset("locs", data=_structured(locs[kept]))
    sidecar = path.with_suffix(".yaml")
    sidecar.write_text(yaml.safe_dump_all([_plain(info)], sort_keys=False))
    return path, sidecar


def _picasso_safe_columns(locs: pd.DataFrame) -> tuple[list[str], list[str]]:
    """The columns to write for picasso, and those left out. picasso's loader drops every row
    with a NaN in any column (``picasso.lib.ensure_sanity``), so a column that is NaN in some
    row that has a position (``acceptance`` of a Laplace row beside a chain's) would hide
    that row; such columns stay in ``locs.parquet`` only. Rows without a position (a refused
    ROI) are written, and picasso leaves them out."""
    placed = locs[list(PICASSO_COLUMNS)].notna().all(axis=1)
    kept, omitted = [], []
    for name in locs.columns:
        column = locs.loc[placed, name]
        numeric = pd.api.types.is_numeric_dtype(column) and not pd.api.types.is_bool_dtype(column)
        if name in PICASSO_COLUMNS or not numeric or np.isfinite(column.to_numpy(float)).all():
            kept.append(name)
        else:
            omitted.append(name)
    return kept, omitted


def _plain(value):
    """``value`` with numpy scalars as Python numbers (YAML's safe dumper takes only those)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def thunderstorm_table(locs: pd.DataFrame, pixel_size: float) -> pd.DataFrame:
    """ThunderSTORM's results table (module docstring) of ``localizations``' table."""
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


def write_all(locs: pd.DataFrame, folder, info: dict) -> dict[str, Path]:
    """``locs.hdf5``, ``locs.yaml``, ``locs.csv`` (ThunderSTORM) and ``locs.parquet`` in
    ``folder``; returns their paths by name."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hdf5, yaml_path = write_picasso(locs, folder / "locs.hdf5", info)
    csv = folder / "locs.csv"
    thunderstorm_table(locs, info["Pixelsize"]).to_csv(csv, index=False)
    parquet = folder / "locs.parquet"
    locs.to_parquet(parquet, index=False)
    return {"locs.hdf5": hdf5, "locs.yaml": yaml_path, "locs.csv": csv, "locs.parquet": parquet}


__all__ = [
    "PICASSO_COLUMNS",
    "localizations",
    "thunderstorm_table",
    "write_all",
    "write_picasso",
]
