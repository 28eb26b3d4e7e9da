"""Posterior: the draws of one molecule's parameters, their summary, plots and result files.

The draws live in an ArviZ 1.x ``xarray.DataTree`` (group ``posterior``, dims
``(chain, draw)`` with one chain per emcee walker). Walkers are not independent chains, so
``r_hat`` over walkers is a heuristic; the sampler's own convergence test uses emcee's
integrated autocorrelation time, reported here as ``tau`` (in steps, before thinning).

A result file (NetCDF, ``Posterior.save``) holds the draws, the observed counts (group
``observed_data``) and, as attributes, the sampler settings, tau, the camera, the scene (TOML)
and the truth when known: it is self-describing and opens in plain ArviZ or xarray.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import xarray as xr
from numpy.typing import ArrayLike

from bayespsf._validate import probability, real_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.result_file import (
    JSON_ATTRIBUTES,
    json_attribute,
    molecule_attributes,
    open_result_file,
    result_attributes,
)
from bayespsf.psf import PARAMETER_NAMES

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bayespsf.model import Model
    from bayespsf.scene import Scene


class Posterior:
    """Draws of ``x0 y0 s_x s_y N b`` (nm, photons) with what produced them.

    Parameters
    ----------
    tree : xarray.DataTree
        An ArviZ tree: group ``posterior`` with one variable per parameter, dims
        ``(chain, draw)``; optional group ``observed_data`` (``counts``) and the attributes
        ``from_draws`` writes (JSON: ``tau``, ``sampler``, ``camera``, ``geometry``,
        ``truth``; ``photon_unit``; ``scene`` as TOML).

    Attributes
    ----------
    tree : xarray.DataTree
        The draws and what made them, as written to and read from a result file.

    See Also
    --------
    sample_posterior : makes one for a ROI.
    Posterior.from_draws : one from an array of draws.
    Posterior.load : one from a result file.

    Notes
    -----
    See the module docstring: walkers are the chains, so ``r_hat`` over them is a heuristic;
    ``tau`` is emcee's integrated autocorrelation time.
    """

    def __init__(self, tree: xr.DataTree):
        self.tree = tree

    @classmethod
    def from_draws(
        cls,
        draws: ArrayLike,
        tau: ArrayLike | None = None,
        info: dict | None = None,
        counts: ArrayLike | None = None,
        model: Model | None = None,
        truth: ArrayLike | None = None,
        scene: Scene | None = None,
    ) -> Posterior:
        """A posterior from draws in the parameter order.

        Parameters
        ----------
        draws : array_like, shape (chains, draws, 6)
            ``x0 y0 s_x s_y`` (nm), ``N`` (photons), ``b`` (photons per pixel).
        tau : array_like, shape (6,), optional
            Integrated autocorrelation time per parameter, in steps.
        info : dict, optional
            Sampler settings and run facts (JSON-serialisable), ``Posterior.info``.
        counts : array_like, shape (roi, roi), optional
            The observed ROI in ADU (group ``observed_data``).
        model : Model, optional
            Its camera, geometry and photon unit are recorded.
        truth : array_like, shape (6,), optional
            True parameters, for plots and calibration.
        scene : Scene, optional
            Recorded as TOML.

        Returns
        -------
        Posterior
        """
        import arviz as az  # imported on use: it takes a second and most commands never need it

        draws = np.asarray(draws, dtype=np.float64)
        data = {name: draws[..., k] for k, name in enumerate(PARAMETER_NAMES)}
        groups = {"posterior": data}
        dims = None
        if counts is not None:
            groups["observed_data"] = {"counts": np.asarray(counts)}
            dims = {"counts": ["row", "column"]}
        with warnings.catch_warnings():
            # arviz guesses that more chains than draws means misnamed dims; ours are named (a
            # short run of many walkers has more chains than draws)
            warnings.filterwarnings("ignore", "Found chain dimension to be longer", UserWarning)
            tree = az.from_dict(groups, dims=dims)
        attrs = result_attributes(model, scene) | molecule_attributes(tau, info, truth)
        tree.attrs.update(attrs)
        return cls(tree)

    # ------------------------------------------------------------------------------ reading

    def _attr(self, key):
        return json_attribute(self.tree.attrs, key, "the posterior")

    @property
    def info(self) -> dict:
        """Sampler settings and run facts (steps, burn, thin, converged, acceptance)."""
        return self._attr("sampler") or {}

    @property
    def method(self) -> str:
        """What made the draws: ``"laplace"``, ``"importance"`` or ``"mcmc"``.

        ``info["method"]``; for files whose ``info`` has no ``method``, ``"importance"``
        where it has ``khat``, else ``"mcmc"``.
        """
        info = self.info
        if info.get("method") in ("laplace", "importance", "mcmc"):
            return info["method"]
        return "importance" if "khat" in info else "mcmc"

    @property
    def converged(self) -> bool:
        """Whether the run met its targets (``info["converged"]``; False if unrecorded)."""
        return bool(self.info.get("converged", False))

    @property
    def tau(self) -> pd.Series:
        """emcee's integrated autocorrelation time per parameter, in steps."""
        return pd.Series(self._attr("tau"), name="tau")

    @property
    def truth(self) -> pd.Series | None:
        """The true ``x0 y0 s_x s_y N b`` when known (simulations), else None."""
        t = self._attr("truth")
        return None if t is None else pd.Series(t, name="truth")

    def draws(self) -> pd.DataFrame:
        """All draws, chains concatenated.

        Returns
        -------
        pandas.DataFrame
            One row per draw, columns ``x0 y0 s_x s_y`` (nm), ``N`` (photons), ``b``
            (photons per pixel).
        """
        post = self.tree["posterior"]
        return pd.DataFrame({n: post[n].values.ravel() for n in PARAMETER_NAMES})

    def summary(self) -> pd.DataFrame:
        """The posterior's summary per parameter (ArviZ ``summary``).

        Returns
        -------
        pandas.DataFrame
            Indexed by parameter (``x0 y0 s_x s_y N b``), with columns ``mean``, ``sd``,
            ``hdi68_lb``, ``hdi68_ub``, ``hdi95_lb``, ``hdi95_ub`` (the 68% and 95% highest
            density intervals), ``ess_bulk``, ``ess_tail``, ``r_hat`` (over walkers: a
            heuristic), ``mcse_mean`` (Monte Carlo standard error of the mean) and, where
            recorded, ``tau`` (in steps).

        See Also
        --------
        Posterior.interval : central or HDI intervals of any probability.
        arviz_stats.summary : the summary this one is made from.

        Examples
        --------
        >>> import bayespsf
        >>> scene = bayespsf.load_scene("paper-fig3")
        >>> counts, truth = bayespsf.simulate(scene, 1, seed=1)
        >>> model = bayespsf.Model.from_scene(scene)
        >>> post = bayespsf.sample_posterior(counts[0], model, seed=1, method="laplace")
        >>> table = post.summary()
        >>> list(table.columns)  # doctest: +NORMALIZE_WHITESPACE
        ['mean', 'sd', 'hdi68_lb', 'hdi68_ub', 'hdi95_lb', 'hdi95_ub', 'ess_bulk',
         'ess_tail', 'r_hat', 'mcse_mean', 'tau']
        >>> bool((table["hdi95_lb"] <= table["mean"]).all())
        True
        """
        import arviz as az

        s68 = az.summary(self.tree, ci_kind="hdi", ci_prob=0.68, round_to="none")
        s95 = az.summary(self.tree, ci_kind="hdi", ci_prob=0.95, round_to="none")
        out = s68[["mean", "sd", "hdi68_lb", "hdi68_ub"]].join(
            s95[["hdi95_lb", "hdi95_ub", "ess_bulk", "ess_tail", "r_hat", "mcse_mean"]]
        )
        tau = self._attr("tau")
        if tau is not None:
            out["tau"] = pd.Series(tau)
        return out.loc[list(PARAMETER_NAMES)]

    def sd(self) -> pd.Series:
        """Posterior SD of each parameter.

        Returns
        -------
        pandas.Series
            Indexed by parameter, in its unit (nm, photons, photons per pixel).
        """
        return self.draws().std(ddof=1)

    def interval(self, prob: float = 0.68, kind: str = "central") -> pd.DataFrame:
        """Per parameter, the ``prob`` credible interval.

        Parameters
        ----------
        prob : float
            Probability inside the interval, in (0, 1).
        kind : {"central", "hdi"}
            Equal tails, or the highest density interval (ArviZ).

        Returns
        -------
        pandas.DataFrame
            Indexed by parameter, columns ``lower`` and ``upper``.

        Raises
        ------
        BayespsfInputError
            If ``prob`` is not a probability.
        ValueError
            If ``kind`` is neither.
        """
        prob = probability("prob", prob)
        d = self.draws()
        if kind == "central":
            q = d.quantile([(1 - prob) / 2, (1 + prob) / 2]).T
            q.columns = ["lower", "upper"]
            return q
        if kind == "hdi":
            import arviz as az

            s = az.summary(self.tree, ci_kind="hdi", ci_prob=prob, round_to="none")
            cols = [c for c in s.columns if c.startswith("hdi")]
            return s[cols].set_axis(["lower", "upper"], axis=1).loc[list(PARAMETER_NAMES)]
        raise ValueError(f"kind must be 'central' or 'hdi', got {kind!r}")

    # -------------------------------------------------------------------------------- plots

    def corner(self, truths: ArrayLike | None = None) -> Figure:
        """Corner plot (corner.py) with 16/50/84% quantiles.

        Parameters
        ----------
        truths : array_like, shape (6,), optional
            Values to mark; default the run's truth if known.

        Returns
        -------
        matplotlib.figure.Figure
        """
        import corner

        truths = self.truth if truths is None else pd.Series(truths, index=list(PARAMETER_NAMES))
        return corner.corner(
            self.draws().to_numpy(),
            labels=[r"$x_0$ (nm)", r"$y_0$ (nm)", r"$s_x$ (nm)", r"$s_y$ (nm)", "N", "b"],
            truths=None if truths is None else truths.to_numpy(),
            quantiles=[0.16, 0.5, 0.84],
            show_titles=True,
        )

    def trace(self) -> Figure:
        """Trace and marginal density of every parameter, all walkers.

        Returns
        -------
        matplotlib.figure.Figure
            ArviZ ``plot_trace_dist``'s figure.
        """
        import arviz as az

        collection = az.plot_trace_dist(self.tree, compact=True, backend="matplotlib")
        return collection.viz["figure"].values.item()

    # -------------------------------------------------------------------------------- files

    def save(self, path: str | os.PathLike) -> Path:
        """Write the self-describing NetCDF result file.

        Parameters
        ----------
        path : str or path-like
            The file (NetCDF4, ``.nc``); its folder is made if missing.

        Returns
        -------
        pathlib.Path
            ``path``.

        See Also
        --------
        Posterior.load : reads it back.
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.tree.to_netcdf(path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Posterior:
        """Read a result file written by ``save``.

        Parameters
        ----------
        path : str or path-like
            A result file (NetCDF4).

        Returns
        -------
        Posterior

        Raises
        ------
        BayespsfInputError
            For a missing, empty, truncated or damaged file, a directory, a NetCDF3 file, or
            a NetCDF without the six parameters' draws (real numbers, dims ``(chain,
            draw)``, at least one draw) in a ``posterior`` group, naming the file and what it
            is not; a named pipe, socket or device (refused before it is opened); or one of
            the attributes in ``JSON_ATTRIBUTES`` that is not a JSON table (damaged after it
            was written), naming the file and the attribute; a file of a ``sample_many``
            store, naming ``Store.posterior``, which reads its molecules.
        """
        path = Path(path)
        tree = open_result_file(path)
        if "molecules" in tree.children:
            raise BayespsfInputError(
                f"{path}: a file of a sample_many store, which holds many molecules; read one "
                f"with bayespsf.parallel.Store({str(path.parent)!r}).posterior(index)"
            )
        missing = _missing_draws(tree)
        if missing:
            raise BayespsfInputError(
                f"{path}: not a bayespsf result file: {missing} (a result file holds the draws "
                f"of {', '.join(PARAMETER_NAMES)} with dims (chain, draw) in its 'posterior' "
                "group)"
            )
        for key in JSON_ATTRIBUTES:  # now, not as a JSON traceback in info or summary()
            json_attribute(tree.attrs, key, str(path))
        return cls(tree)


def _missing_draws(tree) -> str:
    """What a tree lacks of a posterior's draws ('' if nothing): the ``posterior`` group, one
    of the six parameters, dims ``(chain, draw)``, at least one draw, real-number values."""
    if "posterior" not in tree.children:
        return "it has no 'posterior' group"
    post = tree["posterior"]
    absent = [name for name in PARAMETER_NAMES if name not in post.data_vars]
    if absent:
        return f"its posterior group has no {', '.join(absent)}"
    odd = [n for n in PARAMETER_NAMES if tuple(post[n].dims) != ("chain", "draw")]
    if odd:
        return f"{', '.join(odd)} do not have dims (chain, draw)"
    empty = [n for n in PARAMETER_NAMES if post[n].size == 0]
    if empty:
        return f"{', '.join(empty)} have no draws (shape {post[empty[0]].shape})"
    for name in PARAMETER_NAMES:
        try:
            real_array(f"the draws of {name}", post[name].values)
        except BayespsfInputError as exc:
            return str(exc)
    return ""
