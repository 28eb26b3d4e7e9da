"""The log-likelihood of many draws of many ROIs in JAX, with the camera law interpolated.

``bayespsf.inference.fused`` for the JAX backend. Within one ROI's batch of draws each pixel's
count is fixed and only its expected value ``lam`` moves, over the narrow range the draws span;
the camera's log-likelihood is a smooth function of ``lam`` there. So the law is evaluated at
the ``DEGREE + 1`` Chebyshev nodes in ``sqrt(lam)`` spanning each pixel's range over the batch
and at the 4 check points (``chebyshev.CHECKS``), and every draw reads the pixel's
interpolating polynomial by Clenshaw's recurrence: ~20 multiply-adds and a square root per
pixel and draw, where the law itself (``JaxModel.pixel_log_likelihood``) costs a logarithm,
square roots, and, in a program that cannot branch per element, every one of the ``table``
tier's off-grid closed forms (a Bessel function, normal tails). The law runs at 13 points per
pixel instead of one per draw: for a 500-draw batch, 38x fewer evaluations.

Every interpolant is checked against the law at the check points: a ROI with a pixel whose
interpolant misses the law there by more than ``fused.TOLERANCE`` (1e-6 in log p), or whose
law is not finite at a node, or whose range reaches ``lam <= 0``, is flagged, and its caller
scores it with the law itself (``bayespsf.inference.jax_sampling`` reruns the flagged ROIs'
programs with ``exact``: a fixed-shape program cannot choose per ROI without computing both).
The interpolants are a ROI's own, so a ROI scores the same in any chunk; a draw's value depends
on the other draws of its batch (the range) within the tolerance.
"""

from __future__ import annotations

import numpy as np

from bayespsf.inference.chebyshev import AT_CHECKS, DEGREE, POINTS, TO_COEFFICIENTS
from bayespsf.inference.fused import TOLERANCE


def log_likelihood(jm, counts, p):
    """Interpolated ``JaxModel.log_likelihood`` of draws ``p`` (n, k, 6) of ``n`` ROIs.

    Parameters
    ----------
    jm : JaxModel
        The model.
    counts : jax.Array, shape (n, roi, roi)
        Each ROI's counts.
    p : jax.Array, shape (n, k, 6)
        ``x0 y0 s_x s_y N b`` of each ROI's draws, inside the prior's support.

    Returns
    -------
    log_likelihood : jax.Array, shape (n, k)
        Within ``TOLERANCE`` per pixel of the law's sum where ``usable``.
    usable : jax.Array of bool, shape (n,)
        Whether every pixel's interpolant passed the check (module docstring); where not,
        ``log_likelihood`` is not to be used.
    """
    import jax
    import jax.numpy as jnp

    # the factors once: a compiler may otherwise recompute them in each consumer below
    px, py, n, b = jax.lax.optimization_barrier(jm.spot(p))
    lam = n[..., None, None] * py[..., :, None] * px[..., None, :] + b[..., None, None]
    smallest = jnp.min(lam, axis=1)  # (n, roi, roi)
    positive = jnp.all(smallest > 0, axis=(1, 2))
    low, high = jnp.sqrt(jnp.maximum(smallest, 0.0)), jnp.sqrt(jnp.max(lam, axis=1))
    mid = 0.5 * (high + low)
    half = jnp.maximum(0.5 * (high - low), 1e-12 * mid + 1e-300)
    at = mid[:, None] + half[:, None] * jnp.asarray(POINTS)[None, :, None, None]
    values = jm.pixel_log_likelihood(counts[:, None], at * at)  # (n, 13, roi, roi)
    coef = jnp.einsum("kj,njab->nkab", jnp.asarray(TO_COEFFICIENTS), values[:, : DEGREE + 1])
    approx = jnp.einsum("kc,nkab->ncab", jnp.asarray(AT_CHECKS), coef)
    close = jnp.abs(approx - values[:, DEGREE + 1 :]) <= TOLERANCE  # False for NaN
    usable = positive & jnp.all(close, axis=(1, 2, 3))
    x = (jnp.sqrt(jnp.maximum(lam, 0.0)) - mid[:, None]) / half[:, None]
    return jnp.sum(_clenshaw(coef[:, None], x), axis=(-2, -1)), usable


def _clenshaw(c, x):
    """``sum_k c[..., k, :, :] T_k(x)`` (``c`` with the degree on its third-last axis)."""
    x2 = 2.0 * x
    later, last = np.zeros(()), c[..., DEGREE, :, :]
    for k in range(DEGREE - 1, 0, -1):
        later, last = last, c[..., k, :, :] + x2 * last - later
    return c[..., 0, :, :] + x * last - later


__all__ = ["log_likelihood"]
