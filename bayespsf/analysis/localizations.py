"""The localisation table: one row per analysed (molecule, frame), picasso's columns followed by
bayespsf's own, from posterior summary rows (the columns of
``bayespsf.inference.summary.draws_row``: ``x0_mean``, ``x0_sd``, quantiles, ESS, ...) and each
ROI's place in the movie. ``bayespsf.io.locs`` writes it in the files the field's tools open."""

from __future__ import annotations

import numpy as np
import pandas as pd

from bayespsf._validate import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.io.locs import PICASSO_COLUMNS
from bayespsf.psf import PARAMETER_NAMES

INTERVAL = ("q0025", "q0975")  # the central 95% interval's quantile columns
PLACE_COLUMNS = ("molecule", "frame", "row", "col")  # the ROI centre's movie pixel


def localizations(posteriors: pd.DataFrame, pixel_size: float) -> pd.DataFrame:
    """The localisation table: picasso's columns, then bayespsf's, from posterior summary rows.

    Parameters
    ----------
    posteriors : pandas.DataFrame
        One row per (molecule, frame): ``PLACE_COLUMNS`` (``molecule``, ``frame``; ``row``,
        ``col``: the movie pixel at the fitted ROI's centre, which the model's x0 = y0 = 0 is
        the centre of), and for each of x0 y0 s_x s_y N b its ``_mean``, ``_sd`` and 95%
        interval (``_q0025``, ``_q0975``) columns; optionally ``z_mean`` and ``z_sd`` (nm).
    pixel_size : float
        Pixel side in nm (> 0).

    Returns
    -------
    pandas.DataFrame
        One row per row of ``posteriors``: picasso's ``frame`` (uint32), ``x``, ``y``
        (camera pixels, picasso's convention), ``photons``, ``sx``, ``sy`` (pixels), ``bg``
        (photons per pixel), ``lpx``, ``lpy`` (posterior SDs of x and y, pixels), all
        float32, and with a z calibration ``z`` and ``lpz`` (nm); then every other column of
        ``posteriors`` but ``row`` and ``col`` (``molecule``, the summaries, ``selected``,
        ``method``, ``converged``, ESS, ``photon_unit``, ...).

    Raises
    ------
    BayespsfInputError
        A ``pixel_size`` that is not > 0, missing columns, or frames that are not whole
        numbers >= 0.

    See Also
    --------
    analyze : makes and writes this table.
    bayespsf.io.write_locs : writes it for picasso, ThunderSTORM and as parquet.
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


__all__ = ["INTERVAL", "PLACE_COLUMNS", "localizations"]
