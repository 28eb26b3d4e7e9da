"""Maximum likelihood for a whole stack of ROIs at once: every ROI advances together.

A Levenberg-Marquardt iteration with Fisher scoring (Levenberg 1944; Marquardt 1963; the
scoring metric of Smith, Joseph, Rieger & Lidke, Nat. Methods 7 (2010)): per ROI, with ``g`` the
gradient of ``-log L`` (the PSF Jacobian times the camera's per-pixel score) and ``M`` the
expected information (the Jacobian weighted by the camera's per-pixel Fisher information), both
in the coordinates ``u = (x0/a, y0/a, log s_x/a, log s_y/a, log N, b)``, the step solves
``(M + lambda diag M) delta = -g``; a step that lowers ``-log L`` is taken and ``lambda``
shrinks tenfold, one that does not is refused and ``lambda`` grows tenfold. A ROI has
converged when its Newton decrement ``g' M^-1 g`` falls below ``DECREMENT`` (the log-likelihood
is within ~1e-10 of its maximum, a step far below one standard deviation). Fisher scoring
converges linearly, so below a decrement of ``CHORD`` a ROI's metric is carried by the BFGS
secant update (``secant``: superlinear, no information computed), and a ROI below
``DECREMENT`` by the secant's metric converges only once the Fisher metric where it stands
agrees (emccd-typical: 6.7 evaluations per ROI instead of 9.7 at N = 1 000, 14 instead of 34
at N = 200; ``docs/decisions.md``). All the arithmetic of
an iteration is one array pass over the active ROIs of a block: the stack's cost is a few dozen
vectorised likelihood calls, not a Python loop per ROI. Each trial point is evaluated once,
``-log L`` with its gradient and metric (``evaluate``: one PSF pass, and one camera pass for
the log-likelihood and the score together), and a ROI keeps those of the point it stands on, so
a step costs one evaluation whether it is taken or refused. The Jacobian is never formed as
``(n, 6, roi, roi)`` images: the spot is separable, so its rows are outer products of 1-D
factors (``psf.gaussian.axis_factors``), and compiled loops (``inference.separable``) form
the expected counts, ``J' score`` and ``J' diag(F) J`` from them a pixel row at a time.

The box, the flags and the Laplace SDs are those of ``bayespsf.fit_mle``'s one-ROI scipy path
(``maximise_scipy``: the same search box, the same observed information:
``observed_information``, analytic in the spot's factors and the camera law's score and
curvature), so the two paths give the same numbers to the optimisers' tolerance
(``tests/inference/test_solver.py``).
"""

from __future__ import annotations

import numpy as np
from scipy import optimize

from bayespsf._validate import scalar_in_range
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.separable import expected_counts, hessian_sums, jacobian_sums
from bayespsf.psf.gaussian import axis_curvature, axis_factor, axis_factors

DECREMENT = 1e-10  # Newton decrement (in log-likelihood units) below which a ROI has converged
CHORD = 1.0  # ... below which a step carries the metric of the point it leaves (secant)
STATIONARY = 1e-4  # ... and where no step lowers -log L, the decrement that still counts as one
MAX_ITERATIONS = 200
METRIC_FLOOR = 1e-6  # expected photons per pixel (the EMCCD Fisher table's lower end)
BLOCK = 1024  # ROIs per array pass: the Jacobian of a block of 15 x 15 ROIs is 11 MB
BLOCK_PIXELS = 2**20  # ... and at most this many pixels per pass (its Jacobian: 48 MB)


def checked_decrement(decrement, own: bool) -> float:
    """``decrement`` as a float > 0, refused where it is not ``DECREMENT`` and the fit is not
    this engine's (``own`` False: the scipy engine or the JAX backend, which ignore it)."""
    decrement = scalar_in_range("decrement", decrement, 0.0, low_inclusive=False)
    if decrement != DECREMENT and not own:
        raise BayespsfInputError(
            f"decrement={decrement:g} is the NumPy stack engine's test; the scipy engine and "
            "the JAX backend converge by their own (use engine='stack', backend='numpy')"
        )
    return decrement


def block_rois(roi: int) -> int:
    """ROIs per array pass for ROIs of ``roi`` x ``roi`` pixels: ``BLOCK`` up to 31 x 31,
    fewer above (at least one), so that a pass holds at most ``BLOCK_PIXELS`` pixels (1024
    ROIs of 401 x 401 pixels would hold a 7.9 GB Jacobian). A ROI's fit does not depend on
    its block."""
    return int(min(BLOCK, max(1, BLOCK_PIXELS // (roi * roi))))


def box(roi: int) -> tuple[np.ndarray, np.ndarray]:
    """The search box in ``u`` (``fit_mle``'s): the centre within one ROI side of the ROI's
    centre, widths from a/20 to four ROI sides, N from 1e-3 to 1e9, b from 0 to 1e7 photons."""
    low = np.array([-roi, -roi, np.log(0.05), np.log(0.05), np.log(1e-3), 0.0])
    high = np.array([roi, roi, np.log(4 * roi), np.log(4 * roi), np.log(1e9), 1e7])
    return low, high


def to_internal(params: np.ndarray, a: float) -> np.ndarray:
    """``x0 y0 s_x s_y N b`` (..., 6) to ``u``."""
    u = np.array(params, dtype=np.float64)
    u[..., :2] /= a
    u[..., 2:4] = np.log(u[..., 2:4] / a)
    u[..., 4] = np.log(u[..., 4])
    return u


def from_internal(u: np.ndarray, a: float) -> np.ndarray:
    """``u`` (..., 6) to ``x0 y0 s_x s_y N b``."""
    p = np.array(u, dtype=np.float64)
    p[..., :2] *= a
    p[..., 2:4] = a * np.exp(p[..., 2:4])
    p[..., 4] = np.exp(p[..., 4])
    return p


def _chain(p: np.ndarray, a: float) -> np.ndarray:
    """``d params / d u`` per ROI, shape (n, 6)."""
    n = len(p)
    return np.column_stack([np.full(n, a), np.full(n, a), p[:, 2], p[:, 3], p[:, 4], np.ones(n)])


def _objective(model, counts, p):
    """``-log L`` per ROI (n,) at parameters ``p`` (n, 6)."""
    lam = model.expected(p)
    return -model.camera.log_likelihood_unchecked(counts, lam).sum(axis=(-2, -1))


def _gradient_and_metric(model, counts, p):
    """Gradient of ``-log L`` and the expected information, both in ``u``: (n, 6), (n, 6, 6),
    from the camera's score alone (``evaluate`` takes it with the log-likelihood)."""
    lam, x, y = _expected_and_factors(model, p)
    return _in_internal(model, p, lam, x, y, model.camera.score_unchecked(counts, lam))


def evaluate(model, counts, p, need=None):
    """``_objective`` and ``_gradient_and_metric`` at once, the same numbers (to rounding) from one
    PSF pass and one camera pass (``camera.log_likelihood_and_score_unchecked``): (n,), (n, 6),
    (n, 6, 6). The gradient and metric are NaN where ``-log L`` is not finite (never formed there).
    ``need`` (n,) bool: the ROIs whose metric is wanted (default all); the others' metric is NaN,
    and the camera's information is not computed for their pixels."""
    lam, x, y = _expected_and_factors(model, p)
    log_l, score = model.camera.log_likelihood_and_score_unchecked(counts, lam)
    f = -log_l.sum(axis=(-2, -1))
    finite = np.isfinite(f)
    if finite.all():
        return f, *_in_internal(model, p, lam, x, y, score, need)
    grad, metric = np.full((len(p), 6), np.nan), np.full((len(p), 6, 6), np.nan)
    grad[finite], metric[finite] = _in_internal(
        model,
        p[finite],
        lam[finite],
        x[finite],
        y[finite],
        score[finite],
        None if need is None else need[finite],
    )
    return f, grad, metric


def _expected_and_factors(model, p, x=None, y=None):
    """Expected photoelectrons (n, roi, roi) of ``p`` (n, 6), the same numbers as
    ``model.expected_and_jacobian``'s, and the spot's 1-D factors (n, 3, roi) along x and y
    (``psf.gaussian.axis_factors``) that its Jacobian is formed of. A factor given is taken
    as that of ``p`` (valid parameters whose other axis changed)."""
    if x is None and y is None:
        x, y = axis_factors(p, model.roi, model.pixel_size, model.pixel_model)
    elif x is None or y is None:
        centre, width = (0, 2) if x is None else (1, 3)
        made = axis_factor(
            p[:, centre], p[:, width], model.roi, model.pixel_size, model.pixel_model
        )
        x, y = (made, y) if x is None else (x, made)
    lam = expected_counts(
        x[:, 0],
        y[:, 0],
        p[:, 4],
        p[:, 5],
        model.photoelectrons_per_photon,
        model.clock_induced_charge,
        np.empty((len(p), model.roi, model.roi)),
    )
    return lam, x, y


def _reduce(model, p, x, y, score, fisher=None, need=None):
    """``J' score`` (n, 6) and, with ``fisher``, ``J' diag(fisher) J`` (n, 6, 6) in the
    parameters, from the 1-D factors without forming the Jacobian ``J`` (n, 6, roi, roi).
    ``need`` (n,) bool: the ROIs whose ``J' diag(fisher) J`` is formed (default all; the
    others' is NaN, and their ``fisher`` is not read)."""
    n = len(p)
    grad = np.zeros((n, 6))
    metric = np.zeros((n, 6, 6) if fisher is not None else (0, 6, 6))
    fisher = np.empty((0, 1, 1)) if fisher is None else np.ascontiguousarray(fisher, np.float64)
    need = np.ones(len(metric), dtype=bool) if need is None else np.asarray(need, dtype=bool)
    jacobian_sums(
        np.ascontiguousarray(x),
        np.ascontiguousarray(y),
        np.ascontiguousarray(p[:, 4], dtype=np.float64),
        float(model.photoelectrons_per_photon),
        np.ascontiguousarray(score, dtype=np.float64),
        fisher,
        need,
        grad,
        metric,
    )
    return grad, metric


def _in_internal(model, p, lam, x, y, score, need=None):
    """The gradient of ``-log L`` (the Jacobian times the per-pixel score) and the expected
    information, in ``u``, from the pixels' expected counts, the spot's 1-D factors and the
    score; the information only for the ROIs that ``need`` marks (default all; NaN for the
    others)."""
    # the metric only steers the steps (the optimum is where the gradient vanishes): pixels
    # below METRIC_FLOOR, where a camera's tabulated information ends, are scored at the floor
    if need is None or need.all():
        need = None
        fisher = model.camera.step_information_unchecked(np.maximum(lam, METRIC_FLOOR))
    else:
        fisher = np.empty_like(lam)
        if need.any():
            fisher[need] = model.camera.step_information_unchecked(
                np.maximum(lam[need], METRIC_FLOOR)
            )
    chain = _chain(p, model.pixel_size)
    grad, metric = _reduce(model, p, x, y, score, fisher, need)
    return -grad * chain, metric * chain[:, :, None] * chain[:, None, :]


def _contract(jac, pixels):
    """``sum_xy jac[n, k, x, y] pixels[n, x, y]`` (n, 6), as one batched matrix product: with
    ``_information``, the full-Jacobian form of ``_reduce``'s sums (its test reference)."""
    n, pixel_count = len(jac), pixels[0].size if len(pixels) else 0
    return (jac.reshape(n, 6, pixel_count) @ pixels.reshape(n, pixel_count, 1))[..., 0]


def _information(jac, fisher):
    """``J' diag(F) J`` per ROI (n, 6, 6) from the full Jacobian, as one batched matrix
    product (with ``_contract``, the reference of ``_reduce``'s sums)."""
    n, pixel_count = len(jac), fisher[0].size if len(fisher) else 0
    j = jac.reshape(n, 6, pixel_count)
    return (j * fisher.reshape(n, 1, pixel_count)) @ j.transpose(0, 2, 1)


def crlb(model, p, step: bool = False) -> np.ndarray:
    """The Cramér-Rao bound at parameters ``p`` (n, 6): the square roots of the diagonal of the
    inverse expected information ``J' diag(F) J`` in the parameters (the plug-in error bar
    localisation software reports at its fit; Smith et al., Nat. Methods 7 (2010)); NaN where
    the information is singular. ``step``: with the camera's step information instead of its
    Fisher information (``Camera.step_information_unchecked``: close to it, and far cheaper
    for an sCMOS), for checks that need only its scale."""
    lam, x, y = _expected_and_factors(model, p)
    floor = np.maximum(lam, METRIC_FLOOR)
    fisher = (
        model.camera.step_information_unchecked(floor)
        if step
        else model.camera.fisher_information_unchecked(floor)
    )
    _, information = _reduce(model, p, x, y, np.zeros_like(lam), fisher)
    inverse, ok = inverses(information)
    out = np.full((len(p), 6), np.nan)
    out[ok] = np.sqrt(np.diagonal(inverse[ok], axis1=1, axis2=2))
    return out


def inverses(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of ``matrices`` (n, 6, 6), in one batched call where none is singular, and
    which were invertible (n,) bool (the singular ones' entries are NaN)."""
    try:
        return np.linalg.inv(matrices), np.ones(len(matrices), dtype=bool)
    except np.linalg.LinAlgError:
        out, ok = np.full_like(matrices, np.nan), np.zeros(len(matrices), dtype=bool)
        for i, matrix in enumerate(matrices):
            try:
                out[i], ok[i] = np.linalg.inv(matrix), True
            except np.linalg.LinAlgError:
                continue
        return out, ok


def gradient(model, counts, p, x=None, y=None):
    """Gradient of ``-log L`` in the parameters ``x0 y0 s_x s_y N b``: (n, 6). ``x``, ``y``:
    the spot's 1-D factors at ``p`` where known (``_expected_and_factors``)."""
    lam, x, y = _expected_and_factors(model, p, x, y)
    return -_reduce(model, p, x, y, model.camera.score_unchecked(counts, lam))[0]


def observed_information(model, counts, p):
    """The Hessian of ``-log L`` in the parameters, (n, 6, 6): over the pixels, the law's
    curvature in the expected count times ``J J'``, minus its score times the expected
    count's second derivatives (from the spot's 1-D factors and their curvatures,
    ``psf.gaussian.axis_curvature``; analytic). The law's score and curvature come from
    ``camera.score_and_curvature_unchecked``: in closed form where the camera has it (the
    EMCCD table tier's interpolant), else the curvature a central difference of the score."""
    lam, x, y = _expected_and_factors(model, p)
    score, curvature = model.camera.score_and_curvature_unchecked(counts, lam)
    xc = axis_curvature(p[:, 0], p[:, 2], model.roi, model.pixel_size, model.pixel_model)
    yc = axis_curvature(p[:, 1], p[:, 3], model.roi, model.pixel_size, model.pixel_model)
    hessian = np.empty((len(p), 6, 6))
    hessian_sums(
        np.ascontiguousarray(x),
        np.ascontiguousarray(y),
        np.ascontiguousarray(xc),
        np.ascontiguousarray(yc),
        np.ascontiguousarray(p[:, 4], dtype=np.float64),
        float(model.photoelectrons_per_photon),
        np.ascontiguousarray(score, dtype=np.float64),
        np.ascontiguousarray(curvature, dtype=np.float64),
        hessian,
    )
    return hessian


def maximise(model, counts: np.ndarray, starts: np.ndarray, held=None, decrement=DECREMENT):
    """Maximum-likelihood parameters of every ROI of ``counts`` (n, roi, roi) from ``starts``
    (n, 6), block by block; ``held`` (6,) bool marks parameters kept at their start (the
    widths, for a fit at a given axial position: ``bayespsf.axial.posterior``); a ROI has
    converged when its Newton decrement is below ``decrement`` (log-likelihood units).

    Returns ``(params (n, 6), log_likelihood (n,), converged (n,) bool, message (n,) str)``.
    """
    n = len(counts)
    held = np.zeros(6, dtype=bool) if held is None else np.asarray(held, dtype=bool)
    params, logl = np.empty((n, 6)), np.empty(n)
    converged, message = np.zeros(n, dtype=bool), np.empty(n, dtype=object)
    step = block_rois(counts.shape[-1])
    for first in range(0, n, step):
        block = slice(first, min(first + step, n))
        params[block], logl[block], converged[block], message[block] = _maximise_block(
            model, counts[block], starts[block], held, decrement
        )
    return params, logl, converged, message


def _maximise_block(model, counts, starts, held, tolerance):
    a = model.pixel_size
    low, high = box(model.roi)
    u = np.clip(to_internal(starts, a), low, high)
    # -log L, gradient and metric at each ROI's current point, computed with the trial step
    # that moved it there: a refused step costs no new evaluation
    f, gradients, metrics = evaluate(model, counts, from_internal(u, a))
    damping = np.full(len(u), 1e-3)
    by_secant = np.zeros(len(u), dtype=bool)  # whether a ROI's metric is the secant's
    done, failed = np.zeros(len(u), dtype=bool), np.zeros(len(u), dtype=bool)
    message = np.full(len(u), f"iteration limit ({MAX_ITERATIONS})", dtype=object)
    for _ in range(MAX_ITERATIONS):
        active = np.flatnonzero(~done & np.isfinite(f))
        if active.size == 0:
            break
        ua = u[active]
        grad, metric = freeze_bounds(ua, gradients[active], metrics[active], low, high, held)
        diagonal = np.einsum("nkk->nk", metric)
        decrement = np.einsum("nk,nk->n", grad, _solve(metric, grad))
        # below the tolerance by the secant's metric, a ROI stays where it is and takes the Fisher
        # metric there (no step), and has converged only when that decrement is below too
        below = decrement < tolerance
        verify = below & by_secant[active]
        finished = below & ~verify
        # within CHORD of its maximum a ROI's metric, which only steers the step, is not
        # computed again: the secant update carries it to the next point
        keeps_metric = (decrement < CHORD) & ~verify
        done[active[finished]] = True
        message[active[finished]] = f"Newton decrement below {tolerance:g}"
        keep = ~finished
        active, ua, grad, metric, diagonal = (
            active[keep],
            ua[keep],
            grad[keep],
            metric[keep],
            diagonal[keep],
        )
        if active.size == 0:
            break
        verify = verify[keep]
        if verify.any():
            at = active[verify]
            p_at = from_internal(u[at], a)
            lam, x, y = _expected_and_factors(model, p_at)
            metrics[at] = _in_internal(model, p_at, lam, x, y, np.zeros_like(lam))[1]
            by_secant[at] = False
        lm = metric + (damping[active][:, None] * diagonal)[:, :, None] * np.eye(6)
        trial = np.clip(ua + _solve(lm, -grad), low, high)
        # a step that is not finite (an overflowing metric) is refused like a worse one
        f_trial = np.full(len(active), np.inf)
        grad_trial, metric_trial = (
            np.full((len(active), 6), np.nan),
            np.full((len(active), 6, 6), np.nan),
        )
        real = np.isfinite(trial).all(axis=1) & ~verify
        need = ~keeps_metric[keep]
        if real.any():
            f_trial[real], grad_trial[real], metric_trial[real] = evaluate(
                model, counts[active[real]], from_internal(trial[real], a), need[real]
            )
        kept = ~need & real
        at = active[kept]
        metric_trial[kept] = secant(
            metrics[at], trial[kept] - ua[kept], grad_trial[kept] - gradients[at]
        )
        better = np.isfinite(f_trial) & (f_trial <= f[active])
        moved = active[better]
        u[moved], f[moved] = trial[better], f_trial[better]
        gradients[moved], metrics[moved] = grad_trial[better], metric_trial[better]
        by_secant[moved] = kept[better]
        damping[active] = np.where(
            verify, damping[active], np.where(better, damping[active] / 10, damping[active] * 10)
        )
        stuck = ~verify & (damping[active] > 1e12)  # no step lowers -log L: stationary
        done[active[stuck]] = True
        flat = decrement[keep] < STATIONARY
        message[active[stuck & flat]] = "no step lowers -log L (stationary to rounding)"
        message[active[stuck & ~flat]] = "no step lowers -log L away from a stationary point"
        failed[active[stuck & ~flat]] = True
    p = from_internal(u, a)
    converged = done & ~failed & np.isfinite(f)
    message[~np.isfinite(f)] = "non-finite estimate"
    return p, -f, converged, message


ZERO_DENSITY = 1e300  # the scipy path's -log L where the likelihood is 0 (L-BFGS-B needs a number)


def maximise_scipy(model, stack, starts):
    """One ROI at a time by scipy's L-BFGS-B (the reference path of ``fit_mle``), in the
    coordinates and box of ``maximise``, preconditioned by the expected information at the
    start so that a unit step is about one standard deviation in every coordinate."""
    a = model.pixel_size
    low, high = box(model.roi)
    n = len(stack)
    params, logl = np.empty((n, 6)), np.empty(n)
    converged, message = np.zeros(n, dtype=bool), np.empty(n, dtype=object)
    for i, (image, p0) in enumerate(zip(stack, starts, strict=True)):
        _, metric = _gradient_and_metric(model, image[None], p0[None])
        scale = np.sqrt(np.clip(np.diagonal(metric[0]), 1e-8, 1e12))

        def objective(v, img=image, sc=scale):
            p = from_internal(v / sc, a)[None]
            value = _objective(model, img[None], p)[0]
            if not np.isfinite(value):
                return ZERO_DENSITY, np.zeros(6)
            grad = gradient(model, img[None], p)[0] * _chain(p, a)[0]
            return value, grad / sc

        res = optimize.minimize(
            objective,
            np.clip(to_internal(p0, a), low, high) * scale,
            jac=True,
            method="L-BFGS-B",
            bounds=list(zip(low * scale, high * scale, strict=True)),
            options={"maxiter": 2000, "ftol": 1e-13, "gtol": 1e-8},
        )
        params[i] = from_internal(res.x / scale, a)
        logl[i] = -res.fun if res.fun < ZERO_DENSITY else -np.inf  # nowhere a density
        # a line search that stops at machine precision on a flat optimum is not a failure
        converged[i] = bool(res.success or np.all(np.abs(res.jac) < 1e-3))
        message[i] = str(res.message)
    return params, logl, converged, message


def secant(metric, step, change, xp=np):
    """BFGS update of ``metric`` (n, 6, 6) by a ``step`` (n, 6) and the gradient's ``change``
    over it (n, 6): the metric that maps the step to the change (Nocedal & Wright, Numerical
    Optimization (2006), eq. 6.19), positive definite where ``metric`` is; a pair whose
    curvature ``change . step`` is not positive leaves it as it is. ``xp``: NumPy or JAX."""
    ms = xp.einsum("nij,nj->ni", metric, step)
    sms = xp.einsum("ni,ni->n", step, ms)
    ys = xp.einsum("ni,ni->n", change, step)
    ok = (ys > 1e-12 * xp.abs(sms)) & (sms > 0)
    ys, sms = xp.where(ok, ys, 1.0), xp.where(ok, sms, 1.0)
    update = (
        change[:, :, None] * change[:, None, :] / ys[:, None, None]
        - ms[:, :, None] * ms[:, None, :] / sms[:, None, None]
    )
    return metric + xp.where(ok[:, None, None], update, 0.0)


def freeze_bounds(u, grad, metric, low, high, held=False):
    """Projected Newton (Bertsekas, SIAM J. Control Optim. 20 (1982)): a coordinate on a bound
    of the box whose gradient points out of it is held there, its gradient zeroed and its
    metric row and column made the identity, so that a maximum on the boundary (b = 0 for a
    spot without background) converges instead of pushing at the bound. Coordinates marked
    ``held`` are held so everywhere."""
    out = ((u <= low) & (grad > 0)) | ((u >= high) & (grad < 0)) | held
    if not out.any():
        return grad, metric
    grad = np.where(out, 0.0, grad)
    keep = ~out
    metric = metric * (keep[:, :, None] & keep[:, None, :]) + np.eye(6) * out[:, :, None]
    return grad, metric


def _solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``matrix x = rhs`` per ROI; a singular system gives a zero step (that ROI is then
    flagged by its decrement or damping)."""
    try:
        return np.linalg.solve(matrix, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.zeros_like(rhs)
        for i in range(len(rhs)):
            try:
                out[i] = np.linalg.solve(matrix[i], rhs[i])
            except np.linalg.LinAlgError:
                continue
        return out
