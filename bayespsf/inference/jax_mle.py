"""The stacked maximum-likelihood fit in JAX: ``fit_mle(..., backend="jax")``.

The same algorithm as the NumPy stack engine (``bayespsf.inference.solver``), written once as
a function of one ROI and mapped over a chunk of ROIs with ``jax.vmap``, so that it runs on
whatever device JAX finds: Levenberg-Marquardt with Fisher scoring in the coordinates
``u = (x0/a, y0/a, log s_x/a, log s_y/a, log N, b)``, the same search box, projected bounds,
damping schedule, secant updates of the metric near the optimum, iteration limit and
convergence test (the Newton decrement below 1e-10, by the Fisher metric).
Where the NumPy engine differentiates by hand (the PSF Jacobian times the camera's score), this
one differentiates the same log-likelihood automatically (``jax.grad``; ``jax.jacfwd`` for the
metric's PSF Jacobian), and the Laplace covariance is the inverse of the Hessian by the chain
rule through the expected counts (the law's two derivatives per pixel, the PSF's Jacobian and
``jax.hessian`` of the expected counts), where the NumPy engine forms the same terms from the
spot's 1-D factors and takes the law's curvature from its table's interpolant or a difference
of its score: the two agree within 1e-7 relative (``tests/inference/test_jax_backend.py``).

ROIs go to the device in chunks of a fixed size (the last one padded), so one compiled program
serves a whole dataset and the host holds one chunk's arrays at a time; a ROI's fit does not
depend on its chunk. A vmapped loop runs every lane until its last one finishes (emccd-typical:
about half the ROIs converge within 7 iterations, all within 14), so once at most 1/``COMPACT`` of
a chunk's ROIs are still iterating they are gathered into a smaller chunk (a ``bucket`` size)
and go on there, down to ``MIN_BUCKET``: the same fits bit for bit, 1.7x faster on 4 096
emccd-typical ROIs on the CPU. The starting values are ``estimators.start_values``, computed on
the device. The camera law and the PSF are ``bayespsf.inference.jax_model``'s.
"""

from __future__ import annotations

import functools
from functools import partial

import numpy as np

from bayespsf.inference import solver
from bayespsf.inference.backends import jax_modules, start_jax
from bayespsf.inference.estimators import start_values
from bayespsf.inference.jax_model import JaxModel

_MESSAGES = (
    f"iteration limit ({solver.MAX_ITERATIONS})",
    "Newton decrement below 1e-10",
    "no step lowers -log L (stationary to rounding)",
    "no step lowers -log L away from a stationary point",
)
DEVICE_PIXELS = {"cpu": 2**20, "gpu": 2**24}  # pixels per device call (one chunk of ROIs)
HESSIAN_PIXELS = 2**19  # pixels per Laplace/CRLB call (its arrays: ~4 kB per pixel)
MIN_BUCKET = 64  # the smallest chunk: smaller stacks are padded to it (one compiled shape)
TINY = 1e-300  # photons: the Laplace secant's lower end at lam = 0 (the law's slope there)
COMPACT = 8  # a fit's active lanes move to a smaller chunk once at most 1/COMPACT are active


def chunk_rois(roi: int, platform: str) -> int:
    """ROIs per device call for ``roi`` x ``roi`` ROIs on a ``platform`` (``"cpu"`` or a
    GPU): ``DEVICE_PIXELS`` pixels, at least one ROI.

    Parameters
    ----------
    roi : int
        ROI side in pixels.
    platform : str
        JAX's platform name of the device.

    Returns
    -------
    int
        ROIs per call.
    """
    pixels = DEVICE_PIXELS["cpu" if platform == "cpu" else "gpu"]
    return max(1, pixels // (roi * roi))


def bucket(n: int, largest: int) -> int:
    """The chunk size for ``n`` ROIs: the smallest power of two that holds them, at most
    ``largest`` (few distinct shapes, so few compilations, and little padding)."""
    return int(min(largest, max(MIN_BUCKET, 2 ** max(0, (n - 1).bit_length()))))


def to_internal(p, a):
    """``x0 y0 s_x s_y N b`` (..., 6) to ``u`` (``solver.to_internal`` in JAX)."""
    _, jnp = jax_modules()
    return jnp.stack(
        [p[..., 0] / a, p[..., 1] / a, jnp.log(p[..., 2] / a), jnp.log(p[..., 3] / a),
         jnp.log(p[..., 4]), p[..., 5]],
        axis=-1,
    )  # fmt: skip


def from_internal(u, a):
    """``u`` (..., 6) to ``x0 y0 s_x s_y N b`` (``solver.from_internal`` in JAX)."""
    _, jnp = jax_modules()
    return jnp.stack(
        [u[..., 0] * a, u[..., 1] * a, a * jnp.exp(u[..., 2]), a * jnp.exp(u[..., 3]),
         jnp.exp(u[..., 4]), u[..., 5]],
        axis=-1,
    )  # fmt: skip


def _evaluate(jm: JaxModel, counts, u):
    """``-log L``, its gradient and the Fisher-scoring metric, all in ``u``, for a chunk of
    ROIs ``counts`` (n, roi, roi) at ``u`` (n, 6): the PSF's Jacobian in ``u`` (one forward
    pass with six tangents per ROI) times the camera law's per-pixel score (``d log p / d
    lam``, one forward tangent over the chunk's pixels as one array, so that the law's rare
    costly branches run only where needed), as the NumPy engine forms them."""
    jax, jnp = jax_modules()
    a = jm.pixel_size

    def spot(v):
        lam = jm.expected(from_internal(v, a))
        return lam, lam

    jac, lam = jax.vmap(jax.jacfwd(spot, has_aux=True))(u)  # (n, roi, roi, 6), (n, roi, roi)
    log_p, score = jax.jvp(
        lambda x: jm.pixel_log_likelihood(counts, x), (lam,), (jnp.ones_like(lam),)
    )
    n = u.shape[0]
    f = -jnp.sum(log_p, axis=(1, 2))
    j = jac.reshape(n, -1, 6)
    grad = -jnp.einsum("np,npk->nk", score.reshape(n, -1), j)
    fisher = jm.step_information(jnp.maximum(lam, solver.METRIC_FLOOR)).reshape(n, -1)
    metric = jnp.einsum("npk,np,npl->nkl", j, fisher, j)
    finite = jnp.isfinite(f)
    return (
        jnp.where(finite, f, jnp.inf),
        jnp.where(finite[:, None], grad, jnp.nan),
        jnp.where(finite[:, None, None], metric, jnp.nan),
    )


def _freeze(u, grad, metric, low, high):
    """``solver.freeze_bounds`` for one ROI."""
    _, jnp = jax_modules()
    out = ((u <= low) & (grad > 0)) | ((u >= high) & (grad < 0))
    keep = ~out
    grad = jnp.where(out, 0.0, grad)
    metric = metric * (keep[:, None] & keep[None, :]) + jnp.eye(6) * out[:, None]
    return grad, metric


@functools.cache
def _compiled(roi: int):
    """The jitted chunk programs for ``roi`` x ``roi`` ROIs (one compiled program per ROI size
    and model structure; JAX caches the traces per static model fields)."""
    jax, jnp = jax_modules()
    low_np, high_np = solver.box(roi)

    def active(s):
        return ~s["done"] & (jnp.isfinite(s["f"]) | (s["it"] == 0))

    def start_fit(u0):
        low, high = jnp.asarray(low_np), jnp.asarray(high_np)
        n = u0.shape[0]
        # the first pass evaluates the start (compiled once, in the loop's body)
        return dict(
            u=jnp.clip(u0, low, high), f=jnp.full(n, jnp.inf), g=jnp.zeros((n, 6)),
            m=jnp.tile(jnp.eye(6), (n, 1, 1)), damping=jnp.full(n, 1e-3),
            secant=jnp.zeros(n, bool), done=jnp.zeros(n, bool), failed=jnp.zeros(n, bool),
            code=jnp.zeros(n, jnp.int32), it=jnp.asarray(0),
        )  # fmt: skip

    def advance(jm, counts, state, shrink):
        """Iterate every lane (a ROI) of the chunk until all are done or the iteration limit,
        or, with ``shrink``, until at most 1/``COMPACT`` of them are still active (the host
        then gathers those into a smaller chunk: a vmapped loop runs every lane until the
        last finishes)."""
        low, high = jnp.asarray(low_np), jnp.asarray(high_np)
        evaluate = partial(_evaluate, jm)
        n = counts.shape[0]

        def cond(s):
            going = jnp.any(active(s)) & (s["it"] < solver.MAX_ITERATIONS)
            if shrink:
                going &= COMPACT * jnp.sum(active(s)) > n
            return going

        def body(s):
            first = s["it"] == 0
            live = active(s) & ~first
            grad, metric = jax.vmap(_freeze, in_axes=(0, 0, 0, None, None))(
                s["u"], s["g"], s["m"], low, high
            )
            solve = jax.vmap(jnp.linalg.solve)
            decrement = jnp.einsum("nk,nk->n", grad, solve(metric, grad))
            # the NumPy engine's rules: within CHORD a step's metric is the secant update of
            # the one it leaves (there it is then not computed; here every lane computes it,
            # and the rule keeps the two engines' steps the same), and a lane below DECREMENT
            # by the secant's metric takes the Fisher metric where it stands before it is done
            below = live & (decrement < solver.DECREMENT)
            verify = below & s["secant"]
            finished = below & ~verify
            keeps = live & (decrement < solver.CHORD) & ~verify
            stepping = live & ~finished & ~verify
            diagonal = jnp.einsum("nkk->nk", metric)
            lm = metric + (s["damping"][:, None] * diagonal)[:, :, None] * jnp.eye(6)
            trial = jnp.clip(s["u"] + solve(lm, -grad), low, high)
            trial = jnp.where((first | verify)[:, None], s["u"], trial)
            real = jnp.all(jnp.isfinite(trial), axis=1)
            f_t, g_t, m_t = evaluate(counts, jnp.where(real[:, None], trial, s["u"]))
            f_t = jnp.where(real, f_t, jnp.inf)
            kept = solver.secant(s["m"], trial - s["u"], g_t - s["g"], xp=jnp)
            m_t = jnp.where((keeps & real)[:, None, None], kept, m_t)
            better = (stepping & jnp.isfinite(f_t) & (f_t <= s["f"])) | first
            damping = jnp.where(
                stepping, jnp.where(better, s["damping"] / 10, s["damping"] * 10), s["damping"]
            )
            stuck = stepping & (damping > 1e12)
            flat = decrement < solver.STATIONARY
            code = jnp.where(finished, 1, s["code"])
            code = jnp.where(stuck & flat, 2, jnp.where(stuck & ~flat, 3, code))
            return dict(
                u=jnp.where(better[:, None], trial, s["u"]),
                f=jnp.where(better, f_t, s["f"]),
                g=jnp.where(better[:, None], g_t, s["g"]),
                m=jnp.where((better | verify)[:, None, None], m_t, s["m"]),
                damping=damping,
                secant=jnp.where(better, keeps, s["secant"] & ~verify),
                done=s["done"] | finished | stuck,
                failed=s["failed"] | (stuck & ~flat),
                code=code,
                it=s["it"] + 1,
            )

        return jax.lax.while_loop(cond, body, state)

    def finish_fit(jm, s):
        f = jnp.where(jnp.isnan(s["f"]), jnp.inf, s["f"])
        p = from_internal(s["u"], jm.pixel_size)
        return p, -f, s["done"] & ~s["failed"] & jnp.isfinite(f), s["code"], s["u"]

    def gather(state, index):
        return {k: v if k == "it" else v[index] for k, v in state.items()}

    def scatter(state, index, part):  # ``part``'s lanes to the rows ``index`` (past the
        # end for padding lanes, whose updates are dropped): one shape per chunk size
        return {
            n: part[n] if n == "it" else v.at[index].set(part[n], mode="drop")
            for n, v in state.items()
        }

    def laplace_chunk(jm, counts, p):
        def one(c, q):
            # the chain rule through the expected counts: -H = J' diag(l'') J + sum l' d2lam,
            # the law's two derivatives per pixel in one pass (it is element-wise, so its
            # Hessian is diagonal: the product with ones), the geometry's from the cheap PSF;
            # jax.hessian of the whole sum ran the law's reverse pass once per parameter
            lam = jm.expected(q)

            def law(values):
                return jnp.sum(jm.pixel_log_likelihood(c, values))

            score, curvature = jax.jvp(jax.grad(law), (lam,), (jnp.ones_like(lam),))
            # below one photon, the camera's rule (``Camera.score_and_curvature_unchecked``):
            # a difference of the score over 1e-4 photons, a secant from just above 0 where
            # that would go below it; the table's interpolant amplifies its own error there
            # by 1 / lam^2, and the readout-alone branch at lam == 0 has not the law's slope
            step = 1e-4 * jnp.maximum(lam, 1.0)
            low, high = jnp.maximum(lam - step, TINY), lam + step
            secant = (jax.grad(law)(high) - jax.grad(law)(low)) / (high - low)
            curvature = jnp.where(lam < 1.0, secant, curvature)
            jac = jax.jacfwd(jm.expected)(q).reshape(-1, 6)
            fixed = jax.lax.stop_gradient(score)
            second = jax.hessian(lambda v: jnp.sum(fixed * jm.expected(v)))(q)
            hessian = -(jac.T @ (curvature.reshape(-1, 1) * jac) + second)
            return 0.5 * (hessian + hessian.T)

        info = jax.vmap(one)(counts, p)
        cov = jnp.linalg.inv(info)
        definite = jnp.all(jnp.isfinite(cov), axis=(1, 2)) & jnp.all(
            jnp.linalg.eigvalsh(jnp.where(jnp.isfinite(cov), cov, 0.0)) > 0, axis=1
        )
        return cov, definite

    def crlb_chunk(jm, p):
        def one(q):
            jac = jax.jacfwd(jm.expected)(q).reshape(-1, 6)
            fisher = jm.fisher(jnp.maximum(jm.expected(q), solver.METRIC_FLOOR)).reshape(-1, 1)
            return (jac * fisher).T @ jac

        return jnp.sqrt(jnp.diagonal(jnp.linalg.inv(jax.vmap(one)(p)), axis1=1, axis2=2))

    def start_chunk(jm, counts, per_adu, offset):
        photons = (counts - offset) * per_adu
        return to_internal(start_values(photons, jm, xp=jnp), jm.pixel_size)

    fit = dict(
        start=jax.jit(start_fit),
        advance=jax.jit(advance, static_argnames="shrink"),
        active=jax.jit(active),
        finish=jax.jit(finish_fit),
        gather=jax.jit(gather),
        scatter=jax.jit(scatter),
    )
    return fit, jax.jit(laplace_chunk), jax.jit(crlb_chunk), jax.jit(start_chunk)


def _fit(fit: dict, jm, counts, u0, size: int):
    """Fit a chunk of ``size`` ROIs from ``u0``, gathering the lanes still active into ever
    smaller chunks (``bucket`` sizes) once most have finished; each lane's arithmetic is the
    same in any chunk."""
    _, jnp = jax_modules()
    state = fit["advance"](jm, counts, fit["start"](u0), shrink=size > MIN_BUCKET)
    sub, sub_counts = state, counts
    rows = np.arange(size)  # the chunk's row of each of ``sub``'s lanes (the rest: padding)
    while True:
        still = np.flatnonzero(np.asarray(fit["active"](sub))[: len(rows)])
        if still.size == 0 or int(sub["it"]) >= solver.MAX_ITERATIONS:
            break
        smaller = bucket(still.size, len(sub_counts))
        moved = smaller < len(sub_counts)
        if moved:  # the active lanes, padded with the first's copies, into a smaller chunk
            pick = jnp.asarray(_padded(still, smaller))
            sub, sub_counts, rows = fit["gather"](sub, pick), sub_counts[pick], rows[still]
        sub = fit["advance"](jm, sub_counts, sub, shrink=bool(moved and smaller > MIN_BUCKET))
        if len(rows) < size:
            index = np.full(len(sub_counts), size)  # padding lanes: past the end, dropped
            index[: len(rows)] = rows
            state = fit["scatter"](state, jnp.asarray(index), sub)
        else:
            state = sub
    return fit["finish"](jm, state)


def maximise(model, counts: np.ndarray, starts: np.ndarray, laplace: bool, crlb: bool):
    """Fit every ROI of ``counts`` (n, roi, roi; validated) from ``starts`` (n, 6) on JAX's
    device, chunk by chunk.

    Parameters
    ----------
    model : Model
        The inference model (a camera law ``bayespsf.inference.jax_model`` supports).
    counts : ndarray, shape (n, roi, roi)
        Validated ROIs in ADU.
    starts : ndarray, shape (n, 6), or None
        Starting parameters; None: ``estimators.start_values`` of the counts, computed on the
        device.
    laplace, crlb : bool
        Also the Laplace covariances, and the Cramér-Rao bounds.

    Returns
    -------
    dict
        ``params`` (n, 6), ``log_likelihood`` (n,), ``converged`` (n,), ``message`` (n,),
        ``u`` (n, 6) the fit in the search coordinates, and with ``laplace`` ``cov``
        (n, 6, 6) and ``definite`` (n,), with ``crlb`` ``crlb`` (n, 6).
    """
    jax, jnp = jax_modules()
    start_jax()
    jm = JaxModel.from_model(model)
    roi = model.roi
    fit, laplace_chunk, crlb_chunk, start_chunk = _compiled(roi)
    n = len(counts)
    size = bucket(n, chunk_rois(roi, jax.devices()[0].platform))
    out = {
        "params": np.empty((n, 6)),
        "log_likelihood": np.empty(n),
        "converged": np.zeros(n, bool),
        "code": np.zeros(n, np.int32),
        "u": np.empty((n, 6)),
    }
    if laplace:
        out["cov"], out["definite"] = np.empty((n, 6, 6)), np.zeros(n, bool)
    if crlb:
        out["crlb"] = np.empty((n, 6))
    if starts is None:  # start_values on the device: the host's share of a fit is its I/O
        per_adu, offset = model.camera.photons_per_adu()
        per_adu = float(per_adu) / model.photoelectrons_per_photon
    else:
        u0 = solver.to_internal(starts, model.pixel_size)
    for first in range(0, n, size):
        part = slice(first, min(first + size, n))
        c = _padded(counts[part], size)
        on_device = jnp.asarray(c)
        k = part.stop - part.start
        if starts is None:
            u = start_chunk(jm, on_device, per_adu, float(offset))
        else:
            u = jnp.asarray(_padded(u0[part], size))
        p, logl, ok, code, u_end = _fit(fit, jm, on_device, u, size)
        for key, value in zip(
            ("params", "log_likelihood", "converged", "code", "u"),
            (p, logl, ok, code, u_end),
            strict=True,
        ):
            out[key][part] = np.asarray(value)[:k]
        # a Hessian's intermediates hold ~36 numbers per pixel: a fraction of the chunk at once
        step = max(1, min(size, HESSIAN_PIXELS // (roi * roi)))
        for low in range(0, k, step):
            rows = slice(first + low, first + min(low + step, k))
            q = _padded(np.asarray(p)[low : low + step], step)
            if laplace:
                cov, definite = laplace_chunk(
                    jm, jnp.asarray(_padded(c[low : low + step], step)), q
                )
                m = rows.stop - rows.start
                out["cov"][rows], out["definite"][rows] = (
                    np.asarray(cov)[:m],
                    np.asarray(definite)[:m],
                )
            if crlb:
                out["crlb"][rows] = np.asarray(crlb_chunk(jm, q))[: rows.stop - rows.start]
    out["message"] = np.asarray(_MESSAGES, dtype=object)[out.pop("code")]
    return out


def _padded(a: np.ndarray, size: int) -> np.ndarray:
    """``a`` with its first row repeated to ``size`` rows (one compiled shape per chunk)."""
    if len(a) == size:
        return a
    return np.concatenate([a, np.repeat(a[:1], size - len(a), axis=0)])


__all__ = [
    "COMPACT",
    "DEVICE_PIXELS",
    "bucket",
    "chunk_rois",
    "from_internal",
    "maximise",
    "to_internal",
]
