"""How well z can be known: its Cramér-Rao bound under the camera law, the first-order error
propagated from the widths, and the paper's Delta z.

The model of z has the parameters ``theta = (x0, y0, z, N, b)`` and widths
``(s_x, s_y) = defocus.widths(z)``. Its Fisher information follows from the six-parameter one
(``bayespsf.theory.fisher_matrix``) by the chain rule, ``I_theta = A' I_p A`` with
``A = d p / d theta`` (Kay, Fundamentals of Statistical Signal Processing I (1993), sec. 3.8).

The first-order error of z from the widths is the delta method on the calibration curve:
with ``g = (ds_x/dz, ds_y/dz)`` and ``S`` the covariance of the estimated (s_x, s_y),
``var(z) = 1 / (g' S^-1 g)`` (the weighted least-squares fit of one z to the two widths). With
``S`` the widths' own Cramér-Rao covariance (x0, y0, N, b unknown), this equals the bound
on z exactly: the information on z is ``g' (I_ss - I_sn I_nn^-1 I_ns) g``, the widths'
information net of the nuisance parameters, projected on ``g``. Localisation software uses
this error with the covariance at its own fit (picasso's ``lpz`` and ThunderSTORM's
``uncertainty_z`` are of this kind); where ``g`` vanishes (in focus for the symmetric curve) it
is infinite, and near there a first-order error does not describe z's posterior.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus, HuangCurve
from bayespsf.theory import delta_z, fisher_matrix

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from bayespsf.model import Model

THETA_NAMES = ("x0", "y0", "z", "N", "b")


def to_widths(theta, defocus: Defocus) -> np.ndarray:
    """``(x0, y0, z, N, b)`` (..., 5) to the six parameters ``x0 y0 s_x s_y N b``."""
    theta = np.asarray(theta, dtype=np.float64)
    s_x, s_y = defocus.widths(theta[..., 2])
    return np.stack([theta[..., 0], theta[..., 1], s_x, s_y, theta[..., 3], theta[..., 4]], -1)


def chain(theta, defocus: Defocus) -> np.ndarray:
    """``A = d p / d theta`` (..., 6, 5)."""
    theta = np.asarray(theta, dtype=np.float64)
    out = np.zeros((*theta.shape[:-1], 6, 5))
    out[..., 0, 0] = out[..., 1, 1] = out[..., 4, 3] = out[..., 5, 4] = 1.0
    out[..., 2, 2], out[..., 3, 2] = defocus.slopes(theta[..., 2])
    return out


def fisher_z(model, defocus: Defocus, theta, method: str = "exact") -> np.ndarray:
    """The Fisher information of ``(x0, y0, z, N, b)`` (..., 5, 5) of one ROI."""
    a = chain(theta, defocus)
    info = fisher_matrix(model, to_widths(theta, defocus), method)
    return np.swapaxes(a, -1, -2) @ info @ a


def crlb_z(model: Model, defocus: Defocus, theta: ArrayLike, method: str = "exact") -> pd.Series:
    """The square root of the Cramér-Rao bound of ``x0, y0, z, N, b`` at one ``theta``.

    Parameters
    ----------
    model : Model
        Camera law and geometry of one ROI.
    defocus : Defocus
        The widths' curves ``(s_x(z), s_y(z))``.
    theta : array_like, shape (5,)
        ``(x0, y0, z, N, b)``: nm, nm, nm, photons, photons per pixel; ``N > 0``.
    method : {"exact", "excess-noise"}, default "exact"
        The camera's Fisher information (``bayespsf.theory.fisher_matrix``; the
        excess-noise approximation for an EMCCD).

    Returns
    -------
    pandas.Series
        Named ``crlb``, indexed by ``THETA_NAMES`` (``x0``, ``y0``, ``z``, ``N``, ``b``), in
        the parameters' units. z's is infinite where the widths do not change with z (the
        symmetric curve in focus: the others are then bounded as if z were known, not as the
        limit towards focus).

    Raises
    ------
    BayespsfInputError
        ``theta`` not five finite numbers with ``N > 0``.

    See Also
    --------
    first_order_z_sd : the first-order error of z from the widths' covariance.
    bayespsf.theory.crlb : the bound of the six width parameters.
    z_posterior : z's posterior, which the bound describes where it is near normal.

    Notes
    -----
    The Fisher information of ``theta`` follows from the six-parameter one by the chain rule,
    ``I_theta = A' I_p A`` with ``A = d p / d theta`` (Kay, Fundamentals of Statistical Signal
    Processing I (1993), sec. 3.8); the module docstring relates it to the first-order error.

    Examples
    --------
    >>> from bayespsf import Model, load_scene
    >>> from bayespsf.axial import crlb_z
    >>> from bayespsf.psf import Defocus
    >>> scene = load_scene("astigmatic")
    >>> defocus = Defocus.from_table(scene.axial, 130.0, 130.0)
    >>> bound = crlb_z(Model.from_scene(scene), defocus, [0.0, 0.0, 200.0, 2000.0, 10.0])
    >>> bound.round(1).to_dict()
    {'x0': 7.4, 'y0': 5.3, 'z': 28.7, 'N': 75.4, 'b': 0.3}
    """
    theta = finite_array("theta", theta)
    if theta.shape != (5,) or theta[3] <= 0:
        raise BayespsfInputError(f"theta must be one (x0, y0, z, N, b) with N > 0, got {theta!r}")
    info = fisher_z(model, defocus, theta, method)
    scale = np.sqrt(np.diag(info))
    if scale[2] == 0:  # no information on z: the rest are bounded as if z were known
        bound = np.full(5, np.inf)
        keep = [0, 1, 3, 4]
        bound[keep] = np.sqrt(np.diag(np.linalg.inv(info[np.ix_(keep, keep)])))
    else:
        bound = np.sqrt(np.diag(np.linalg.inv(info / np.outer(scale, scale)))) / scale
    return pd.Series(bound, index=list(THETA_NAMES), name="crlb")


def precision(covariance) -> np.ndarray:
    """The inverse of a widths' covariance ``S`` (2 x 2, finite, positive definite)."""
    covariance = np.asarray(covariance, dtype=np.float64)
    if covariance.shape != (2, 2) or not np.all(np.isfinite(covariance)):
        raise BayespsfInputError(f"covariance must be a finite 2 x 2 matrix, got {covariance!r}")
    try:
        np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        raise BayespsfInputError("covariance must be positive definite") from None
    return np.linalg.inv(covariance)


def first_order_z_sd(defocus: Defocus, z: ArrayLike, covariance: ArrayLike) -> np.ndarray:
    """The first-order SD of z from the widths' covariance, ``1 / sqrt(g' S^-1 g)``.

    Parameters
    ----------
    defocus : Defocus
        The widths' curves.
    z : array_like
        Axial positions, nm.
    covariance : array_like, shape (2, 2)
        ``S``, the covariance of the estimated ``(s_x, s_y)``, nm²; finite and positive
        definite.

    Returns
    -------
    numpy.ndarray
        The SD of z at each ``z`` (nm, z's shape); infinite where ``g = (ds_x/dz, ds_y/dz)``
        vanishes.

    Raises
    ------
    BayespsfInputError
        A ``z`` that is not finite, or a ``covariance`` that is not a finite, positive
        definite 2 x 2 matrix.

    See Also
    --------
    crlb_z : equal to this when ``S`` is the widths' own Cramér-Rao covariance.
    paper_delta_z : the paper's Delta z on its symmetric curve.

    Notes
    -----
    The delta method on the calibration curve (module docstring): the weighted least-squares
    fit of one z to the two widths. Localisation software uses this error with the
    covariance at its own fit (picasso's ``lpz``, ThunderSTORM's ``uncertainty_z``); near a
    point where ``g`` vanishes it does not describe z's posterior.
    """
    g = np.stack(defocus.slopes(finite_array("z", z)), axis=-1)
    information = np.einsum("...i,ij,...j->...", g, precision(covariance), g)
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(information)


def paper_delta_z(delta_s: ArrayLike, defocus: Defocus, z: ArrayLike) -> np.ndarray:
    """The paper's Delta z from Delta s, on the paper's symmetric curve only.

    Parameters
    ----------
    delta_s : array_like
        The width's error, nm.
    defocus : Defocus
        The paper's symmetric curve (``Defocus.symmetric``: both axes the same, in focus at
        0, ``A = B = 0``).
    z : array_like
        Axial positions, nm.

    Returns
    -------
    numpy.ndarray
        Delta z, nm (``bayespsf.theory.delta_z``); infinite in focus.

    Raises
    ------
    BayespsfInputError
        A curve other than the paper's symmetric one.

    See Also
    --------
    first_order_z_sd : the error of z for any curve.
    bayespsf.theory.delta_z : the equation of the paper's Discussion.
    """
    curve = defocus.x
    symmetric = type(curve) is HuangCurve and defocus.y == curve
    if not (symmetric and curve.c == 0.0 and curve.A == 0.0 and curve.B == 0.0):
        raise BayespsfInputError(
            "paper_delta_z needs the paper's symmetric curve (Defocus.symmetric); use "
            "first_order_z_sd for another curve"
        )
    return delta_z(delta_s, curve.w0, curve.width(z), curve.d)


__all__ = [
    "THETA_NAMES",
    "chain",
    "crlb_z",
    "first_order_z_sd",
    "fisher_z",
    "paper_delta_z",
    "precision",
    "to_widths",
]
