"""The paper's experimental width precision per molecule (issue 14, item 2).

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

from bayespsf._checks import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.theory import delta_s_analytic

ESTIMATORS = {"lsq": "least squares", "mle": "MLE", "mean": "posterior mean"}


def width_spread(
    frames: pd.DataFrame, pixel_size: float, *, width: str = "s_x", by: str = "molecule",
    photons: str = "N_mean", background: str = "b_mean", background_variance=None,
) -> pd.DataFrame:  # fmt: skip
    """Per molecule: ``frames``, mean ``N`` and ``b``, ``delta_s_<estimator>`` (the SD over
    frames, ``ddof=1``, of each ``{width}_<estimator>`` column present: ``lsq``, ``mle``,
    ``mean``) with its standard error (``delta / sqrt(2 (K - 1))`` for normal estimates; NaN
    for a molecule of one frame),
    ``posterior_sd`` (the mean of ``{width}_sd``, if present), ``crlb`` (the mean of
    ``crlb_{width}``, if present) and ``eq_sigma2dp3``.

    ``background_variance``: the background photons' variance per pixel (a number, or a column
    name); default the mean background (Poisson photons).
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
        out["N"], g[f"{width}_mean"].mean(), g[f"{other}_mean"].mean(), pixel_size,
        np.sqrt(variance), out["b"],
    )  # fmt: skip
    return out.reset_index()


__all__ = ["ESTIMATORS", "width_spread"]
