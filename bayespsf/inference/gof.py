"""Model criticism per ROI: can the model have made this image?

A parametric-bootstrap goodness-of-fit test, calibrated by simulation: the discrepancy of an
ROI is its negative log-likelihood at the maximum-likelihood fit, ``T(y) = -log p(y |
theta(y))``; ``replicates`` images are drawn from the camera law at ``theta(y)`` and fitted
again, and the p-value is ``(1 + #{T(y_rep) >= T(y)}) / (1 + replicates)`` (Davison &
Hinkley, Bootstrap Methods and their Application (1997), ch. 4). Refitting every replicate
makes the test account for the fit's own freedom, so on ROIs the model describes the p-values
are near uniform, and a flag at ``p <= alpha`` fires at rate ~alpha. ROIs the model cannot
explain (two molecules, an undeclared hot pixel, a spot that is not Gaussian) fit worse than
their replicates and get small p-values.

The replicates are drawn and refitted ``ROUND`` at a time, and a ROI's stop once ``stop_after``
(``STOP_AFTER``, 10) of them are at least as discrepant as it is: its p-value is then
``stop_after / l``, ``l`` the replicates up to and including the one that made ``stop_after``
(Besag & Clifford, Biometrika 78 (1991) 301, sequential Monte Carlo p-values). The p-value is
valid as the full test's is, ``P(p <= s) = s`` at each value ``s`` it can take where the
model holds, and it is the full test's wherever that is below ``stop_after / replicates``
(0.2 at 49): the flags at ``p <= 0.1`` are the same test. A ROI the model describes has
p-values spread over (0, 1) and stops early: on emccd-typical's ROIs (N = 1 000) 26 of the
49 replicates count on average (the round that stops a ROI is refitted whole). Above
``stop_after / replicates`` the p-value takes the values ``stop_after / l`` (10/49 ... 1),
not the lattice ``k / 50``.

The replicates are continuous counts from the camera law (``Camera.sample``); an ADC that
rounds to whole ADU adds 1/12 ADU^2 of variance that they lack, negligible beside a readout of
a few ADU. Each replicate is refitted from the ROI's fit until its Newton decrement is below
``REFIT_DECREMENT`` (1e-6, where ``fit_mle`` goes on to 1e-10): its ``T`` is then within half
of that of its maximum's (5.9e-7 at most over 9 800 emccd-typical replicates, whose ``T`` has
an SD of 9 about each ROI's), and the full test took 16% less time; the p-values of 512
emccd-typical ROIs were all the same as at 1e-10.

Two discrepancies are offered. The default, the negative log-likelihood, is the most
sensitive to a spot of the wrong shape, but its mean under the model depends on the fitted
parameters (through each pixel's entropy), and a plug-in bootstrap p-value is then
conservative (Robins, van der Vaart & Ventura, JASA 95 (2000)): with 2.75 background photons
per pixel it flagged 5-8% of the ROIs the model describes at p <= 0.1. Pearson's statistic
``sum (y - E y)^2 / var y`` at the fit has a mean near the number of pixels whatever the
parameters, and flagged 7-11% of the same ROIs, with a power alike on the misfits
(``validation/model_check.py``, 200 ROIs per case and N, compares both).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import stats

from bayespsf._runtime import refuse_beyond_memory
from bayespsf._validate import real_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.estimators import fit_mle, fit_screened
from bayespsf.inference.settings import check_settings
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

REPLICATE_STREAM = 0x6F66  # a ROI's replicates: its seed's stream of this number
REFIT_DECREMENT = 1e-6  # a replicate's refit has converged below this Newton decrement
STOP_AFTER = 10  # a ROI's replicates stop once this many are at least as discrepant as it
ROUND = 10  # replicates drawn and refitted at a time per ROI
CHUNK = 256  # ROIs whose replicates are drawn and refitted together (memory ~ CHUNK x replicates)
CHUNK_PIXELS = 2**26  # ... fewer where their replicates would pass this many pixels (512 MB)


DISCREPANCIES = ("likelihood", "pearson")


def check_discrepancy(name: str, value) -> str:
    """``value`` if it names one of ``DISCREPANCIES``, else an error naming ``name``."""
    if not (isinstance(value, str) and value in DISCREPANCIES):
        raise BayespsfInputError(f"{name} must be one of {', '.join(DISCREPANCIES)}; got {value!r}")
    return value


def check_option(check) -> str | bool:
    """``sample_many``'s ``check`` as False or the name of the discrepancy to test with.

    Parameters
    ----------
    check : bool or str
        True (the default discrepancy, ``"likelihood"``), False, or one of
        ``DISCREPANCIES``.

    Returns
    -------
    str or False
        The discrepancy's name, or False.

    Raises
    ------
    BayespsfInputError
        For anything else, naming ``check``.
    """
    if isinstance(check, bool | np.bool_):
        return "likelihood" if check else False
    return check_discrepancy("check (True, False or a discrepancy)", check)


def check_rows(stack, model: Model, seeds, discrepancy: str, fits=None) -> list[dict]:
    """The model check of each ROI as ``sample_many`` adds it to its rows.

    Parameters
    ----------
    stack : ndarray, shape (n, roi, roi)
        ROIs in ADU.
    model : Model
        The model to test.
    seeds : sequence of int
        Each ROI's seed: its replicates come from it alone.
    discrepancy : str
        One of ``DISCREPANCIES``.
    fits : pandas.DataFrame, optional
        ``fit_mle``'s table of the ROIs, if made.

    Returns
    -------
    list of dict
        Per ROI ``gof_p``, ``gof_discrepancy`` and ``gof_replicates`` (``bootstrap_check``).
    """
    table = bootstrap_check(
        stack, model, seed=[int(s) for s in seeds], fits=fits, discrepancy=discrepancy
    )
    return [
        {"gof_p": float(p), "gof_discrepancy": float(t), "gof_replicates": int(k)}
        for p, t, k in table[["gof_p", "gof_discrepancy", "gof_replicates"]].itertuples(index=False)
    ]


def describe_check(discrepancy: str) -> str:
    """The model check's procedure in words, as a store's manifest records it (a store made
    under another procedure is another run).

    Parameters
    ----------
    discrepancy : str
        One of ``DISCREPANCIES``.

    Returns
    -------
    str
        The test, its discrepancy where not the default, and its sequential stop.
    """
    check_discrepancy("discrepancy", discrepancy)
    named = "" if discrepancy == "likelihood" else f", discrepancy {discrepancy}"
    return (
        f"parametric bootstrap (bayespsf.inference.gof){named}, replicates stopped once "
        f"{STOP_AFTER} are as discrepant, {ROUND} at a time"
    )


def pearson(model: Model, counts: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Pearson's statistic of each ROI at ``theta`` (n, 6): ``sum (y - E y)^2 / var y`` over its
    pixels, with the camera law's mean (``offset + lam / photons_per_adu``) and variance. A
    pixel the model gives no variance (a photon counter where ``lam`` is 0) adds 0 where it
    matches its mean and infinity where it does not."""
    lam = model.expected(theta)
    per_adu, offset = model.camera.photons_per_adu()
    residual = counts - (offset + lam / per_adu)
    square, variance = np.broadcast_arrays(residual * residual, model.camera.variance(lam))
    terms = np.divide(square, variance, out=np.where(square > 0, np.inf, 0.0), where=variance > 0)
    return np.sum(terms, axis=(-2, -1))


FIT_KEYS = ("chi2", "chi2_dof", "chi2_p", "chi2_at")  # in every posterior's info and row


def pearson_fit(model: Model, counts: np.ndarray, theta: np.ndarray, at: str) -> list[dict]:
    """The cheap goodness-of-fit statistic every posterior carries: Pearson's chi-square of
    each ROI at ``theta``, its degrees of freedom and its chi-square p-value.

    Parameters
    ----------
    model : Model
        The model the posterior was made under.
    counts : ndarray, shape (n, roi, roi)
        The ROIs in ADU (validated).
    theta : ndarray, shape (n, 6)
        Where each ROI is judged: its maximum-likelihood fit, or its posterior mean.
    at : str
        Which (``"mle"`` or ``"posterior mean"``), recorded as ``chi2_at``.

    Returns
    -------
    list of dict
        Per ROI ``chi2`` (``pearson``: ``sum (y - E y)^2 / var y`` over the pixels, with the
        camera law's mean and variance), ``chi2_dof`` (pixels - 6), ``chi2_p`` (the
        chi-square law's upper tail at ``chi2``) and ``chi2_at``.

    Notes
    -----
    One pass over the pixels at one point, so it costs next to nothing beside the posterior;
    it changes no draw. Under the model, at the fit, Pearson's statistic has a mean near the
    degrees of freedom whatever the parameters, and ``chi2_p`` (the upper tail: a fit worse
    than the model allows) is near uniform where the statistic's spread is the chi-square's.
    Measured on 200 ROIs of 15 x 15 pixels and 1000 photons (fraction at ``chi2_p <= 0.1``):
    photon counting at 0.2, 2 and 20 background photons per pixel 0.105, 0.095, 0.080;
    ``emccd-typical`` (10 photons) 0.100 (``tests/inference/test_hostile_inputs.py``
    holds two of these within 4 SE). Its calibration limit is the per-pixel law's excess
    kurtosis, which widens the statistic's spread beyond the chi-square's: an EM register's is
    about ``6 / lam``, so on ``emccd-typical`` at 1 background photon per pixel 21% of 1000
    ROIs had ``chi2_p <= 0.1``; at such counts, read it as a ranking, and use the parametric
    bootstrap ``bootstrap_check`` (``sample_many(check="pearson")``, calibrated at any count,
    at ~50 refits per ROI). A scene quieter than the model's law (a sub-Poisson background)
    gives ``chi2_p`` near 1. A small ``chi2_p`` says the model does not describe the ROI (two
    molecules: two 1000-photon spots 400 nm apart had ``chi2_p <= 0.01`` in 40 of 40 ROIs
    whose posteriors converged; a hot pixel; a spot that is not the model's Gaussian), and the
    posterior, however narrow, is that of the wrong model.
    """
    columns = pearson_columns(model, pearson(model, counts, theta), at)
    return [
        {"chi2": float(t), "chi2_dof": columns["chi2_dof"], "chi2_p": float(p), "chi2_at": at}
        for t, p in zip(columns["chi2"], columns["chi2_p"], strict=True)
    ]


def pearson_columns(model: Model, chi2: np.ndarray, at: str) -> dict:
    """``pearson_fit``'s columns for a whole stack from Pearson's statistic per ROI.

    Parameters
    ----------
    model : Model
        Gives the ROI's pixels.
    chi2 : ndarray, shape (n,)
        Pearson's statistic per ROI (``pearson``, or the JAX backend's).
    at : str
        Where it was taken (``"mle"`` or ``"posterior mean"``).

    Returns
    -------
    dict
        ``chi2`` (n,), ``chi2_dof`` (int: pixels - 6), ``chi2_p`` (n,) and ``chi2_at``.
    """
    dof = model.roi * model.roi - len(PARAMETER_NAMES)
    return {"chi2": chi2, "chi2_dof": int(dof), "chi2_p": stats.chi2.sf(chi2, dof), "chi2_at": at}


def bootstrap_check(
    counts: ArrayLike,
    model: Model,
    *,
    replicates: int = 49,
    seed: int | Sequence[int] = 0,
    fits: pd.DataFrame | None = None,
    discrepancy: str = "likelihood",
    stop_after: int | None = STOP_AFTER,
) -> pd.DataFrame:
    """The parametric-bootstrap goodness-of-fit p-value of every ROI under ``model``.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU.
    model : Model
        The model to test (its camera law draws the replicates).
    replicates : int
        The most replicate images drawn and refitted per ROI (>= 1).
    seed : int or sequence of int
        One integer for the whole stack, or one per ROI (then ROI ``k``'s replicates depend
        on ``seed[k]`` alone, not on the stack it is checked in: ``sample_many`` checks each
        molecule so).
    fits : pandas.DataFrame, optional
        ``fit_mle``'s table of these ROIs, if already made.
    discrepancy : {"likelihood", "pearson"}
        ``"likelihood"`` (the MLE's negative log-likelihood) or ``"pearson"`` (``pearson`` at
        the fit; calibrated where the other is conservative, module docstring).
    stop_after : int or None, default 10
        A ROI's replicates stop once this many are at least as discrepant as it is (Besag &
        Clifford's sequential p-value, module docstring); None: every ROI's ``replicates``
        are refitted.

    Returns
    -------
    pandas.DataFrame
        One row per ROI: ``gof_p`` (NaN where the ROI's own fit, or every replicate's refit,
        did not converge), ``gof_discrepancy`` (``T(y)``) and ``gof_replicates`` (the
        replicates whose refit converged, which the p-value counts, up to the one that
        stopped them; a replicate that fails to converge is likely one of high ``T``, so many
        failures bias ``p`` up).

    Raises
    ------
    BayespsfInputError
        If ``replicates``, ``seed``, ``discrepancy`` or ``stop_after`` is invalid
        (``replicates`` so many that one ROI's cannot be held in memory, too), ``counts`` is
        not real of shape ``(n, roi, roi)``, or ``fits`` is not ``fit_mle``'s table of these
        ROIs.

    See Also
    --------
    fit_mle : the fit the test is made at.
    bayespsf.parallel.sample_many : runs this test per molecule with ``check=True``.

    Notes
    -----
    The test, its calibration, the sequential stop and the two discrepancies are described
    in the module docstring (Davison & Hinkley 1997; Besag & Clifford 1991; Robins, van der
    Vaart & Ventura 2000).
    """
    if (
        isinstance(replicates, bool)
        or not isinstance(replicates, numbers.Integral)
        or replicates < 1
    ):
        raise BayespsfInputError(f"replicates must be an integer >= 1, got {replicates!r}")
    replicates = int(replicates)
    refuse_beyond_memory(  # one ROI's replicates and their expected images, at least
        16.0 * replicates * model.roi**2,
        f"replicates = {replicates} of {model.roi} x {model.roi} ROIs",
        "use fewer replicates (49, the default, resolves p-values of 0.02)",
    )
    discrepancy = check_discrepancy("discrepancy", discrepancy)
    if stop_after is not None and (
        isinstance(stop_after, bool)
        or not isinstance(stop_after, numbers.Integral)
        or stop_after < 1
    ):
        raise BayespsfInputError(f"stop_after must be an integer >= 1 or None, got {stop_after!r}")
    stack = real_array("counts", counts)
    if stack.ndim != 3 or stack.shape[1:] != (model.roi, model.roi):
        raise BayespsfInputError(
            f"counts must have shape (n, {model.roi}, {model.roi}), got {stack.shape}"
        )
    if fits is None:
        fits = fit_mle(stack, model, laplace=False, crlb=False)
    missing = [c for c in (*PARAMETER_NAMES, "log_likelihood", "converged") if c not in fits]
    if missing or len(fits) != len(stack):
        raise BayespsfInputError(
            f"fits must be fit_mle's table of these {len(stack)} ROIs; got {len(fits)} rows"
            + (f" without {', '.join(missing)}" if missing else "")
        )
    theta = fits[list(PARAMETER_NAMES)].to_numpy(float)
    converged = fits["converged"].to_numpy(bool)

    def measure(images, fitted):
        """The discrepancy of each image at its fit: the fit's own negative log-likelihood,
        or Pearson's statistic (NaN where the fit did not converge)."""
        if discrepancy == "likelihood":
            return -fitted["log_likelihood"].to_numpy()
        thetas = fitted[list(PARAMETER_NAMES)].to_numpy(float)
        good = fitted["converged"].to_numpy(bool) & np.all(np.isfinite(thetas), axis=1)
        t = np.full(len(images), np.nan)
        t[good] = pearson(model, images[good], thetas[good])
        return t

    out = pd.DataFrame(
        {"gof_p": np.nan, "gof_discrepancy": measure(stack, fits), "gof_replicates": 0}
    )
    t = out["gof_discrepancy"].to_numpy()
    ok = np.flatnonzero(converged & np.isfinite(t))
    drawer = _Replicates(seed, len(stack), model)

    def replicate_round(rows, k):
        """``k`` more replicates of each of ``rows``, refitted from its fit: their
        discrepancies and whether each counts (its refit converged), ``(len(rows), k)``."""
        lam = np.repeat(model.expected(theta[rows]), k, axis=0)
        images = drawer.draw(rows, lam, k)
        refits = fit_screened(
            images,
            model,
            model.roi_problems(images),
            start=np.repeat(theta[rows], k, axis=0),
            laplace=False,
            crlb=False,
            decrement=REFIT_DECREMENT,
        )
        t_rep = measure(images, refits).reshape(-1, k)
        return t_rep, refits["converged"].to_numpy(bool).reshape(-1, k) & np.isfinite(t_rep)

    chunk = min(CHUNK, max(1, CHUNK_PIXELS // (min(ROUND, replicates) * model.roi**2)))
    for first in range(0, len(ok), chunk):
        rows = ok[first : first + chunk]
        p, counted = _sequential_p(rows, t[rows], replicates, stop_after, replicate_round)
        out.loc[rows, "gof_p"] = p
        out.loc[rows, "gof_replicates"] = counted
        drawer.forget(rows)
    return out


def _sequential_p(rows, t, replicates: int, stop_after, replicate_round):
    """The p-values and counted replicates of ``rows`` (m,), of discrepancy ``t`` (m,):
    ``replicate_round(rows, k)`` gives ``k`` more replicates' discrepancies and whether each
    counts, ``ROUND`` at a time up to ``replicates``; a ROI stops at the replicate that makes
    ``stop_after`` at least as discrepant (p = stop_after / counted), else p = (1 +
    exceeding) / (1 + counted) (NaN where none counts)."""
    exceed, counted = np.zeros(len(t), dtype=int), np.zeros(len(t), dtype=int)
    p = np.full(len(t), np.nan)
    active = np.arange(len(t))
    for done in range(0, replicates, ROUND):
        if not active.size:
            break
        k = min(ROUND, replicates - done)
        t_rep, counts = replicate_round(rows[active], k)
        hits = counts & (t_rep >= t[active, None])
        stops = np.zeros(len(active), dtype=bool)
        if stop_after is not None:
            reached = exceed[active, None] + np.cumsum(hits, axis=1) >= stop_after
            stops = reached.any(axis=1)
            at = reached.argmax(axis=1)
            length = counted[active] + np.cumsum(counts, axis=1)[np.arange(len(active)), at]
            p[active[stops]] = stop_after / length[stops]
            counted[active[stops]] = length[stops]
        going = active[~stops]
        exceed[going] += hits[~stops].sum(axis=1)
        counted[going] += counts[~stops].sum(axis=1)
        active = going
    p[active] = np.where(counted[active] > 0, (1 + exceed[active]) / (1 + counted[active]), np.nan)
    return p, counted


class _Replicates:
    """The replicates' draws: from one stream for the stack (an integer ``seed``), or from
    each ROI's own (``[seed[k], REPLICATE_STREAM]``), kept between its rounds."""

    def __init__(self, seed, n: int, model: Model):
        self.model = model
        self.streams: dict[int, np.random.Generator] = {}
        if np.ndim(seed) == 0:
            self.rng, self.seeds = np.random.default_rng(check_settings(seed=seed).seed), None
            return
        try:  # Python integers: molecule seeds reach 2**64
            self.seeds = [check_settings(seed=s).seed for s in seed]
        except BayespsfInputError as error:
            raise BayespsfInputError(f"{error} (seed: one per ROI)") from None
        if len(self.seeds) != n:
            raise BayespsfInputError(
                f"seed must be an integer or {n} integers >= 0 (one per ROI), got "
                f"{len(self.seeds)} values"
            )

    def draw(self, rows, lam, k: int) -> np.ndarray:
        """``k`` replicates of each of ``rows`` from their expected counts ``lam``
        (``len(rows) * k``, roi, roi)."""
        if self.seeds is None:
            return self.model.camera.sample(lam, self.rng)
        parts = lam.reshape(len(rows), k, *lam.shape[1:])
        return np.concatenate(
            [
                self.model.camera.sample(part, self._stream(r))
                for r, part in zip(rows, parts, strict=True)
            ]
        )

    def _stream(self, row: int) -> np.random.Generator:
        if row not in self.streams:
            self.streams[row] = np.random.default_rng([int(self.seeds[row]), REPLICATE_STREAM])
        return self.streams[row]

    def forget(self, rows) -> None:
        """Drop the streams of ``rows`` (their replicates are done)."""
        for r in rows:
            self.streams.pop(int(r), None)


def flag_excess_p(gof_p: pd.Series, alpha: float) -> float:
    """The dataset-level test of the per-frame goodness-of-fit flags: the binomial probability
    of at least as many frames with ``gof_p <= alpha`` as observed if each is flagged with
    probability ``alpha`` (the model holding in every frame). A misfit shared by every frame
    (an Airy spot fitted with a Gaussian), which the check across frames cannot see, shows
    here; NaN without p-values."""
    p = np.asarray(gof_p, dtype=np.float64)
    p = p[np.isfinite(p)]
    if not len(p):
        return np.nan
    return float(stats.binom.sf(int((p <= alpha).sum()) - 1, len(p), alpha))


__all__ = [
    "DISCREPANCIES",
    "FIT_KEYS",
    "bootstrap_check",
    "check_discrepancy",
    "check_option",
    "check_rows",
    "describe_check",
    "flag_excess_p",
    "pearson",
    "pearson_columns",
    "pearson_fit",
]
