"""A confidence interval of the distance from focus on a curve even about a plane, with its
coverage at every fixed z, the focus included: calibrated near focus.

Where both axes' widths are even about a plane ``c`` (the paper's symmetric defocus,
DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), Discussion), the image tells only the
distance ``t = |z - c|``, and t = 0 is the edge of its range. There no credible interval can
promise its nominal coverage at every fixed t: near the edge, z's posterior (uniform prior)
over-covers at some t and under-covers at others (``validation/axial.py``; in the Gaussian
limit, where z^2's estimate is a Gaussian mean bounded at 0 (Mandelkern, Statist. Sci. 17
(2002)), by quadrature in ``validation/axial_edge.py``). The
unified interval of Feldman & Cousins, Phys. Rev. D 57, 3873 (1998) is built to have it: a
Neyman belt ordered by the likelihood ratio to the best allowed value, which turns from an
upper limit into a two-sided interval as the data move away from the edge, with no choice
made after seeing them.

It is applied to ``tau = t^2``, in which the curves are linear when their quartic term is
zero (``B = 0``): per axis ``w^2 = w0^2 (1 + tau / d^2)`` (Huang curve) or
``w = w0 (1 + tau / d^2)`` (polynomial). The maximum-likelihood widths ``(s_x, s_y)`` with
their covariance ``S`` give ``tau``'s generalised least-squares estimate, Gaussian with the
SD ``sigma`` that ``S`` implies (first order in the widths' errors); the belt of a Gaussian
mean bounded at 0 in units of ``sigma`` (``bounded_mean_interval``) then gives tau's
interval, and its square root t's. Away from focus it is the first-order interval of tau.
"""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.special import ndtr, ndtri

from bayespsf._validate import finite_array, probability
from bayespsf.axial.push import symmetry_plane, widths
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus, PolynomialCurve

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

BELT_POINTS = 4000  # means on the belt's grid, geometric from 1e-6 to 1, then linear
BISECTIONS = 80


@lru_cache(maxsize=8)
def _belt(prob: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The acceptance intervals ``[x1, x2]`` of the unit Gaussian with mean ``mu >= 0`` on a
    grid of ``mu`` (Feldman & Cousins 1998, Sec. IV.B): the x with the largest likelihood
    ratio ``R = phi(x - mu) / phi(x - max(0, x))`` until they hold ``prob``. With ``h`` the
    half-width on the side x >= 0, ``R >= exp(-h^2 / 2)`` is ``x2 = mu + h`` and
    ``x1 = mu - h`` (h <= mu) or ``(mu^2 - h^2) / (2 mu)`` (h > mu, where R = exp(x mu -
    mu^2 / 2) for x < 0). From ``mu = c = ndtri((1 + prob) / 2)`` on, the belt is the central
    interval ``mu +- c``."""
    c = float(ndtri(0.5 * (1.0 + prob)))
    mu = np.concatenate(
        [
            np.geomspace(1e-6, 1.0, BELT_POINTS // 2, endpoint=False),
            np.linspace(1.0, c + 1.0, BELT_POINTS // 2),
        ]
    )
    lo, hi = np.zeros_like(mu), np.full_like(mu, c + 10.0)

    def lower_edge(h):
        return np.where(h <= mu, mu - h, (mu * mu - h * h) / (2.0 * mu))

    for _ in range(BISECTIONS):  # the held probability grows with h
        h = 0.5 * (lo + hi)
        held = ndtr(h) - ndtr(lower_edge(h) - mu)
        lo, hi = np.where(held < prob, h, lo), np.where(held < prob, hi, h)
    h = 0.5 * (lo + hi)
    return mu, lower_edge(h), mu + h, c


def bounded_mean_interval(x: ArrayLike, prob: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Feldman & Cousins' unified interval for the mean ``mu >= 0`` of a unit Gaussian.

    Parameters
    ----------
    x : array_like
        Observations, each of a unit Gaussian of mean ``mu >= 0``; finite.
    prob : float, default 0.95
        The interval's coverage, in (0, 1).

    Returns
    -------
    lower, upper : numpy.ndarray
        The interval of ``mu`` from each ``x`` (``x``'s shape): the ``mu`` whose acceptance
        interval holds ``x``. At ``x = 0`` it is ``[0, ndtri((1 + prob) / 2)]``.

    Raises
    ------
    BayespsfInputError
        An ``x`` that is not finite or a ``prob`` outside (0, 1).

    See Also
    --------
    distance_from_focus : applies it to the distance from focus.

    Notes
    -----
    Its coverage is ``prob`` at every ``mu``, 0 included (by construction; the tests check it
    by simulation). The acceptance intervals are the belt of Feldman & Cousins (1998), Sec.
    IV.B, ordered by the likelihood ratio to the best allowed mean; the interval turns from an
    upper limit into the central interval ``x +- ndtri((1 + prob) / 2)`` as ``x`` grows.

    References
    ----------
    .. [1] G. J. Feldman and R. D. Cousins, Phys. Rev. D 57, 3873 (1998).

    Examples
    --------
    >>> from bayespsf.axial import bounded_mean_interval
    >>> lower, upper = bounded_mean_interval([0.0, 1.0, 5.0])
    >>> lower.round(2).tolist(), upper.round(2).tolist()
    ([0.0, 0.0, 3.04], [1.96, 2.96, 6.96])
    """
    x = finite_array("x", x)
    prob = probability("prob", prob)
    mu, x1, x2, c = _belt(prob)
    lower = np.where(x <= x2[0], 0.0, np.interp(x, x2, mu))
    lower = np.where(x > x2[-1], x - c, lower)
    upper = np.where(x >= x1[-1], x + c, np.interp(x, x1, mu, left=mu[0]))
    return lower, upper


def _linear_axes(defocus: Defocus, plane: float):
    """Per axis: the transform ``f`` of the width that is linear in ``tau``, its derivative,
    ``f(w0)`` and the slope ``f(w0) / d^2``; or a named error for a curve with a quartic
    term."""
    axes = []
    for name, curve in (("x", defocus.x), ("y", defocus.y)):
        if curve.B != 0.0:
            raise BayespsfInputError(
                f"the unified interval needs curves without a quartic term; the {name} curve "
                f"has B = {curve.B:g} (its widths are then not linear in (z - {plane:g})^2)"
            )
        if isinstance(curve, PolynomialCurve):
            axes.append((lambda s: s, lambda s: np.ones_like(s), curve.w0, curve.w0 / curve.d**2))
        else:
            axes.append((np.square, lambda s: 2.0 * s, curve.w0**2, curve.w0**2 / curve.d**2))
    return axes


def distance_from_focus(
    defocus: Defocus,
    s_x: ArrayLike,
    s_y: ArrayLike,
    covariance: ArrayLike,
    prob: float = 0.95,
) -> pd.DataFrame:
    """Per ROI, the unified interval of the distance ``|z - c|`` from the plane of focus.

    Parameters
    ----------
    defocus : Defocus
        Curves even about a plane ``c`` (both axes in focus at ``c``, no odd term ``A``; the
        paper's ``Defocus.symmetric``) without a quartic term (``B = 0``).
    s_x, s_y : array_like, shape (n,)
        The maximum-likelihood widths of each ROI, nm.
    covariance : array_like, shape (2, 2) or (n, 2, 2)
        Their covariance, nm², e.g. the Laplace covariance of
        ``bayespsf.inference.estimators.covariance``; finite and positive definite.
    prob : float, default 0.95
        The interval's coverage, in (0, 1).

    Returns
    -------
    pandas.DataFrame
        One row per ROI: ``lower`` and ``upper`` (nm), the estimate ``tau_hat`` of
        ``(z - c)^2`` (nm², negative where the spot is narrower than in focus) and its SD
        ``tau_sd``, and the ``plane`` c (nm). The emitter's z is in ``[c - upper, c - lower]``
        or ``[c + lower, c + upper]``.

    Raises
    ------
    BayespsfInputError
        Curves not even about a plane (they tell z's sign: use ``z_posterior``), a curve with
        a quartic term, widths that are not finite and > 0, or a covariance of the wrong
        shape, not finite or not positive definite.

    See Also
    --------
    bounded_mean_interval : the belt the interval is read from.
    z_posterior : z's posterior, for curves that tell its sign.
    ZPosterior.hdi : the posterior's highest-density region.

    Notes
    -----
    The interval of ``tau = (z - c)^2``, in which the curves are linear: the generalised
    least-squares estimate of tau from the widths, Gaussian with the SD ``tau_sd`` that the
    covariance implies (first order in the widths' errors), in units of its SD, gives the
    unified interval of a Gaussian mean bounded at 0 (``bounded_mean_interval``); its square
    root is that of the distance (module docstring). Its coverage holds at every fixed z,
    the focus included, where no credible interval's can.

    References
    ----------
    .. [1] G. J. Feldman and R. D. Cousins, Phys. Rev. D 57, 3873 (1998).

    Examples
    --------
    The paper's symmetric curve, widths measured with an SD of 3 nm in focus and at 300 nm:

    >>> import numpy as np
    >>> from bayespsf.axial import distance_from_focus
    >>> from bayespsf.psf import Defocus
    >>> defocus = Defocus.symmetric(130.0, depth=400.0)
    >>> s_x, s_y = defocus.widths(np.array([0.0, 300.0]))
    >>> table = distance_from_focus(defocus, s_x, s_y, np.diag([9.0, 9.0]))
    >>> table[["lower", "upper", "plane"]].round(0)
       lower  upper  plane
    0    0.0  101.0    0.0
    1  278.0  321.0    0.0
    """
    plane = symmetry_plane(defocus) if isinstance(defocus, Defocus) else None
    if plane is None:
        raise BayespsfInputError(
            "the unified interval of |z - c| is for a defocus even about a plane c (both axes "
            "in focus at c, no odd term A); this one tells z's sign, so use z_posterior"
        )
    s_x, s_y = widths(s_x, s_y)
    s = np.stack([np.ravel(s_x), np.ravel(s_y)], axis=-1)
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape not in ((2, 2), (len(s), 2, 2)):
        raise BayespsfInputError(
            f"covariance must be 2 x 2 or one 2 x 2 per ROI ({len(s)}, 2, 2); got {cov.shape}"
        )
    cov = np.broadcast_to(cov, (len(s), 2, 2))
    if not np.all(np.isfinite(cov)):
        raise BayespsfInputError("covariance must be finite")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise BayespsfInputError("covariance must be positive definite for every ROI") from None
    weight = np.linalg.inv(cov)
    axes = _linear_axes(defocus, plane)
    f = np.column_stack([axis[0](s[:, a]) for a, axis in enumerate(axes)])
    df = np.column_stack([axis[1](s[:, a]) for a, axis in enumerate(axes)])
    in_focus = np.array([axis[2] for axis in axes])
    slope = np.array([axis[3] for axis in axes])
    w = weight / (df[:, :, None] * df[:, None, :])  # the precision of f(s), first order
    information = np.einsum("i,nij,j->n", slope, w, slope)
    tau_hat = np.einsum("i,nij,nj->n", slope, w, f - in_focus) / information
    tau_sd = 1.0 / np.sqrt(information)
    lower, upper = bounded_mean_interval(tau_hat / tau_sd, prob)
    return pd.DataFrame(
        {
            "lower": np.sqrt(lower * tau_sd),
            "upper": np.sqrt(upper * tau_sd),
            "tau_hat": tau_hat,
            "tau_sd": tau_sd,
            "plane": plane,
        }
    )


__all__ = ["bounded_mean_interval", "distance_from_focus"]
