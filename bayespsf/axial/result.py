"""``ZPosterior``: the draws of an emitter's axial posterior (``z_posterior``) and the
regions read from them."""

from __future__ import annotations

from dataclasses import dataclass, field

import arviz_stats
import numpy as np
import pandas as pd

from bayespsf._validate import probability, scalar_in_range


@dataclass
class ZPosterior:
    """Equally weighted draws of ``(x0, y0, z, N, b)`` and how they were made.

    Parameters
    ----------
    draws : pandas.DataFrame
        One row per draw, columns ``x0``, ``y0``, ``z`` (nm), ``N`` (photons), ``b``
        (photons per pixel).
    info : dict
        How they were made (``z_posterior``'s Returns lists the keys).
    grid : pandas.DataFrame, optional
        ``z`` (nm) on the coarse grid and its Laplace ``log_marginal`` (unnormalised).

    See Also
    --------
    z_posterior : makes one.
    distance_from_focus : the unified interval of ``|z - c|`` on a symmetric curve.
    """

    draws: pd.DataFrame
    info: dict = field(default_factory=dict)
    grid: pd.DataFrame | None = None  # z and its Laplace log marginal (unnormalised)

    def summary(self) -> pd.DataFrame:
        """Mean, SD and the 2.5/16/50/84/97.5% quantiles of every parameter.

        Returns
        -------
        pandas.DataFrame
            One row per column of ``draws``.
        """
        q = self.draws.quantile([0.025, 0.16, 0.5, 0.84, 0.975]).T
        q.columns = ["q2.5", "q16", "median", "q84", "q97.5"]
        return pd.concat(
            [self.draws.mean().rename("mean"), self.draws.std().rename("sd"), q], axis=1
        )

    def hdi(self, prob: float = 0.95) -> pd.DataFrame:
        """The highest-density region of z holding ``prob`` of its posterior: one row per
        interval (``lower``, ``upper``, nm, as ``Posterior.interval`` names them), from a
        kernel density estimate of the draws (``arviz_stats.hdi``, ``method="multimodal"``),
        so that two modes give two intervals.

        Where the curves are even about a plane (``info["plane"]``) the posterior is exactly
        symmetric about it, so the draws are taken with their mirror images: the region is then
        symmetric too, and where the density peaks at the plane (in focus on the paper's
        symmetric curve) it is one interval across it. A region of |z - plane| read from the
        shortest interval of folded draws would start at the smallest draw, never at the plane
        itself, and so never cover an emitter exactly in focus.

        Parameters
        ----------
        prob : float, optional
            The probability the region holds, in (0, 1).

        Returns
        -------
        pandas.DataFrame
            Columns ``lower`` and ``upper``, one row per interval.
        """
        prob = probability("prob", prob)
        z = self.draws["z"].to_numpy(dtype=np.float64)
        if "plane" in self.info:
            z = np.concatenate([z, 2.0 * self.info["plane"] - z])
        if np.ptp(z) == 0:
            return pd.DataFrame({"lower": [z[0]], "upper": [z[0]]})
        region = np.atleast_2d(np.asarray(arviz_stats.hdi(z, prob=prob, method="multimodal")))
        region = region[np.all(np.isfinite(region), axis=1)]
        return pd.DataFrame(region[np.argsort(region[:, 0])], columns=["lower", "upper"])

    def covers(self, z: float, prob: float = 0.95) -> bool:
        """Whether ``z`` (nm) lies in the ``prob`` highest-density region (``hdi``).

        Parameters
        ----------
        z : float
            An axial position in nm.
        prob : float, optional
            As ``hdi``.

        Returns
        -------
        bool
        """
        region = self.hdi(prob)
        z = scalar_in_range("z", z, -np.inf)
        return bool(np.any((region["lower"] <= z) & (z <= region["upper"])))
