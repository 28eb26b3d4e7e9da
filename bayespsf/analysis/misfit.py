"""Where a model misfits, made visible: residual images and the width's dependence on the
fitting window (issue 14, item 5).

A goodness-of-fit p-value says *that* a ROI is not the model's; these say *how*:

* ``mean_residuals``: per molecule, the Pearson residuals ``(y - E y) / sd(y)`` of its frames
  at their fits (``y`` in N's unit, ``Model.to_photons``; ``E y`` and ``sd(y)`` from the camera
  law at the fit), averaged over the K frames and multiplied by ``sqrt(K)``: each pixel is then
  ~N(0, 1) where the model holds (up to the few degrees of freedom the fit takes), and a spot
  the model does not describe leaves a pattern (an Airy disk fitted with a Gaussian: a bright
  core and ring against a dim shoulder).
* ``width_by_window``: the mean fitted ``s_x`` and ``s_y`` of each molecule's frames when only
  the central ``w x w`` pixels are fitted, for several ``w``. A Gaussian spot gives the same
  width in every window within its error; a spot with heavier shoulders than a Gaussian gives
  a width that grows with the window (on a real bead image a user measured +6% from 7 x 7 to
  15 x 15).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.estimators import fit_mle
from bayespsf.model import MIN_ROI, Model
from bayespsf.movie.extract import check_sizes


def pearson_residuals(counts, model: Model, params) -> np.ndarray:
    """``(y - E y) / sd(y)`` per pixel of ``counts`` (n, roi, roi) at ``params`` (n, 6)."""
    lam = model.expected(np.asarray(params, dtype=np.float64))
    y = model.to_photons(model.check_counts(counts))
    return (y - lam / model.photoelectrons_per_photon) / np.sqrt(model.photon_variance(lam))


def mean_residuals(counts, model: Model, params, molecules) -> tuple[np.ndarray, np.ndarray]:
    """The molecules (sorted ids) and, per molecule, ``sqrt(K)`` times the mean over its K
    frames of the Pearson residuals at ``params``: (m,), (m, roi, roi). Frames with a
    non-finite fit are left out."""
    params = np.asarray(params, dtype=np.float64)
    molecules = np.asarray(molecules)
    if len(params) != len(counts) or len(molecules) != len(counts):
        raise BayespsfInputError(
            f"params ({len(params)} rows) and molecules ({len(molecules)}) must have one entry "
            f"per ROI of counts ({len(counts)})"
        )
    usable = np.isfinite(params).all(axis=1)
    residuals = pearson_residuals(np.asarray(counts)[usable], model, params[usable])
    ids, which = np.unique(molecules[usable], return_inverse=True)
    total = np.zeros((len(ids), *residuals.shape[1:]))
    np.add.at(total, which, residuals)
    k = np.bincount(which, minlength=len(ids))
    return ids, total / np.sqrt(k)[:, None, None]


def central(counts, window: int) -> np.ndarray:
    """The central ``window x window`` pixels of ROIs (n, roi, roi) of odd sizes (the sizes
    checked as ``movie.extract.check_sizes`` checks a fit inside a ROI)."""
    roi = counts.shape[-1]
    try:
        check_sizes(roi, window)
        small = window < MIN_ROI
    except BayespsfInputError as error:
        small, detail = True, f" ({error})"
    else:
        detail = ""
    if small:
        raise BayespsfInputError(
            f"window must be odd, from {MIN_ROI} to the ROI size {roi}; got {window!r}{detail}"
        )
    first = (roi - window) // 2
    return counts[..., first : first + window, first : first + window]


def width_by_window(counts, model: Model, molecules, windows=(7, 11, 15)) -> pd.DataFrame:
    """Per molecule and window: the number of frames whose fit converged, and the mean and
    standard error over them of the fitted ``s_x`` and ``s_y`` (nm), with the central
    ``window x window`` pixels of each ROI fitted by ``fit_mle`` (``model`` of the full ROI;
    windows larger than the ROI are skipped)."""
    counts = np.asarray(counts, dtype=np.float64)
    molecules = np.asarray(molecules)
    if len(molecules) != len(counts):
        raise BayespsfInputError(
            f"molecules ({len(molecules)}) must name the molecule of each ROI ({len(counts)})"
        )
    fitted = sorted(w for w in np.atleast_1d(windows) if w <= counts.shape[-1])
    if not fitted:
        raise BayespsfInputError(
            f"windows: none of {windows!r} fits in the {counts.shape[-1]}-pixel ROIs"
        )
    rows = []
    for window in fitted:
        fits = fit_mle(central(counts, window), model.for_roi(window), laplace=False, crlb=False)
        table = fits[["s_x", "s_y"]].where(fits["converged"].astype(bool), axis=0)
        table["molecule"] = molecules
        g = table.groupby("molecule")
        summary = pd.DataFrame({"window": window, "frames": g["s_x"].count()})
        for p in ("s_x", "s_y"):
            summary[p] = g[p].mean()
            summary[f"{p}_se"] = g[p].std(ddof=1) / np.sqrt(g[p].count())
        rows.append(summary.reset_index())
    return pd.concat(rows, ignore_index=True)


__all__ = ["central", "mean_residuals", "pearson_residuals", "width_by_window"]
