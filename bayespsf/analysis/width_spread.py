"""The paper's experimental width precision per molecule.

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), Fig. 2's experimental points: for each
immobile molecule, the spread of its per-frame width estimates across its valid frames,
``Delta s_rms``, against its mean photon count N. ``width_spread`` gives it for every
estimator a table carries (least squares as the paper, MLE, the posterior mean), beside what
should predict it: the mean posterior SD, the mean Cramér–Rao bound, and Eq. sigma2dp3 at the
molecule's mean N, background and widths.

Eq. sigma2dp3 needs the background's photon variance ``sigma_b^2`` beside its mean ``<b>``;
for Poisson background photons ``sigma_b^2 = <b>`` (the default), and a measured value can be
given. It is stated in detected photons, so the table's N and b must be detected
photoelectrons (``photon_unit``), which the function checks where the column exists.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from bayespsf._validate import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.theory import delta_s_analytic

ESTIMATORS = {"lsq": "least squares", "mle": "MLE", "mean": "posterior mean"}


def width_spread(
    frames: pd.DataFrame,
    pixel_size: float,
    *,
    width: str = "s_x",
    by: str = "molecule",
    photons: str = "N_mean",
    background: str = "b_mean",
    background_variance: float | str | None = None,
) -> pd.DataFrame:
    """Per molecule, the spread of its width estimates over frames beside its predictions.

    Parameters
    ----------
    frames : pandas.DataFrame
        One row per (molecule, frame): ``by``, ``photons``, ``background``, ``s_x_mean``,
        ``s_y_mean`` and, where present, ``{width}_lsq``, ``{width}_mle``, ``{width}_sd`` and
        ``crlb_{width}`` (nm); N and b in detected photoelectrons (``photon_unit``, checked
        where the column exists).
    pixel_size : float
        Pixel side in nm (> 0).
    width : {"s_x", "s_y"}, default "s_x"
        The width whose spread is measured.
    by : str, default "molecule"
        The column naming each row's molecule.
    photons : str, default "N_mean"
        The column of each frame's photon count N.
    background : str, default "b_mean"
        The column of each frame's background b, photons per pixel.
    background_variance : float or str, optional
        The background photons' variance per pixel (a number, or a column name); default the
        mean background (Poisson photons).

    Returns
    -------
    pandas.DataFrame
        One row per molecule: ``by``, ``frames``, mean ``N`` and ``b``,
        ``delta_s_<estimator>`` (the SD over frames, ``ddof=1``, of each
        ``{width}_<estimator>`` column present: ``lsq``, ``mle``, ``mean``, nm) with its
        standard error ``delta_s_<estimator>_se`` (``delta / sqrt(2 (K - 1))`` for normal
        estimates; NaN for a molecule of one frame), ``posterior_sd`` (the mean of
        ``{width}_sd``, if present), ``crlb`` (the mean of ``crlb_{width}``, if present) and
        ``eq_sigma2dp3`` (nm).

    Raises
    ------
    BayespsfInputError
        A ``pixel_size`` that is not > 0, an unknown ``width``, missing columns, or N and b
        in a unit other than detected photoelectrons.

    See Also
    --------
    bayespsf.theory.delta_s_analytic : Eq. sigma2dp3.
    frame_consistency : whether the frames agree within their stated SDs.
    analyze : writes this table as ``width_spread.csv``.

    Notes
    -----
    The paper's Fig. 2, experimental points (module docstring): ``Delta s_rms`` of each
    immobile molecule over its valid frames against its mean N, for every estimator, beside
    the mean posterior SD, the mean Cramér–Rao bound and Eq. sigma2dp3 at the molecule's mean
    N, background and widths. Eq. sigma2dp3 is stated in detected photons.
    """
    pixel_size = scalar_in_range("pixel_size", pixel_size, 0.0, low_inclusive=False)
    if width not in ("s_x", "s_y"):
        raise BayespsfInputError(f"width must be 's_x' or 's_y', got {width!r}")
    other = "s_y" if width == "s_x" else "s_x"
    needed = [by, photons, background, f"{width}_mean", f"{other}_mean"]
    missing = [c for c in needed if c not in frames]
    if missing:
        raise BayespsfInputError(f"frames: no column(s) {', '.join(missing)}")
    present = [e for e in ESTIMATORS if f"{width}_{e}" in frames]  # "mean" at least
    if "photon_unit" in frames and set(frames["photon_unit"].dropna()) - {"photoelectrons"}:
        raise BayespsfInputError(
            "frames: Eq. sigma2dp3 is stated in detected photons, but N and b are in "
            f"{', '.join(sorted(set(frames['photon_unit'])))} (use photon_unit = 'detected')"
        )
    g = frames.groupby(by)
    out = pd.DataFrame({"frames": g.size(), "N": g[photons].mean(), "b": g[background].mean()})
    for e in present:
        delta = g[f"{width}_{e}"].std(ddof=1)
        out[f"delta_s_{e}"] = delta
        out[f"delta_s_{e}_se"] = delta / np.sqrt(2 * (out["frames"] - 1))
    if f"{width}_sd" in frames:
        out["posterior_sd"] = g[f"{width}_sd"].mean()
    if f"crlb_{width}" in frames:
        out["crlb"] = g[f"crlb_{width}"].mean()
    if background_variance is None:
        variance = out["b"]
    elif isinstance(background_variance, str):
        variance = g[background_variance].mean()
    else:
        variance = pd.Series(float(background_variance), index=out.index)
    out["eq_sigma2dp3"] = delta_s_analytic(
        out["N"],
        g[f"{width}_mean"].mean(),
        g[f"{other}_mean"].mean(),
        pixel_size,
        np.sqrt(variance),
        out["b"],
    )
    return out.reset_index()


__all__ = ["ESTIMATORS", "width_spread"]
