"""Point estimates for a stack of ROIs: the paper's least squares, maximum likelihood, Laplace.

All three return a DataFrame with one row per ROI and the truth table's columns
``x0 y0 s_x s_y N b``, plus ``status``, ``converged`` (bool) and ``message``; ``fit_mle`` adds
``sd_<p>`` columns and the 15 correlations ``corr_<p>_<q>`` of the Laplace approximation
(``covariance`` rebuilds the matrices) and ``log_likelihood``. Outcomes are per ROI, never an
exception for the whole stack. ``status`` is ``"converged"`` where the fit converged; ``"not
converged"`` where the optimiser failed, a width ran away or the information is not positive
definite (the row keeps the last iterate, or NaN; the reason in ``message``); ``"refused"``
where the model cannot analyse the ROI (``Model.roi_problems``: constant, saturated, counts not
above the offset, ...; parameters NaN, the reason in ``message``).

The tables hold plain columns only, so they print, concatenate and save as CSV or Parquet.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import optimize

from bayespsf._runtime import one_blas_thread
from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import solver as stack_mle
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES, pixel_centres


def start_values(photons: np.ndarray, model: Model) -> np.ndarray:
    """Robust starting parameters of every ROI, from its moments.

    Parameters
    ----------
    photons : ndarray, shape (n, roi, roi)
        ROIs in N's unit (photons; ``Model.to_photons`` of the counts).
    model : Model
        Gives the ROI size and the pixel size ``a`` (nm).

    Returns
    -------
    ndarray, shape (n, 6)
        ``x0 y0 s_x s_y N b`` per ROI (nm, photons, photons per pixel).

    Notes
    -----
    Background: the median of the border pixels (>= 0). Position: the centroid of the
    background-subtracted image (negative values set to 0). Widths: its second moments,
    kept within [a/2, ROI side / 2]. N: the background-subtracted total, at least 1.
    """
    a, roi = model.pixel_size, model.roi
    c = pixel_centres(roi, a)
    border = np.concatenate(
        [photons[:, 0, :], photons[:, -1, :], photons[:, 1:-1, 0], photons[:, 1:-1, -1]], axis=1
    )
    b = np.maximum(np.median(border, axis=1), 0.0)
    signal = np.maximum(photons - b[:, None, None], 0.0)
    total = signal.sum(axis=(1, 2))
    weight = np.where(total > 0, total, 1.0)
    px, py = signal.sum(axis=1), signal.sum(axis=2)
    x0 = np.where(total > 0, px @ c / weight, 0.0)
    y0 = np.where(total > 0, py @ c / weight, 0.0)
    sx = np.sqrt(np.maximum(px @ c**2 / weight - x0**2 - a * a / 12, 0.0))
    sy = np.sqrt(np.maximum(py @ c**2 / weight - y0**2 - a * a / 12, 0.0))
    lo, hi = 0.5 * a, 0.5 * roi * a
    return np.column_stack(
        [x0, y0, np.clip(sx, lo, hi), np.clip(sy, lo, hi), np.maximum(total, 1.0), b]
    )


CORRELATIONS = [
    (i, j, f"corr_{PARAMETER_NAMES[i]}_{PARAMETER_NAMES[j]}")
    for i in range(6)
    for j in range(i + 1, 6)
]


def _frame(rows: list[dict], model: Model) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    first = [*PARAMETER_NAMES, "photon_unit"]
    df["photon_unit"] = model.photon_unit_label
    df["status"] = np.where(df["converged"], "converged", "not converged")
    if "refused" in df:
        df.loc[df["refused"].eq(True), "status"] = "refused"
        df = df.drop(columns="refused")
    return df[first + [c for c in df.columns if c not in first]]


def _stack(counts, model: Model):
    """The ROIs as ``(n, roi, roi)`` and why each cannot be fitted (``None`` where it can)."""
    c = model.check_shape(counts)
    stack = c.reshape(-1, model.roi, model.roi)
    return stack, model.roi_problems(stack)


def _refused_row(reason: str, extra: tuple[str, ...] = ()) -> dict:
    row = dict.fromkeys((*PARAMETER_NAMES, *extra), np.nan)
    return {**row, "converged": False, "message": reason, "refused": True}


def covariance(fits: pd.DataFrame) -> np.ndarray:
    """The Laplace covariance matrices of ``fit_mle``'s rows.

    Parameters
    ----------
    fits : pandas.DataFrame
        ``fit_mle``'s table (with ``laplace=True``): its ``sd_<p>`` and ``corr_<p>_<q>``.

    Returns
    -------
    ndarray, shape (n, 6, 6)
        In the order ``x0 y0 s_x s_y N b``; NaN where the fit did not converge.
    """
    sd = fits[[f"sd_{name}" for name in PARAMETER_NAMES]].to_numpy(float)
    corr = np.broadcast_to(np.eye(6), (len(fits), 6, 6)).copy()
    for i, j, column in CORRELATIONS:
        corr[:, i, j] = corr[:, j, i] = fits[column].to_numpy(float)
    return corr * sd[:, :, None] * sd[:, None, :]


# ---------------------------------------------------------------------------- least squares
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


# ----------------------------------------------------------------------- maximum likelihood
def _scipy_maximise(model, stack, starts):
    """One ROI at a time by scipy's L-BFGS-B (the reference path of ``fit_mle``), in the
    coordinates and box of ``stack_mle``, preconditioned by the expected information at the
    start so that a unit step is about one standard deviation in every coordinate."""
    a = model.pixel_size
    low, high = stack_mle.box(model.roi)
    n = len(stack)
    params, logl = np.empty((n, 6)), np.empty(n)
    converged, message = np.zeros(n, dtype=bool), np.empty(n, dtype=object)
    for i, (image, p0) in enumerate(zip(stack, starts, strict=True)):
        _, metric = stack_mle._gradient_and_metric(model, image[None], p0[None])
        scale = np.sqrt(np.clip(np.diagonal(metric[0]), 1e-8, 1e12))

        def objective(v, img=image, sc=scale):
            p = stack_mle.from_internal(v / sc, a)[None]
            value = stack_mle._objective(model, img[None], p)[0]
            if not np.isfinite(value):
                return 1e300, np.zeros(6)
            grad = stack_mle.gradient(model, img[None], p)[0] * stack_mle._chain(p, a)[0]
            return value, grad / sc

        res = optimize.minimize(
            objective,
            np.clip(stack_mle.to_internal(p0, a), low, high) * scale,
            jac=True,
            method="L-BFGS-B",
            bounds=list(zip(low * scale, high * scale, strict=True)),
            options={"maxiter": 2000, "ftol": 1e-13, "gtol": 1e-8},
        )
        params[i] = stack_mle.from_internal(res.x / scale, a)
        logl[i] = -res.fun
        # a line search that stops at machine precision on a flat optimum is not a failure
        converged[i] = bool(res.success or np.all(np.abs(res.jac) < 1e-3))
        message[i] = str(res.message)
    return params, logl, converged, message


ENGINES = ("stack", "scipy")


@one_blas_thread
def fit_mle(
    counts: ArrayLike,
    model: Model,
    start: ArrayLike | None = None,
    laplace: bool = True,
    engine: str = "stack",
    crlb: bool = True,
) -> pd.DataFrame:
    """Maximum likelihood under the model's camera law (any tier), with the Laplace SDs.

    Parameters
    ----------
    counts : array_like, shape (..., roi, roi)
        ROIs in ADU.
    model : Model
        Geometry, camera law and photon unit.
    start : array_like, shape (..., 6), optional
        Starting ``x0 y0 s_x s_y N b`` per ROI (nm, photons, photons per pixel); default
        ``start_values`` of the counts in photons.
    laplace : bool
        Add the Laplace SDs and correlations.
    engine : {"stack", "scipy"}
        The optimiser (Notes).
    crlb : bool
        Fill the ``crlb_<p>`` columns (NaN without): the expected information at every fit
        (for sCMOS, a quadrature per pixel, the costliest step of a fit).

    Returns
    -------
    pandas.DataFrame
        One row per ROI, in this order: ``x0 y0 s_x s_y`` (nm), ``N`` (photons), ``b``
        (photons per pixel), ``photon_unit``, ``log_likelihood``, ``crlb_x0`` ... ``crlb_b``,
        with ``laplace`` ``sd_x0`` ... ``sd_b`` and the 15 ``corr_<p>_<q>`` (``corr_x0_y0``
        ... ``corr_N_b``), then ``converged`` (bool), ``message`` and ``status``
        (``"converged"``, ``"not converged"`` or ``"refused"``; module docstring).

    Raises
    ------
    BayespsfInputError
        For an unknown ``engine``, counts not real or not ``(..., roi, roi)``, a bad ``start``.

    See Also
    --------
    fit_lsq : the paper's least squares.
    covariance : the ``(n, 6, 6)`` Laplace covariances of this table.
    sample_posterior : the posterior of one ROI, started from this fit.

    Notes
    -----
    ``engine="stack"`` (default): every ROI of the stack advances together in a vectorised
    Levenberg-Marquardt iteration with Fisher scoring (``bayespsf.inference.solver``). ``"scipy"``:
    L-BFGS-B one ROI at a time, the reference it is tested against (same optimum to ~1e-10 in
    log-likelihood). Both search ``(x0/a, y0/a, log s_x/a, log s_y/a, log N, b >= 0)`` in the
    same physical box (a fit ending on a bound is flagged), with the analytic gradient (PSF
    Jacobian times the camera's per-pixel score). With ``laplace``, ``sd_<p>`` columns are
    the square roots of the diagonal of the inverse observed information (the Hessian of
    -log L by differences of the analytic gradient) and ``corr_<p>_<q>`` its correlations
    (``covariance(fits)`` rebuilds the ``(n, 6, 6)`` matrices; NaN where not converged).
    ``crlb_<p>`` columns hold the Cramér-Rao bound at the fit (the inverse expected
    information, the plug-in error bar other fitters report; ``solver.crlb``). Not
    converged: the optimiser failed, a width ran away beyond the ROI, or the Hessian is not
    positive definite (SDs then NaN). ROIs the model cannot analyse are ``refused`` rows
    (module docstring); the other ROIs are fitted.

    Examples
    --------
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("paper-fig3")
    >>> counts, truth = bayespsf.simulate(scene, 2, seed=1)
    >>> fits = bayespsf.fit_mle(counts, bayespsf.Model.from_scene(scene))
    >>> fits[["x0", "sd_x0", "crlb_x0"]].notna().all().all(), fits["status"].tolist()
    (np.True_, ['converged', 'converged'])
    """
    if engine not in ENGINES:
        raise BayespsfInputError(f"engine must be one of {', '.join(ENGINES)}; got {engine!r}")
    stack, problems = _stack(counts, model)
    starts = (
        start_values(model.to_photons(stack), model)
        if start is None
        else finite_array("start", start).reshape(-1, 6)
    )
    if len(starts) != len(stack):
        raise BayespsfInputError(
            f"start must have one row per ROI ({len(stack)}), got {len(starts)}"
        )
    fit = np.flatnonzero([problem is None for problem in problems])
    maximise = stack_mle.maximise if engine == "stack" else _scipy_maximise
    params, logl, ok, message = maximise(model, stack[fit], starts[fit])
    low, high = stack_mle.box(model.roi)
    u = stack_mle.to_internal(params, model.pixel_size)
    # b's bound 0 is physical; any other coordinate on its bound is a failed search
    on_bound = np.any((np.abs(u - low) < 1e-9)[:, :5] | (np.abs(u - high) < 1e-9)[:, :5], axis=1)
    limit = model.roi * model.pixel_size
    runaway = (params[:, 2] > limit) | (params[:, 3] > limit)
    finite = np.all(np.isfinite(params), axis=1) & np.isfinite(logl)
    message = np.asarray(message, dtype=object)
    message[on_bound] = "ended on a bound of the search box"
    message[runaway] = "a width ran away beyond the ROI"
    message[~finite] = "non-finite estimate"
    ok &= finite & ~runaway & ~on_bound
    bound = np.full((len(fit), 6), np.nan)
    if crlb and ok.any():
        with np.errstate(invalid="ignore"):  # a negative diagonal (not invertible): NaN
            bound[ok] = _in_blocks(lambda p: stack_mle.crlb(model, p), params[ok], roi=model.roi)
    cov = np.full((len(fit), 6, 6), np.nan)
    if laplace and ok.any():
        cov[ok], definite = _laplace(model, stack[fit][ok], params[ok])
        bad = np.flatnonzero(ok)[~definite]
        message[bad] = "observed information not positive definite"
        ok[bad] = False
        cov[bad] = np.nan
    rows: list[dict] = []
    laplace_columns = (*(f"sd_{n}" for n in PARAMETER_NAMES), *(c for _, _, c in CORRELATIONS))
    crlb_columns = tuple(f"crlb_{n}" for n in PARAMETER_NAMES)
    fitted = dict(zip(fit, range(len(fit)), strict=True))
    for i, problem in enumerate(problems):
        if problem is not None:
            rows.append(_refused_row(problem, ("log_likelihood", *crlb_columns, *laplace_columns)))
            continue
        k = fitted[i]
        row = dict(zip(PARAMETER_NAMES, params[k], strict=True), log_likelihood=logl[k])
        row.update(zip(crlb_columns, bound[k], strict=True))
        if laplace:
            sd = np.sqrt(np.diagonal(cov[k]))
            row.update({f"sd_{name}": v for name, v in zip(PARAMETER_NAMES, sd, strict=True)})
            row.update({c: cov[k, p, q] / (sd[p] * sd[q]) for p, q, c in CORRELATIONS})
        row.update(converged=bool(ok[k]), message=str(message[k]))
        rows.append(row)
    return _frame(rows, model)


def _in_blocks(function, *arrays, roi: int):
    """``function`` over blocks of ``stack_mle.block_rois(roi)`` ROIs (bounded memory)."""
    n, step = len(arrays[0]), stack_mle.block_rois(roi)
    parts = [function(*(a[first : first + step] for a in arrays)) for first in range(0, n, step)]
    return np.concatenate(parts) if parts else np.empty((0, 6))


def _laplace(model, stack, params):
    """Inverse observed information per ROI and whether it is positive definite."""
    info = _in_blocks(
        lambda c, p: stack_mle.observed_information(model, c, p), stack, params, roi=model.roi
    )
    cov = np.full_like(info, np.nan)
    definite = np.zeros(len(info), dtype=bool)
    for i, matrix in enumerate(info):
        try:
            inverse = np.linalg.inv(matrix)
        except np.linalg.LinAlgError:
            continue
        if np.all(np.isfinite(inverse)) and np.all(np.linalg.eigvalsh(inverse) > 0):
            cov[i], definite[i] = inverse, True
    return cov, definite


def fit_laplace(counts: ArrayLike, model: Model, start: ArrayLike | None = None) -> pd.DataFrame:
    """The Laplace approximation: ``fit_mle`` with its ``sd_<p>`` columns.

    Parameters
    ----------
    counts, model, start
        As for ``fit_mle``: ROIs (ADU), the model, starting parameters (optional).

    Returns
    -------
    pandas.DataFrame
        ``fit_mle``'s table with ``laplace=True``: the fit, ``sd_<p>`` and ``corr_<p>_<q>``.

    See Also
    --------
    fit_mle, covariance
    """
    return fit_mle(counts, model, start=start, laplace=True)
