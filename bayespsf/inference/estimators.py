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

from bayespsf._runtime import one_blas_thread
from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import diagnostics, solver
from bayespsf.inference.backends import check_backend
from bayespsf.inference.settings import check_model
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES, pixel_centres


def start_values(photons, model, xp=np):
    """Robust starting parameters of every ROI, from its moments.

    Parameters
    ----------
    photons : array, shape (n, roi, roi)
        ROIs in N's unit (photons; ``Model.to_photons`` of the counts).
    model : Model or JaxModel
        Gives the ROI size ``roi`` and the pixel size ``pixel_size`` ``a`` (nm).
    xp : module
        The array library of ``photons``: NumPy, or ``jax.numpy`` (also under ``jax.jit``).

    Returns
    -------
    array, shape (n, 6)
        ``x0 y0 s_x s_y N b`` per ROI (nm, photons, photons per pixel).

    Notes
    -----
    Background: the median of the border pixels (>= 0). A first estimate from the whole ROI,
    background subtracted with negative values set to 0: position its centroid, widths its
    second moments (kept within [a/2, ROI side / 2]), N its total (at least 1). Clipping the
    noise at 0 inflates the widths and N (emccd-typical at N = 1 000: by ~18 and ~6 of their
    SDs), so the estimate is refined ``WINDOW_ROUNDS`` times from the pixels within
    ``WINDOW`` widths of the centre, background subtracted without clipping (the noise then
    averages out): position, widths and N from those pixels' moments and total, where that
    total is above a quarter of the first estimate's N and the moments are real (else the
    previous estimate stays). The maximum-likelihood fit starts nearer its optimum
    (emccd-typical at N = 1 000: 6.7 evaluations per ROI instead of 8.1 from the clipped
    estimate).
    """
    a, roi = model.pixel_size, model.roi
    c = xp.asarray(pixel_centres(roi, a))
    border = xp.concatenate(
        [photons[:, 0, :], photons[:, -1, :], photons[:, 1:-1, 0], photons[:, 1:-1, -1]], axis=1
    )
    b = xp.maximum(xp.median(border, axis=1), 0.0)
    lo, hi = 0.5 * a, 0.5 * roi * a
    clipped = xp.maximum(photons - b[:, None, None], 0.0)
    x0, y0, sx, sy, n = _moments(clipped.sum(axis=1), clipped.sum(axis=2), c, a, xp)
    sx, sy, n = xp.clip(sx, lo, hi), xp.clip(sy, lo, hi), xp.maximum(n, 1.0)
    for _ in range(WINDOW_ROUNDS):  # the window's marginals, without a masked copy of the ROIs
        in_x = (xp.abs(c[None, :] - x0[:, None]) <= WINDOW * sx[:, None]).astype(photons.dtype)
        in_y = (xp.abs(c[None, :] - y0[:, None]) <= WINDOW * sy[:, None]).astype(photons.dtype)
        px = xp.einsum("nij,ni->nj", photons, in_y) - (b * in_y.sum(axis=1))[:, None]
        py = xp.einsum("nij,nj->ni", photons, in_x) - (b * in_x.sum(axis=1))[:, None]
        wx, wy, wsx, wsy, total = _moments(px * in_x, py * in_y, c, a, xp)
        ok = total > 0.25 * n
        x0, y0 = xp.where(ok, wx, x0), xp.where(ok, wy, y0)
        sx = xp.where(ok & (wsx > 0), xp.clip(wsx, lo, hi), sx)
        sy = xp.where(ok & (wsy > 0), xp.clip(wsy, lo, hi), sy)
        n = xp.where(ok, total, n)
    return xp.stack([x0, y0, sx, sy, n, b], axis=1)


WINDOW = 2.5  # start_values' refinement: the pixels within this many widths of the centre
WINDOW_ROUNDS = 2


def _moments(px, py, c, a, xp):
    """Centroid, widths (0 where the second moment less the pixel's ``a^2/12`` is not
    positive) and total of a signal whose marginals along x and y are ``px``, ``py``
    (n, roi); the centroid 0 where the total is not positive. ``c``: the pixel centres
    (roi,). Sums by einsum: BLAS's ``@`` rounds a row by its place in the stack."""
    total = px.sum(axis=1)
    weight = xp.where(total > 0, total, 1.0)
    x0 = xp.where(total > 0, xp.einsum("nj,j->n", px, c) / weight, 0.0)
    y0 = xp.where(total > 0, xp.einsum("nj,j->n", py, c) / weight, 0.0)
    vx = xp.einsum("nj,j->n", px, c**2) / weight - x0**2 - a * a / 12
    vy = xp.einsum("nj,j->n", py, c**2) / weight - y0**2 - a * a / 12
    return x0, y0, xp.sqrt(xp.maximum(vx, 0.0)), xp.sqrt(xp.maximum(vy, 0.0)), total


CORRELATIONS = [
    (i, j, f"corr_{PARAMETER_NAMES[i]}_{PARAMETER_NAMES[j]}")
    for i in range(6)
    for j in range(i + 1, 6)
]
_PAIRS = tuple(np.array([pair[k] for pair in CORRELATIONS]) for k in (0, 1))  # (i, j) arrays


def _frame(rows: list[dict], model: Model) -> pd.DataFrame:
    empty = {**dict.fromkeys(PARAMETER_NAMES, np.float64), "converged": bool, "message": object}
    df = pd.DataFrame(rows) if rows else pd.DataFrame(columns=list(empty)).astype(empty)
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
    names = [f"sd_{name}" for name in PARAMETER_NAMES] + [c for _, _, c in CORRELATIONS]
    missing = [name for name in names if name not in fits]
    if missing:
        raise BayespsfInputError(
            f"fits has no {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}: "
            "covariance needs fit_mle's table with laplace=True"
        )
    values = fits[names].to_numpy(float)  # one block: the table's columns read once
    sd, upper = values[:, :6], values[:, 6:]
    i, j = _PAIRS
    corr = np.empty((len(fits), 6, 6))
    corr[:, i, j] = corr[:, j, i] = upper
    corr[:, np.arange(6), np.arange(6)] = 1.0
    return corr * sd[:, :, None] * sd[:, None, :]


# ----------------------------------------------------------------------- maximum likelihood
ENGINES = ("stack", "scipy")


def fit_mle(
    counts: ArrayLike,
    model: Model,
    start: ArrayLike | None = None,
    laplace: bool = True,
    engine: str = "stack",
    crlb: bool = True,
    backend: str = "numpy",
) -> pd.DataFrame:
    """Maximum likelihood under the model's camera law (any tier), with the Laplace SDs.

    Parameters
    ----------
    counts : array_like, shape (..., roi, roi)
        ROIs in ADU.
    model : Model
        Geometry, camera law and photon unit.
    start : array_like, shape (n, 6), optional
        Starting ``x0 y0 s_x s_y N b`` per ROI (nm, photons, photons per pixel; widths and N
        > 0, b >= 0); default ``start_values`` of the counts in photons.
    laplace : bool
        Add the Laplace SDs and correlations.
    engine : {"stack", "scipy"}
        The optimiser (Notes).
    crlb : bool
        Fill the ``crlb_<p>`` columns (NaN without): the expected information at every fit
        (for sCMOS, a quadrature per pixel, interpolated over the pixels of one readout).
    backend : {"numpy", "jax"}
        ``"jax"``: the stack engine in JAX (``bayespsf.inference.jax_mle``) on whatever
        device JAX finds (a GPU where one is installed); Photon and EMCCD cameras.

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
        For an unknown ``engine`` or ``backend`` (or ``"jax"`` without JAX), counts not real
        or not ``(..., roi, roi)``, a bad ``start``; with ``backend="jax"``, a camera law it
        does not support (sCMOS; the EMCCD ``exact`` tier with readout).

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
    -log L, analytic in the spot's 1-D factors and the camera law's score and curvature:
    ``solver.observed_information``) and ``corr_<p>_<q>`` its correlations
    (``covariance(fits)`` rebuilds the ``(n, 6, 6)`` matrices; NaN where not converged).
    ``crlb_<p>`` columns hold the Cramér-Rao bound at the fit (the inverse expected
    information, the plug-in error bar other fitters report; ``solver.crlb``). Not
    converged: the optimiser failed, a width ran away beyond the ROI, the Hessian is not
    positive definite, or the centre is not identified at the fit (its Cramér-Rao bound or
    Laplace SD undefined or beyond the ROI: a spot collapsed far below a pixel's width); SDs
    then NaN. ROIs the model cannot analyse are ``refused`` rows
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
    # before the screen: a bad option costs no work
    _check_options(engine, backend, model, laplace=laplace, crlb=crlb)
    stack, problems = _stack(counts, model)
    return fit_screened(stack, model, problems, start, laplace, engine, crlb, backend)


def _check_options(engine: str, backend: str, model, **flags) -> None:
    """``fit_mle``'s options: the engine and backend, the model, and ``flags`` (bool)."""
    check_model(model)
    for name, value in flags.items():
        if not isinstance(value, bool | np.bool_):
            raise BayespsfInputError(f"{name} must be True or False, got {value!r}")
    if engine not in ENGINES:
        raise BayespsfInputError(f"engine must be one of {', '.join(ENGINES)}; got {engine!r}")
    if check_backend(backend) == "jax" and engine != "stack":
        raise BayespsfInputError("backend='jax' runs the stack engine; use engine='stack'")


@one_blas_thread
def fit_screened(
    stack: ArrayLike,
    model: Model,
    problems: list | None = None,
    start: ArrayLike | None = None,
    laplace: bool = True,
    engine: str = "stack",
    crlb: bool = True,
    backend: str = "numpy",
    *,
    decrement: float = solver.DECREMENT,
) -> pd.DataFrame:
    """``fit_mle`` of a stack whose ROIs ``Model.roi_problems`` has already judged: the fit
    without judging them again (``sample_many`` screens a stack once, then fits it).

    Parameters
    ----------
    stack : array_like, shape (n, roi, roi)
        ROIs in ADU. Their values are not judged here: a ROI that ``roi_problems`` would
        refuse, given as passed, is fitted as it is.
    model : Model
        Geometry, camera law and photon unit.
    problems : list of (str or None), optional
        ``model.roi_problems(stack)``, one entry per ROI: those with a reason are refused rows
        with it. None: every ROI passed.
    start, laplace, engine, crlb, backend
        As ``fit_mle``.
    decrement : float, default 1e-10
        The NumPy stack engine's convergence test: a ROI has converged when its Newton
        decrement (log-likelihood units: about twice its distance from the maximum) is below
        this (``bayespsf.inference.solver``; another value is refused with the other engine or
        backend). The model check's refits take 1e-6.

    Returns
    -------
    pandas.DataFrame
        ``fit_mle``'s table.

    Raises
    ------
    BayespsfInputError
        As ``fit_mle`` for the stack's shape and the options; ``problems`` not one entry per
        ROI; a ``decrement`` that is not > 0, or not the default with the scipy engine or the
        JAX backend.

    See Also
    --------
    fit_mle : the same fit of counts not yet judged.
    """
    _check_options(engine, backend, model, laplace=laplace, crlb=crlb)
    decrement = solver.checked_decrement(decrement, engine == "stack" and backend == "numpy")
    stack = model.check_shape(stack)
    if stack.ndim != 3:
        raise BayespsfInputError(f"stack must have shape (n, roi, roi), got {stack.shape}")
    if problems is None:
        problems = [None] * len(stack)
    elif len(problems) != len(stack) or any(
        not (p is None or isinstance(p, str)) for p in problems
    ):  # e.g. a boolean mask would refuse every ROI with the reason True
        raise BayespsfInputError(
            f"problems must be one reason (str) or None per ROI ({len(stack)}), as "
            f"Model.roi_problems gives them; got {len(problems)} entries"
        )
    starts = None if start is None else _checked_starts(start, len(stack))
    fit = np.flatnonzero(np.equal(np.array(problems, dtype=object), None))
    fitted = stack if len(fit) == len(stack) else stack[fit]  # no copy where every ROI fits
    if starts is not None:
        starts = starts[fit]
    elif backend != "jax":  # the JAX backend computes them on its device
        starts = start_values(model.to_photons(fitted), model)
    if backend == "jax":
        from bayespsf.inference import jax_mle

        found = jax_mle.maximise(model, fitted, starts, laplace, True)  # bound: see below
        params, logl = found["params"], found["log_likelihood"]
        ok, message = found["converged"], found["message"]
    elif engine == "stack":
        params, logl, ok, message = solver.maximise(model, fitted, starts, decrement=decrement)
    else:
        params, logl, ok, message = solver.maximise_scipy(model, fitted, starts)
    low, high = solver.box(model.roi)
    u = solver.to_internal(params, model.pixel_size)
    # b's bound 0 is physical; any other coordinate on its bound is a failed search
    on_bound = np.any((np.abs(u - low) < 1e-9)[:, :5] | (np.abs(u - high) < 1e-9)[:, :5], axis=1)
    limit = model.roi * model.pixel_size
    runaway = (params[:, 2] > limit) | (params[:, 3] > limit)
    finite = np.all(np.isfinite(params), axis=1) & np.isfinite(logl)
    message = np.asarray(message, dtype=object)
    message[on_bound] = "ended on a bound of the search box"
    message[runaway] = "a width ran away beyond the ROI"
    message[~finite] = "non-finite estimate"
    for i in np.flatnonzero(~finite & np.all(np.isfinite(params), axis=1)):
        message[i] = diagnostics.no_density(fitted[i], model, params[i]) or message[i]
    ok &= finite & ~runaway & ~on_bound
    # the bound whatever ``crlb``, for the check that the centre is identified (without
    # ``crlb``, from the camera's step information: no quadrature for an sCMOS)
    bound = np.full((len(fit), 6), np.nan)
    if ok.any():
        with np.errstate(invalid="ignore"):  # a negative diagonal (not invertible): NaN
            bound[ok] = (
                found["crlb"][ok]
                if backend == "jax"
                else _in_blocks(
                    lambda p: solver.crlb(model, p, step=not crlb), params[ok], roi=model.roi
                )
            )
    cov = np.full((len(fit), 6, 6), np.nan)
    if laplace and ok.any():
        if backend == "jax":
            cov[ok], definite = found["cov"][ok], found["definite"][ok]
        else:
            cov[ok], definite = _laplace(model, fitted[ok], params[ok])
        bad = np.flatnonzero(ok)[~definite]
        message[bad] = "observed information not positive definite"
        ok[bad] = False
        cov[bad] = np.nan
    with np.errstate(invalid="ignore"):  # NaN SDs compare False
        spread = np.sqrt(np.abs(np.diagonal(cov, axis1=1, axis2=2)[:, :2]))
        lost = (spread > limit) | ~(bound[:, :2] <= limit)
    for i in np.flatnonzero(ok & lost.any(axis=1)):
        message[i] = _not_identified(params[i], model.pixel_size, limit)
        ok[i], cov[i] = False, np.nan
    if not crlb:
        bound[:] = np.nan
    return _mle_table(
        model, problems, fit, params, logl, bound, cov if laplace else None, ok, message
    )


def _not_identified(p: np.ndarray, a: float, limit: float) -> str:
    """Why a fit's centre is not identified, with the widths' likely reason."""
    widths = f"s_x = {p[2]:.3g}, s_y = {p[3]:.3g} nm"
    if min(p[2], p[3]) < 0.2 * a:
        widths += ": a spot much narrower than a pixel leaves its centre free within one"
    elif max(p[2], p[3]) > limit / 4:
        widths += ": a spot a quarter of the ROI wide is barely told from the background"
    return (
        "the centre is not identified at the fit: its Cramér-Rao bound or Laplace SD is "
        f"undefined or beyond the ROI's {limit:g} nm ({widths})"
    )


def _checked_starts(start, n: int) -> np.ndarray:
    """``fit_mle``'s ``start``: one row ``x0 y0 s_x s_y N b`` per ROI, finite, with widths and
    N > 0 and b >= 0 (the search's coordinates take their logs)."""
    starts = finite_array("start", start)
    if starts.ndim not in (1, 2) or starts.shape[-1] != 6 or starts.size != 6 * n:
        raise BayespsfInputError(
            f"start must have one row x0 y0 s_x s_y N b per ROI, shape ({n}, 6); got {starts.shape}"
        )
    starts = starts.reshape(n, 6)
    for k, name in ((2, "s_x"), (3, "s_y"), (4, "N")):
        if np.any(starts[:, k] <= 0):
            raise BayespsfInputError(f"start's {name} must be > 0 in every row")
    if np.any(starts[:, 5] < 0):
        raise BayespsfInputError("start's b must be >= 0 in every row")
    return starts


def _mle_table(model, problems, fit, params, logl, bound, cov, ok, message) -> pd.DataFrame:
    """``fit_mle``'s table, column by column (a dataset of 10^6 ROIs is not a loop of rows):
    fitted rows from the arrays, refused rows NaN with their reason."""
    n = len(problems)
    columns = {name: np.full(n, np.nan) for name in PARAMETER_NAMES}
    columns["photon_unit"] = model.photon_unit_label
    columns["log_likelihood"] = np.full(n, np.nan)
    for k, name in enumerate(PARAMETER_NAMES):
        columns[name][fit] = params[:, k]
    columns["log_likelihood"][fit] = logl
    for k, name in enumerate(PARAMETER_NAMES):
        columns[f"crlb_{name}"] = np.full(n, np.nan)
        columns[f"crlb_{name}"][fit] = bound[:, k]
    if cov is not None:
        with np.errstate(invalid="ignore"):  # NaN covariances (not converged) stay NaN
            sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
            for k, name in enumerate(PARAMETER_NAMES):
                columns[f"sd_{name}"] = np.full(n, np.nan)
                columns[f"sd_{name}"][fit] = sd[:, k]
            for p, q, column in CORRELATIONS:
                columns[column] = np.full(n, np.nan)
                columns[column][fit] = cov[:, p, q] / (sd[:, p] * sd[:, q])
    converged = np.zeros(n, dtype=bool)
    converged[fit] = ok
    messages = np.array(problems, dtype=object)  # the reason of each refused ROI
    messages[fit] = message  # the optimiser's (str)
    status = np.full(n, "refused", dtype=object)
    status[fit] = "not converged"
    status[converged] = "converged"
    return pd.DataFrame(columns | {"converged": converged, "message": messages, "status": status})


def _in_blocks(function, *arrays, roi: int):
    """``function`` over blocks of ``solver.block_rois(roi)`` ROIs (bounded memory)."""
    n, step = len(arrays[0]), solver.block_rois(roi)
    parts = [function(*(a[first : first + step] for a in arrays)) for first in range(0, n, step)]
    return np.concatenate(parts) if parts else np.empty((0, 6))


def _laplace(model, stack, params):
    """Inverse observed information per ROI and whether it is positive definite."""
    info = _in_blocks(
        lambda c, p: solver.observed_information(model, c, p), stack, params, roi=model.roi
    )
    inverse, definite = solver.inverses(info)
    definite &= np.all(np.isfinite(inverse), axis=(1, 2))
    if definite.any():
        definite[definite] = np.all(np.linalg.eigvalsh(inverse[definite]) > 0, axis=1)
    cov = np.full_like(info, np.nan)
    cov[definite] = inverse[definite]
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
