"""A z calibration as a TOML file: saved, loaded, and recorded in the results that use it.

Layout (every number in nm, except the dimensionless A and B)::

    format = "bayespsf z calibration 1"
    curve = "huang"                      # or "polynomial"
    created = "2026-11-25T05:00:00+00:00"
    bayespsf = "0.1.0"
    [source]                             # provenance (the stack, the command), and:
    pixel_size = 100.0                   # the model's pixel size and camera kind the widths
    camera_kind = "emccd"                # were measured with (bayespsf.axial.calibrate)
    [x]                                  # and [y]: one table per axis
    w0 = 130.0
    c = -200.0
    d = 400.0
    A = 0.0
    B = 0.0
    covariance = [[...], ...]            # 5 x 5, in the order w0 c d A B
    chi2 = 26.5
    dof = 26
    p = 0.43
    [steps]                              # the per-step widths the curves were fitted to
    z = [...]
    s_x = [...]
    ...

``pixel_size`` and ``camera_kind`` of ``[source]`` are checked against the model a calibration
is used with (``bayespsf.axial.match.check_calibration``): the curves hold for the optics and
pixels of their bead stack, and another pixel size or camera is a named error.
"""

from __future__ import annotations

import datetime
import os
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.psf import CURVES, TERMS, Defocus, DefocusCalibration

FORMAT = "bayespsf z calibration 1"
STEP_COLUMNS = ("z", "frames", "s_x", "s_x_sd", "s_y", "s_y_sd")
#: The file's top-level keys (``calibration_dict``).
KEYS = ("format", "curve", "created", "bayespsf", "source", "x", "y", "steps")


def plain_values(value):
    """``value`` with NumPy scalars and arrays as Python numbers and lists, and dict keys as
    strings, recursively: what TOML, YAML's safe dumper and JSON write.

    Parameters
    ----------
    value : object
        A dict, list, tuple, array, NumPy scalar or anything else (returned as it is).

    Returns
    -------
    object
        The same content in plain Python types.
    """
    if isinstance(value, dict):
        return {str(k): plain_values(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [plain_values(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def calibration_dict(calibration: DefocusCalibration) -> dict:
    """The file's content as a dict (module docstring)."""
    from bayespsf import __version__

    out = {
        "format": FORMAT,
        "curve": calibration.curve,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "bayespsf": __version__,
        "source": plain_values(calibration.source),
    }
    for axis in ("x", "y"):
        row = calibration.fits.loc[axis]
        out[axis] = {t: float(row[t]) for t in TERMS}
        out[axis].update(
            covariance=plain_values(calibration.covariance[axis]),
            chi2=float(row["chi2"]),
            dof=int(row["dof"]),
            p=float(row["p"]),
        )
    steps = calibration.steps
    out["steps"] = {c: plain_values(steps[c].to_numpy()) for c in STEP_COLUMNS if c in steps}
    return out


def write_z_calibration(calibration: DefocusCalibration, path: str | os.PathLike) -> Path:
    """Write a z calibration to a TOML file.

    Parameters
    ----------
    calibration : DefocusCalibration
        The curves of both axes, their fits, covariances, steps and source
        (``bayespsf.axial.calibrate``).
    path : str or path-like
        The file (overwritten).

    Returns
    -------
    pathlib.Path
        ``path``.

    See Also
    --------
    read_z_calibration : reads it back.

    Notes
    -----
    The layout (every number in nm, except A and B) is in the module docstring.
    """
    import tomli_w

    path = Path(path)
    path.write_text(tomli_w.dumps(calibration_dict(calibration)))
    return path


def read_z_calibration(path: str | os.PathLike) -> DefocusCalibration:
    """Read a z calibration file.

    Parameters
    ----------
    path : str or path-like
        A TOML file written by ``write_z_calibration``.

    Returns
    -------
    DefocusCalibration
        The curve kind, the ``Defocus`` of both axes, the fits (indexed by axis: the terms
        ``w0 c d A B``, their SDs ``<t>_sd``, ``chi2``, ``dof``, ``p``), the 5 x 5
        covariances by axis, the steps, and the source (with ``file`` and ``created``).

    Raises
    ------
    BayespsfInputError
        If the file is missing or not TOML, a key is unknown or missing or a value bad (a
        ``[source] pixel_size`` that is not a number > 0, a covariance with an infinity, a
        fit's ``chi2``, ``dof`` or ``p`` that is not a number), named with the file.

    See Also
    --------
    write_z_calibration : writes one.
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BayespsfInputError(f"no calibration file {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BayespsfInputError(f"{path} is not a calibration file (not TOML: {exc})") from None
    where = f"calibration file {path}"
    unknown = sorted(set(doc) - set(KEYS))
    if unknown:
        raise BayespsfInputError(f"{where}: unknown key(s) {unknown}; a calibration has {KEYS}")
    if doc.get("format") != FORMAT:
        raise BayespsfInputError(f"{where}: format must be {FORMAT!r}, got {doc.get('format')!r}")
    curve = doc.get("curve")
    if curve not in CURVES:
        raise BayespsfInputError(f"{where}: curve must be one of {sorted(CURVES)}, got {curve!r}")
    rows, covariance, curves = [], {}, {}
    for axis in ("x", "y"):
        table = doc.get(axis)
        if not isinstance(table, dict):
            raise BayespsfInputError(f"{where}: no table [{axis}]")
        missing = [k for k in (*TERMS, "covariance", "chi2", "dof", "p") if k not in table]
        if missing:
            raise BayespsfInputError(f"{where}: [{axis}] has no {', '.join(missing)}")
        try:
            curves[axis] = CURVES[curve](*(table[t] for t in TERMS))
            cov = np.array(table["covariance"], dtype=np.float64)
        except (BayespsfInputError, TypeError, ValueError) as exc:
            raise BayespsfInputError(f"{where}: [{axis}]: {exc}") from None
        if cov.shape != (5, 5) or np.any(np.isinf(cov)):  # NaN where the fit had none
            raise BayespsfInputError(
                f"{where}: [{axis}] covariance must be 5 x 5 numbers (NaN where not defined)"
            )
        for key in ("chi2", "dof", "p"):  # the fit's record: numbers (NaN where not defined)
            if isinstance(table[key], bool) or not isinstance(table[key], int | float):
                raise BayespsfInputError(
                    f"{where}: [{axis}] {key} must be a number, got {table[key]!r}"
                )
        covariance[axis] = cov
        sd = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
        rows.append(
            {
                "axis": axis,
                **{t: float(table[t]) for t in TERMS},
                **{f"{t}_sd": s for t, s in zip(TERMS, sd, strict=True)},
                "chi2": table["chi2"],
                "dof": table["dof"],
                "p": table["p"],
            }
        )
    steps = pd.DataFrame(doc.get("steps", {}))
    recorded = doc.get("source", {})
    if not isinstance(recorded, dict):
        raise BayespsfInputError(f"{where}: source must be a table [source]")
    pixel_size = recorded.get("pixel_size", 1.0)
    if isinstance(pixel_size, bool) or not (
        isinstance(pixel_size, int | float) and np.isfinite(pixel_size) and pixel_size > 0
    ):
        raise BayespsfInputError(
            f"{where}: [source] pixel_size must be the stack's pixel size in nm (> 0), got "
            f"{pixel_size!r}"
        )
    source = {**recorded, "file": str(path), "created": doc.get("created")}
    return DefocusCalibration(
        curve,
        Defocus(curves["x"], curves["y"]),
        pd.DataFrame(rows).set_index("axis"),
        covariance,
        steps,
        source,
    )


__all__ = [
    "FORMAT",
    "calibration_dict",
    "plain_values",
    "read_z_calibration",
    "write_z_calibration",
]
