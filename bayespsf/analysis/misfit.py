"""Where a model misfits, made visible: residual images and the width's dependence on the
fitting window.

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

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle
from bayespsf.model import MIN_ROI, Model
from bayespsf.movie.extract import check_sizes

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


def pearson_residuals(counts: ArrayLike, model: Model, params: ArrayLike) -> np.ndarray:
    """``(y - E y) / sd(y)`` per pixel of ``counts`` (n, roi, roi) at ``params`` (n, 6)."""
    lam = model.expected(np.asarray(params, dtype=np.float64))
    y = model.to_photons(model.check_counts(counts))
    return (y - lam / model.photoelectrons_per_photon) / np.sqrt(model.photon_variance(lam))


def mean_residuals(
    counts: ArrayLike, model: Model, params: ArrayLike, molecules: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Each molecule's mean Pearson residual image at its frames' fits.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU, as ``model`` reads them.
    model : Model
        Camera law and geometry of the ROIs.
    params : array_like, shape (n, 6)
        Each ROI's fit ``x0 y0 s_x s_y N b`` (e.g. the MLE); rows with a non-finite value
        are left out.
    molecules : array_like, shape (n,)
        The molecule of each ROI.

    Returns
    -------
    ids : numpy.ndarray, shape (m,)
        The molecules, sorted.
    images : numpy.ndarray, shape (m, roi, roi)
        Per molecule, ``sqrt(K)`` times the mean over its K frames of the Pearson residuals
        ``(y - E y) / sd(y)``: ~N(0, 1) per pixel where the model holds.

    Raises
    ------
    BayespsfInputError
        ``params`` or ``molecules`` without one entry per ROI, or ``counts`` the model
        cannot read.

    See Also
    --------
    pearson_residuals : the residuals of each ROI.
    width_by_window : the width against the fitting window.

    Notes
    -----
    ``y`` is in N's unit (``Model.to_photons``), ``E y`` and ``sd(y)`` come from the camera
    law at the fit (module docstring). A spot the model does not describe leaves a pattern
    (an Airy disk fitted with a Gaussian: a bright core and ring against a dim shoulder).
    """
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


def central(counts: np.ndarray, window: int) -> np.ndarray:
    """The central ``window x window`` pixels of ROIs (n, roi, roi) of odd sizes (the sizes
    checked as ``movie.extract.check_sizes`` checks a fit inside a ROI)."""
    roi = counts.shape[-1]
    try:
        check_sizes(roi, window, names=("the ROI size", "window"), smallest=MIN_ROI)
    except BayespsfInputError as error:
        raise BayespsfInputError(
            f"window must be odd, from {MIN_ROI} to the ROI size {roi}; got {window!r} ({error})"
        ) from None
    first = (roi - window) // 2
    return counts[..., first : first + window, first : first + window]


def width_by_window(
    counts: ArrayLike,
    model: Model,
    molecules: ArrayLike,
    windows: ArrayLike = (7, 11, 15),
) -> pd.DataFrame:
    """Each molecule's mean fitted widths when only the central ``w x w`` pixels are fitted.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU.
    model : Model
        The model of the full ROI (``model.for_roi(window)`` fits each window).
    molecules : array_like, shape (n,)
        The molecule of each ROI.
    windows : array_like of int, default (7, 11, 15)
        Odd window sides in pixels, from ``MIN_ROI``; those larger than the ROI are skipped.

    Returns
    -------
    pandas.DataFrame
        One row per molecule and window: ``molecule``, ``window``, ``frames`` (whose fit
        converged), ``s_x``, ``s_x_se``, ``s_y``, ``s_y_se`` (the mean over those frames of
        the fitted widths and its standard error, nm).

    Raises
    ------
    BayespsfInputError
        ``molecules`` without one entry per ROI, no window that fits in the ROIs, or a
        window that is even or below ``MIN_ROI``.

    See Also
    --------
    mean_residuals : the residual images.
    bayespsf.fit_mle : the fit of each window.

    Notes
    -----
    A Gaussian spot gives the same width in every window within its error; a spot with
    heavier shoulders than a Gaussian gives a width that grows with the window (on a real
    bead image a user measured +6% from 7 x 7 to 15 x 15).
    """
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
