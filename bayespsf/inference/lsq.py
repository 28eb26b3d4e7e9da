"""The paper's fit: unweighted least squares of Eq. gauss2dfxn to counts in photons
(DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)), and its first-order prediction.

Returns the same table as the other point estimates (``bayespsf.inference.estimators``): one
row per ROI with ``x0 y0 s_x s_y N b``, ``status``, ``converged`` and ``message``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import optimize

from bayespsf.inference.estimators import _frame, _refused_row, _stack, start_values
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES, pixel_centres


def gauss2d(theta, model: Model):
    """Eq. gauss2dfxn sampled at the pixel centres, and its Jacobian.

    ``theta = (f0, x0, y0, s_x, s_y, b)``: ``f0 exp(-(x-x0)^2/2s_x^2 - (y-y0)^2/2s_y^2) + b``.
    Returns ``(values (roi, roi), jacobian (6, roi, roi))``.
    """
    f0, x0, y0, sx, sy, _ = theta
    c = pixel_centres(model.roi, model.pixel_size)
    dx, dy = (c - x0) / sx, (c - y0) / sy
    gx, gy = np.exp(-0.5 * dx * dx), np.exp(-0.5 * dy * dy)
    shape = gy[:, None] * gx[None, :]
    jac = np.empty((6, model.roi, model.roi))
    jac[0] = shape
    jac[1] = f0 * shape * (dx / sx)[None, :]
    jac[2] = f0 * shape * (dy / sy)[:, None]
    jac[3] = f0 * shape * (dx * dx / sx)[None, :]
    jac[4] = f0 * shape * (dy * dy / sy)[:, None]
    jac[5] = 1.0
    return f0 * shape + theta[5], jac


def lsq_to_params(theta, pixel_size: float) -> np.ndarray:
    """``(f0, x0, y0, s_x, s_y, b)`` to ``x0 y0 s_x s_y N b`` with ``N = 2 pi s_x s_y f0 / a^2``
    (the Gaussian's integral over the plane, in photons)."""
    f0, x0, y0, sx, sy, b = np.moveaxis(np.asarray(theta, float), -1, 0)
    return np.stack([x0, y0, sx, sy, 2 * np.pi * sx * sy * f0 / pixel_size**2, b], axis=-1)


def _lsq_one(photons, start, model):
    a = model.pixel_size
    f0 = start[4] * a * a / (2 * np.pi * start[2] * start[3])
    theta0 = np.array([f0, start[0], start[1], start[2], start[3], start[5]])
    lower = [-np.inf, -np.inf, -np.inf, 1e-3 * a, 1e-3 * a, -np.inf]
    y = photons.ravel()

    def residual(theta):
        return gauss2d(theta, model)[0].ravel() - y

    def jacobian(theta):
        return gauss2d(theta, model)[1].reshape(6, -1).T

    res = optimize.least_squares(
        residual, theta0, jac=jacobian, bounds=(lower, np.inf), method="trf", x_scale="jac"
    )
    return res


def fit_lsq(counts: ArrayLike, model: Model) -> pd.DataFrame:
    """The paper's fit: unweighted least squares of Eq. gauss2dfxn to counts in photons.

    Parameters
    ----------
    counts : array_like, shape (..., roi, roi)
        ROIs in ADU.
    model : Model
        Geometry and camera (its mean gain converts the counts to photons).

    Returns
    -------
    pandas.DataFrame
        One row per ROI: ``x0 y0 s_x s_y`` (nm), ``N`` (photons), ``b`` (photons per pixel),
        ``photon_unit``, ``converged`` (bool), ``message`` and ``status`` (``"converged"``,
        ``"not converged"`` or ``"refused"``; module docstring).

    Raises
    ------
    BayespsfInputError
        If ``counts`` is not real or not of shape ``(..., roi, roi)``.

    See Also
    --------
    fit_mle : maximum likelihood under the camera law, with error bars.
    lsq_first_order : this fit's limit and covariance, predicted to first order.

    Notes
    -----
    As in DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) (MATLAB ``lsqcurvefit``):
    counts are converted to photons with the camera's mean gain (``Model.to_photons``) and
    fitted by a trust-region least squares (scipy ``least_squares``, analytic Jacobian) of the
    sampled Gaussian with amplitude f0 and constant background. Its widths estimate the
    pixelated width (Eq. tophat), not s0. Not converged: the optimiser failed, a width ran
    away beyond the ROI, or a value is not finite.

    Examples
    --------
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("paper-fig3")
    >>> counts, truth = bayespsf.simulate(scene, 2, seed=1)
    >>> bayespsf.fit_lsq(counts, bayespsf.Model.from_scene(scene))["status"].tolist()
    ['converged', 'converged']
    """
    stack, problems = _stack(counts, model)
    photons = model.to_photons(stack)
    starts = start_values(photons, model)
    rows = []
    limit = model.roi * model.pixel_size
    for image, start, problem in zip(photons, starts, problems, strict=True):
        if problem is not None:
            rows.append(_refused_row(problem))
            continue
        res = _lsq_one(image, start, model)
        params = lsq_to_params(res.x, model.pixel_size)
        ok, message = bool(res.success), res.message
        if not np.all(np.isfinite(params)):
            ok, message = False, "non-finite estimate"
        elif params[2] > limit or params[3] > limit:
            ok, message = False, "a width ran away beyond the ROI"
        rows.append(dict(zip(PARAMETER_NAMES, params, strict=True), converged=ok, message=message))
    return _frame(rows, model)


def lsq_first_order(model: Model, params):
    """First-order prediction of ``fit_lsq``: its limit and its covariance.

    The limit is the least-squares fit of Eq. gauss2dfxn to the noise-free expected image (in
    photons): the sampled Gaussian that best matches the pixel-integrated spot. The covariance
    is the M-estimator sandwich ``A^-1 B A^-1`` with ``A`` the Hessian of the half sum of
    squares at the limit (including the residual-curvature term, since the models differ) and
    ``B = J^T diag(var) J`` with the camera's exact pixel variances in photons (Huber 1967;
    White 1982). Returned in ``x0 y0 s_x s_y N b`` by the delta method.

    Returns
    -------
    limit : ndarray (6,), covariance : ndarray (6, 6)
    """
    params = np.asarray(params, float)
    lam = model.expected(params)  # expected photoelectrons (CIC included)
    mean = lam / model.photoelectrons_per_photon  # the mean of model.to_photons(counts)
    res = _lsq_one(mean, params, model)
    theta = res.x
    _, jac = gauss2d(theta, model)
    j = jac.reshape(6, -1).T
    variance = model.photon_variance(lam).ravel()

    def gradient(th):
        values, jj = gauss2d(th, model)
        return jj.reshape(6, -1) @ (values - mean).ravel()

    steps = 1e-6 * np.maximum(np.abs(theta), 1.0)
    hess = np.array(
        [
            (gradient(theta + e) - gradient(theta - e)) / (2 * h)
            for e, h in zip(np.diag(steps), steps, strict=True)
        ]
    )
    a_inv = np.linalg.inv(0.5 * (hess + hess.T))
    cov_theta = a_inv @ (j.T * variance) @ j @ a_inv
    f0, _, _, sx, sy, _ = theta
    a2 = model.pixel_size**2
    to_params = np.zeros((6, 6))  # d(x0 y0 s_x s_y N b) / d(f0 x0 y0 s_x s_y b)
    to_params[0, 1] = to_params[1, 2] = to_params[2, 3] = to_params[3, 4] = to_params[5, 5] = 1.0
    to_params[4] = [
        2 * np.pi * sx * sy / a2,
        0,
        0,
        2 * np.pi * sy * f0 / a2,
        2 * np.pi * sx * f0 / a2,
        0,
    ]
    return lsq_to_params(theta, model.pixel_size), to_params @ cov_theta @ to_params.T


__all__ = ["fit_lsq", "gauss2d", "lsq_first_order", "lsq_to_params"]
