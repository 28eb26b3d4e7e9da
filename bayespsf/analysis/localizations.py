"""The localisation table: one row per analysed (molecule, frame), picasso's columns followed by
bayespsf's own, from posterior summary rows (the columns of
``bayespsf.inference.summary.draws_row``: ``x0_mean``, ``x0_sd``, quantiles, ESS, ...) and each
ROI's place in the movie. ``bayespsf.io.locs`` writes it in the files the field's tools open."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

from bayespsf._validate import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.io.locs import PICASSO_COLUMNS
from bayespsf.psf import PARAMETER_NAMES

INTERVAL = ("q0025", "q0975")  # the central 95% interval's quantile columns
PLACE_COLUMNS = ("molecule", "frame", "row", "col")  # the ROI centre's movie pixel
# the columns the reasons for a missing value come from (missing_values)
_CONTEXT = ("status", "message", "method", "mle_converged", "mle_status", "mle_message")
_CONTEXT += ("gof_replicates", "z_why")


def localizations(
    posteriors: pd.DataFrame, pixel_size: float, estimate: str = "posterior"
) -> pd.DataFrame:
    """The localisation table: picasso's columns, then bayespsf's, from posterior summary rows
    (or from maximum-likelihood fits).

    Parameters
    ----------
    posteriors : pandas.DataFrame
        One row per (molecule, frame): ``PLACE_COLUMNS`` (``molecule``, ``frame``; ``row``,
        ``col``: the movie pixel at the fitted ROI's centre, which the model's x0 = y0 = 0 is
        the centre of), and for each of x0 y0 s_x s_y N b its ``_mean``, ``_sd`` and 95%
        interval (``_q0025``, ``_q0975``) columns; optionally ``z_mean`` and ``z_sd`` (nm).
    pixel_size : float
        Pixel side in nm (> 0).
    estimate : {"posterior", "mle"}, default "posterior"
        Where picasso's columns come from: the posterior's means and SDs, or the MLE
        (``<p>_mle``) and its Cramér-Rao bound (``crlb_<p>``) as ``lpx``, ``lpy``; then
        ``posteriors`` needs those columns instead of the posterior's, and a row whose fit did
        not converge (``mle_converged`` false) has no position: NaN in picasso's columns,
        which picasso leaves out, its fit kept in ``<p>_mle``.

    Returns
    -------
    pandas.DataFrame
        One row per row of ``posteriors``: picasso's ``frame`` (uint32), ``x``, ``y``
        (camera pixels, picasso's convention), ``photons``, ``sx``, ``sy`` (pixels), ``bg``
        (photons per pixel), ``lpx``, ``lpy`` (posterior SDs of x and y, pixels), all
        float32, and with a z calibration ``z`` and ``lpz`` (nm); then every other column of
        ``posteriors`` but ``row`` and ``col`` (``molecule``, the summaries, ``selected``,
        ``method``, ``converged``, ESS, ``photon_unit``, ...); last ``missing``
        (``missing_values``): which of the row's values are NaN and why, ``""`` where none
        is. ``bayespsf.io.write_locs`` writes such values into ``locs.hdf5`` as its fill value.

    Raises
    ------
    BayespsfInputError
        A ``pixel_size`` that is not > 0, an unknown ``estimate``, missing columns, or frames
        that are not whole numbers >= 0.

    See Also
    --------
    analyze : makes and writes this table.
    bayespsf.io.write_locs : writes it for picasso, ThunderSTORM and as parquet.
    """
    a = scalar_in_range("pixel_size", pixel_size, 0.0, low_inclusive=False)
    if estimate not in ("posterior", "mle"):
        raise BayespsfInputError(f"estimate must be 'posterior' or 'mle', got {estimate!r}")
    if estimate == "posterior":
        value, spread = "{}_mean", "{}_sd"
        needed = [f"{p}_{stat}" for p in PARAMETER_NAMES for stat in ("mean", "sd", *INTERVAL)]
    else:
        value, spread = "{}_mle", "crlb_{}"
        needed = [c.format(p) for p in PARAMETER_NAMES for c in (value, spread)]
    needed = [*PLACE_COLUMNS, *needed]
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
            "x": (t["col"] + t[value.format("x0")] / a).to_numpy(np.float32),
            "y": (t["row"] + t[value.format("y0")] / a).to_numpy(np.float32),
            "photons": t[value.format("N")].to_numpy(np.float32),
            "sx": (t[value.format("s_x")] / a).to_numpy(np.float32),
            "sy": (t[value.format("s_y")] / a).to_numpy(np.float32),
            "bg": t[value.format("b")].to_numpy(np.float32),
            "lpx": (t[spread.format("x0")] / a).to_numpy(np.float32),
            "lpy": (t[spread.format("y0")] / a).to_numpy(np.float32),
        }
    )
    if estimate == "mle" and "mle_converged" in t:  # no position from a fit that did not end
        failed = ~t["mle_converged"].to_numpy(bool)
        locs.loc[failed, [c for c in locs.columns if c != "frame"]] = np.nan
    if "z_mean" in t:  # a z calibration was given (bayespsf.axial): picasso's z and lpz, nm
        locs["z"] = t["z_mean"].to_numpy(np.float32)
        locs["lpz"] = t["z_sd"].to_numpy(np.float32)
    rest = [c for c in t.columns if c not in (*PICASSO_COLUMNS, "row", "col", "missing")]
    out = pd.concat([locs, t[rest].reset_index(drop=True)], axis=1)
    out["missing"] = missing_values(out)
    return out


def locs_info(movie, model, generated_by: str, settings: dict) -> dict:
    """picasso's YAML content for ``bayespsf.io.write_locs``: the movie's ``Width``,
    ``Height`` and ``Frames``, the model's ``Pixelsize`` (nm), ``Generated by`` and, under
    ``bayespsf``, the model, its photon unit and ``settings`` (the run's options and
    provenance)."""
    _, height, width = movie.shape
    return {
        "Width": int(width),
        "Height": int(height),
        "Frames": len(movie),
        "Pixelsize": float(model.pixel_size),
        "Generated by": generated_by,
        "bayespsf": {"model": repr(model), "photon_unit": model.photon_unit_label, **settings},
    }


def missing_values(locs: pd.DataFrame) -> pd.Series:
    """Per row, which of its numeric values are missing (NaN or infinite) and why.

    Parameters
    ----------
    locs : pandas.DataFrame
        A localisation table (``localizations``' columns, or any of them).

    Returns
    -------
    pandas.Series of str
        ``""`` where every value is present; else ``"; "``-separated groups ``columns:
        reason``, the columns named with ``*`` for the parameter (``crlb_*: the
        maximum-likelihood fit did not converge``). The reasons come from the row's own
        columns: ``status`` and ``message`` (no posterior: refused or failed), ``method``
        (``acceptance`` exists for a Markov chain only), ``mle_converged`` (the MLE, its
        Cramér-Rao bound and the goodness of fit's test), ``gof_replicates``, ``z_why``.
    """
    numeric = [
        c
        for c in locs.columns
        if pd.api.types.is_numeric_dtype(locs[c]) and not pd.api.types.is_bool_dtype(locs[c])
    ]
    with np.errstate(invalid="ignore"):
        absent = ~np.isfinite(locs[numeric].to_numpy(np.float64))
    out = np.full(len(locs), "", dtype=object)
    rows = np.flatnonzero(absent.any(axis=1))
    if rows.size == 0:
        return pd.Series(out, index=locs.index, dtype=object)
    # rows alike in what is missing and in the columns the reasons come from share one text:
    # grouped by pandas (in compiled code), each group's text made from its first row
    keys = pd.DataFrame(np.packbits(absent[rows], axis=1))
    for c in _CONTEXT:
        if c in locs:  # numbers by value (NaN a group of its own: dropna=False), else as text
            values = locs[c].iloc[rows]
            by_value = isinstance(values.dtype, np.dtype) and values.dtype.kind in "biuf"
            keys[c] = values.to_numpy() if by_value else np.asarray(values, object).astype(str)
    group = keys.groupby(list(keys.columns), sort=False, dropna=False).ngroup().to_numpy()
    first = np.unique(group, return_index=True)[1]
    texts = np.empty(len(first), dtype=object)
    for g, k in enumerate(first):
        i, groups = rows[k], {}
        row = locs.iloc[i]
        for name in (numeric[j] for j in np.flatnonzero(absent[i])):
            family = _family(name)
            reasons = groups.setdefault(_why_missing(row, name), [])
            if family not in reasons:
                reasons.append(family)
        texts[g] = "; ".join(f"{', '.join(f)}: {why}" for why, f in groups.items())
    out[rows] = texts[group]
    return pd.Series(out, index=locs.index, dtype=object)


def _family(name: str) -> str:
    """A column's name with its parameter as ``*`` and a quantile's digits as ``*``
    (``crlb_x0`` -> ``crlb_*``, ``s_x_q0025`` -> ``*_q*``)."""
    for p in sorted(PARAMETER_NAMES, key=len, reverse=True):
        if name.startswith(f"{p}_"):
            name = "*" + name[len(p) :]
            break
        if name.endswith(f"_{p}"):
            name = name[: -len(p)] + "*"
            break
    return re.sub(r"_q\d{4}$", "_q*", name)


def _why_missing(row: pd.Series, name: str) -> str:
    """Why ``row`` has no value of column ``name``, from the row's own columns."""
    status = str(row.get("status", ""))
    if status in ("refused", "failed"):  # no posterior: its columns and the position
        message = str(row.get("message", "") or "").strip()
        return f"no posterior ({status}{': ' + message if message else ''})"
    mle_failed = "mle_converged" in row and not bool(row["mle_converged"])
    if name == "acceptance" and str(row.get("method", "mcmc")) != "mcmc":
        return f"the {row['method']} posterior has no Markov chain"
    if mle_failed and name in PICASSO_COLUMNS and "x0_mean" not in row:  # from the MLE
        if row.get("mle_status") == "refused":
            return f"the ROI was refused ({str(row.get('mle_message', '')).strip()})"
        return "the maximum-likelihood fit did not converge"
    if name in ("z", "lpz") or name.startswith("z_"):
        why = str(row.get("z_why", "") or "").strip()
        return "no z posterior" + (f" ({why})" if why else "")
    if name.startswith("crlb_") or name.endswith("_mle"):
        if mle_failed:
            return "the maximum-likelihood fit did not converge"
        return "the information at the maximum-likelihood fit is not invertible"
    if name.endswith("_lsq"):
        return "the least-squares fit did not converge"
    if name == "gof_p":
        if mle_failed:
            return "no goodness-of-fit test (the maximum-likelihood fit did not converge)"
        if row.get("gof_replicates", 1) == 0:
            return "no goodness-of-fit test (no replicate's refit converged)"
        return "no goodness-of-fit test"
    if name == "gof_discrepancy" and mle_failed:
        return "the maximum-likelihood fit did not converge"
    if name.endswith("_rank"):
        return "too few near-independent draws for a rank"
    return "not computed for this row"


__all__ = ["INTERVAL", "PLACE_COLUMNS", "localizations", "missing_values"]
