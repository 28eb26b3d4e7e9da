"""A calibration check on real data, without ground truth.

An immobile molecule's true position and width are the same in every frame, so its per-frame
posteriors must agree with one another within their stated widths. Per molecule and
parameter, with posterior means ``m_k`` and SDs ``s_k`` over its K frames:

* the combined estimate is the inverse-variance weighted mean ``theta = sum w_k m_k / sum w_k``,
  ``w_k = 1 / s_k^2``, with standard error ``sigma = 1 / sqrt(sum w_k)``;
* each frame's z-score is ``(m_k - theta) / sqrt(s_k^2 - sigma^2)``: ``m_k - theta`` has that
  variance when ``m_k ~ N(true, s_k^2)``, since ``theta`` includes ``m_k``;
* ``chi2 = sum w_k (m_k - theta)^2`` follows chi-square with K - 1 degrees of freedom (its
  p-value is the molecule's verdict);
* a frame's 95% interval ``m_k +- 1.96 s_k`` covers ``theta`` with probability
  ``2 Phi(1.96 s_k / sqrt(s_k^2 - sigma^2)) - 1``, a little above 0.95; the expected and the
  observed fractions are reported side by side.

This holds where the posteriors are near normal and their means near unbiased across frames
(a common bias, as widths' at low N, cancels in ``m_k - theta``). A camera gain misdeclared
by 20% scales every stated SD by ~sqrt(1.2) against the true spread, and the z-scores' SD
moves away from 1 by as much; a PSF the model does not describe moves the widths with the
photon count.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

from bayespsf.errors import BayespsfInputError

PARAMETERS = ("x0", "y0", "s_x", "s_y")
Z95 = stats.norm.ppf(0.975)


def two_sided(chi2: float | np.ndarray, dof: float | np.ndarray) -> float | np.ndarray:
    """``2 min(P(X >= chi2), P(X <= chi2))`` for X ~ chi-square(dof), at most 1: small both
    when the frames scatter more than their SDs say (posteriors too narrow) and when they
    scatter less (too wide: a gain declared too high reads so)."""
    return np.minimum(1.0, 2 * np.minimum(stats.chi2.sf(chi2, dof), stats.chi2.cdf(chi2, dof)))


def frame_consistency(
    table: pd.DataFrame, parameters: Sequence[str] | str = PARAMETERS, by: str = "molecule"
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Whether each immobile molecule's per-frame posteriors agree within their stated widths.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per (molecule, frame) with ``by`` and ``{p}_mean``, ``{p}_sd`` for every
        ``p`` in ``parameters`` (posterior summaries, e.g. ``sample_many``'s rows); rows
        with a missing mean or SD are left out.
    parameters : sequence of str or str, default ``PARAMETERS``
        The parameters checked (``x0``, ``y0``, ``s_x``, ``s_y``: those an immobile
        molecule keeps from frame to frame).
    by : str, default "molecule"
        The column naming each row's molecule.

    Returns
    -------
    frames : DataFrame
        ``table``'s ``by`` and ``frame`` (if present), and per parameter ``{p}_z`` and
        ``{p}_covers`` (the frame's 95% interval holds the combined estimate).
    molecules : DataFrame
        Per molecule and parameter: ``frames``, ``combined`` and ``combined_se``, ``chi2``,
        ``dof``, ``p_value`` (large chi2: frames scatter more than stated), ``p_two_sided``
        (``two_sided``), ``z_sd``, ``coverage`` and ``expected_coverage``.
    overall : DataFrame
        Per parameter over all molecules: ``frames``, ``molecules``, ``z_sd`` with its
        standard error (``sqrt((kurtosis - 1) / (4 n))`` for the SD of n values, 1/sqrt(2n) for
        normal ones), total ``chi2``, ``dof``, ``p_value`` and ``p_two_sided``, ``coverage``
        with its binomial SE and ``expected_coverage``.

    Raises
    ------
    BayespsfInputError
        A table without the columns, or an SD that is 0, negative or infinite.

    See Also
    --------
    two_sided : the two-sided chi-square p-value.
    analyze : runs this check on every analysed movie.
    width_spread : the width's spread over frames against its predictions.

    Notes
    -----
    The module docstring gives the check: per molecule and parameter, the inverse-variance
    weighted mean of the frames' posterior means, each frame's z-score about it, the
    chi-square of the frames with K - 1 degrees of freedom, and the coverage of each frame's
    95% interval against its expected value. It holds where the posteriors are near normal
    and their means near unbiased across frames.

    Examples
    --------
    Four frames each of two molecules whose posterior means scatter by their stated SDs:

    >>> import pandas as pd
    >>> from bayespsf.analysis import frame_consistency
    >>> table = pd.DataFrame({
    ...     "molecule": [0, 0, 0, 0, 1, 1, 1, 1],
    ...     "x0_mean": [1.0, -1.0, 0.5, -0.5, 10.0, 12.0, 9.0, 11.0],
    ...     "x0_sd": [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
    ... })
    >>> frames, molecules, overall = frame_consistency(table, "x0")
    >>> molecules[["molecule", "frames", "combined", "chi2", "dof"]]
       molecule  frames  combined  chi2  dof
    0         0       4       0.0   2.5    3
    1         1       4      10.5   5.0    3
    """
    if isinstance(parameters, str):
        parameters = (parameters,)
    missing = [by] * (by not in table) + [
        f"{p}_{s}" for p in parameters for s in ("mean", "sd") if f"{p}_{s}" not in table
    ]
    if missing:
        raise BayespsfInputError(f"table: no column(s) {', '.join(missing)}")
    for p in parameters:
        sd = table[f"{p}_sd"].astype(float)
        bad = sd.notna() & ~((sd > 0) & np.isfinite(sd))
        if bad.any():
            raise BayespsfInputError(
                f"table: {int(bad.sum())} row(s) with {p}_sd not a finite number > 0 (first: "
                f"{sd[bad].iloc[0]!r}); a posterior SD is one (NaN marks a row without one)"
            )
    keep = [c for c in (by, "frame") if c in table]
    frames = table[keep].copy()
    molecule_rows, overall_rows = [], []
    for p in parameters:
        m, s = table[f"{p}_mean"].astype(float), table[f"{p}_sd"].astype(float)
        usable = m.notna() & s.notna() & (s > 0)
        w = 1.0 / s.where(usable) ** 2
        groups = table[by].where(usable)
        sum_w = w.groupby(groups).transform("sum")
        combined = (w * m).groupby(groups).transform("sum") / sum_w
        count = usable.groupby(groups).transform("sum")
        # a molecule of one frame has no spread about its own estimate: NaN, not sqrt(0 or -eps)
        spread = (s**2 - 1.0 / sum_w).where(usable & (count > 1))
        z = ((m - combined) / np.sqrt(spread)).where(usable & (count > 1))
        covers = ((m - combined).abs() <= Z95 * s).where(usable & (count > 1))
        expected = pd.Series(2 * stats.norm.cdf(Z95 * s / np.sqrt(spread)) - 1, index=s.index)
        frames[f"{p}_z"], frames[f"{p}_covers"] = z, covers
        per = pd.DataFrame(
            {
                by: table[by],
                "w": w,
                "chi": w * (m - combined) ** 2,
                "z": z,
                "covers": covers.astype(float),
                "expected": expected.where(covers.notna()),
                "combined": combined,
                "combined_se": 1 / np.sqrt(sum_w),
            }
        )[usable & (count > 1)]
        g = per.groupby(by)
        summary = pd.DataFrame(
            {
                "parameter": p,
                "frames": g.size(),
                "combined": g["combined"].first(),
                "combined_se": g["combined_se"].first(),
                "chi2": g["chi"].sum(),
                "z_sd": g["z"].std(ddof=1),
                "coverage": g["covers"].mean(),
                "expected_coverage": g["expected"].mean(),
            }
        ).reset_index()
        summary["dof"] = summary["frames"] - 1
        summary["p_value"] = stats.chi2.sf(summary["chi2"], summary["dof"])
        summary["p_two_sided"] = two_sided(summary["chi2"], summary["dof"])
        molecule_rows.append(summary)
        n = len(per)
        zs = per["z"].to_numpy()
        kurtosis = stats.kurtosis(zs, fisher=False) if n > 3 else 3.0
        coverage = per["covers"].mean()
        dof = int(summary["dof"].sum())
        overall_rows.append(
            {
                "parameter": p,
                "frames": n,
                "molecules": len(summary),
                "z_sd": zs.std(ddof=1) if n > 1 else np.nan,
                "z_sd_se": np.sqrt(max(kurtosis - 1.0, 0.0) / (4 * n)) if n else np.nan,
                "chi2": float(summary["chi2"].sum()),
                "dof": dof,
                "p_value": float(stats.chi2.sf(summary["chi2"].sum(), dof)) if dof else np.nan,
                "p_two_sided": float(two_sided(summary["chi2"].sum(), dof)) if dof else np.nan,
                "coverage": coverage,
                "coverage_se": np.sqrt(coverage * (1 - coverage) / n) if n else np.nan,
                "expected_coverage": per["expected"].mean(),
            }
        )
    molecules = pd.concat(molecule_rows, ignore_index=True)
    return frames, molecules, pd.DataFrame(overall_rows)


__all__ = ["PARAMETERS", "frame_consistency", "two_sided"]
