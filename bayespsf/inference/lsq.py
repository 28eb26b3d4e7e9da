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
    centres = pixel_centres(model.roi, model.pixel_size)
    values, jac = _gauss2d_stack(np.asarray(theta, dtype=float)[None], centres)
    return values.reshape(model.roi, model.roi), jac.reshape(6, model.roi, model.roi)


def lsq_to_params(theta, pixel_size: float) -> np.ndarray:
    """``(f0, x0, y0, s_x, s_y, b)`` to ``x0 y0 s_x s_y N b`` with ``N = 2 pi s_x s_y f0 / a^2``
    (the Gaussian's integral over the plane, in photons)."""
    f0, x0, y0, sx, sy, b = np.moveaxis(np.asarray(theta, float), -1, 0)
    return np.stack([x0, y0, sx, sy, 2 * np.pi * sx * sy * f0 / pixel_size**2, b], axis=-1)


STOPPED = "a step lowered the sum of squares by less than 1e-13 of itself"
FTOL = 1e-13  # the stack's stop: a step lowers the sum of squares by less than this of itself
MAX_STEPS = 200  # steps tried per ROI before the stack leaves it to scipy
BLOCK = 1024  # ROIs per pass of the stack (~11 kB of Jacobian per ROI of 15 x 15)
LOWEST_WIDTH = 1e-3  # the widths' lower bound, in pixels


def params_to_lsq(params, pixel_size: float) -> np.ndarray:
    """``x0 y0 s_x s_y N b`` to ``(f0, x0, y0, s_x, s_y, b)``, the inverse of
    ``lsq_to_params``."""
    x0, y0, sx, sy, n, b = np.moveaxis(np.asarray(params, float), -1, 0)
    return np.stack([n * pixel_size**2 / (2 * np.pi * sx * sy), x0, y0, sx, sy, b], axis=-1)


def _gauss2d_stack(theta, centres):
    """``gauss2d`` for a stack of ``theta`` (m, 6): values (m, P) and Jacobians (m, 6, P)."""
    f0, x0, y0, sx, sy, b = theta.T
    dx = (centres - x0[:, None]) / sx[:, None]
    dy = (centres - y0[:, None]) / sy[:, None]
    gx, gy = np.exp(-0.5 * dx * dx), np.exp(-0.5 * dy * dy)
    shape = gy[:, :, None] * gx[:, None, :]
    spot = f0[:, None, None] * shape
    m, n = spot.shape[:2]
    jac = np.empty((m, 6, n, n))
    jac[:, 0] = shape
    jac[:, 1] = spot * (dx / sx[:, None])[:, None, :]
    jac[:, 2] = spot * (dy / sy[:, None])[:, :, None]
    jac[:, 3] = spot * (dx * dx / sx[:, None])[:, None, :]
    jac[:, 4] = spot * (dy * dy / sy[:, None])[:, :, None]
    jac[:, 5] = 1.0
    return (spot + b[:, None, None]).reshape(m, -1), jac.reshape(m, 6, -1)


def _lsq_stack(photons, theta, model):
    """Levenberg-Marquardt for a stack of ROIs at once, from ``theta`` (m, 6).

    Returns the estimates (m, 6) and whether each converged: a step lowered its sum of
    squares by less than ``FTOL`` of itself. The damping is scaled by the diagonal of
    ``J^T J`` (Marquardt's scaling, as scipy's ``x_scale="jac"``); a step that would take a
    width below ``LOWEST_WIDTH`` pixels, or to a non-finite value, is refused as one that
    raises the sum. A ROI whose damping grows past 1e12 (no step lowers its sum) or that
    takes ``MAX_STEPS`` steps is left unconverged, for scipy.
    """
    centres = pixel_centres(model.roi, model.pixel_size)
    lowest = LOWEST_WIDTH * model.pixel_size
    y = photons.reshape(len(photons), -1)
    theta = np.array(theta, dtype=float)
    values, jac = _gauss2d_stack(theta, centres)
    residual = values - y
    cost = np.einsum("mp,mp->m", residual, residual)
    damping = np.full(len(theta), 1e-3)
    converged = np.zeros(len(theta), dtype=bool)
    active = np.arange(len(theta))
    for _ in range(MAX_STEPS):
        if not active.size:
            break
        j = jac[active]
        normal = np.einsum("mip,mjp->mij", j, j)
        gradient = np.einsum("mip,mp->mi", j, residual[active])
        scale = np.einsum("mii->mi", normal)
        scale = np.maximum(scale, 1e-12 * scale.max(axis=1, keepdims=True))  # a null column
        damped = normal + damping[active, None, None] * (scale[:, :, None] * np.eye(6))
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            trial = theta[active] - _solve(damped, gradient)
            valid = np.isfinite(trial).all(axis=1) & (trial[:, 3:5] > lowest).all(axis=1)
            trial[~valid] = theta[active][~valid]
            trial_values, trial_jac = _gauss2d_stack(trial, centres)
            trial_residual = trial_values - y[active]
            trial_cost = np.einsum("mp,mp->m", trial_residual, trial_residual)
        better = valid & (trial_cost < cost[active])
        done = better & (cost[active] - trial_cost <= FTOL * cost[active])
        kept = active[better]
        theta[kept], jac[kept] = trial[better], trial_jac[better]
        residual[kept], cost[kept] = trial_residual[better], trial_cost[better]
        damping[active] = np.where(better, damping[active] / 3, damping[active] * 4)
        converged[active[done]] = True
        active = active[~done & (damping[active] <= 1e12)]
    return theta, converged


def _solve(matrices, vectors):
    """``matrices^-1 vectors`` per ROI, NaN for a singular matrix (LAPACK solves matrix by
    matrix either way, so one singular matrix does not change the others' solutions)."""
    try:
        return np.linalg.solve(matrices, vectors[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full_like(vectors, np.nan)
        for k, (matrix, vector) in enumerate(zip(matrices, vectors, strict=True)):
            try:
                out[k] = np.linalg.solve(matrix, vector)
            except np.linalg.LinAlgError:
                pass
        return out


def _lsq_one(photons, start, model):
    a = model.pixel_size
    theta0 = params_to_lsq(start, a)
    lower = [-np.inf, -np.inf, -np.inf, LOWEST_WIDTH * a, LOWEST_WIDTH * a, -np.inf]
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
    the sampled Gaussian with amplitude f0 and constant background is fitted by least squares
    with an analytic Jacobian, the widths bounded below by ``LOWEST_WIDTH`` pixels. The stack
    is fitted at once, ``BLOCK`` ROIs at a time, by Levenberg-Marquardt (damping scaled by the
    diagonal of ``J^T J``), each ROI until a step lowers its sum of squares by less than
    ``FTOL`` of itself (``message``: ``STOPPED``); a ROI on which it stalls gets scipy's
    trust-region ``least_squares`` (``x_scale="jac"``) with scipy's message. The stack's
    estimates lie within ~1e-7 (relative) of the exact minimum, scipy's default stops within
    ~1e-5. Its widths estimate the pixelated width (Eq. tophat), not s0. Not converged: the
    optimiser failed, a width ran away beyond the ROI, or a value is not finite.

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
    todo = np.array([k for k, problem in enumerate(problems) if problem is None], dtype=int)
    theta, stopped = np.full((len(stack), 6), np.nan), np.zeros(len(stack), dtype=bool)
    for first in range(0, todo.size, BLOCK):
        block = todo[first : first + BLOCK]
        start = params_to_lsq(starts[block], model.pixel_size)
        theta[block], stopped[block] = _lsq_stack(photons[block], start, model)
    rows = []
    limit = model.roi * model.pixel_size
    for k, (image, start, problem) in enumerate(zip(photons, starts, problems, strict=True)):
        if problem is not None:
            rows.append(_refused_row(problem))
            continue
        if stopped[k]:
            params, ok, message = lsq_to_params(theta[k], model.pixel_size), True, STOPPED
        else:  # stalled in the stack: scipy's trust region, with the width's bound
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


__all__ = ["fit_lsq", "gauss2d", "lsq_first_order", "lsq_to_params", "params_to_lsq"]
