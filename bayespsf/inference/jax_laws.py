"""Camera laws in JAX: per-pixel log-likelihoods and Fisher information for ``jax_model``.

Pure ``jax.numpy`` translations of the NumPy laws of ``bayespsf.cameras``, formula for formula:
the Poisson pmf of the ``Photon`` camera and the ``EMCCD`` tiers ``poisson``, ``gaussian``,
``high-gain`` (with and without readout) and ``table`` (the bicubic patches of the camera's own
table, the second-order small-lam expansion below its grid, the readout alone at lam = 0), and
the exact-law EMCCD Fisher information (the camera's own spline of ``log(lam I)``). Everything
is in gain units (``t = (counts - offset) e_per_adu / gain``, ``r = readout_sd / gain``) and in
float64.

Every function is jit-able, vmap-able and differentiable by lam: where a formula is undefined
off its branch (``log 0``, ``sqrt 0``), that branch is evaluated at a safe stand-in and then
masked (the "double where"), so that neither values nor gradients carry NaN from the branch not
taken. Points are classified by the sign of ``counts - offset`` rather than of ``t``: the two
agree except where ``t`` underflows, which the CPU backend flushes to zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import special

LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)
# terms of log_ndtr's asymptotic series below -20: JAX's default, 3, is 2e-11 relative there,
# 10 is within an ulp of scipy's (and of mpmath) down to -1e4
LOG_NDTR_ORDER = 10


def log_ndtr(x):
    """``log Phi(x)`` to full double precision (``scipy.special.log_ndtr``)."""
    return special.log_ndtr(x, series_order=LOG_NDTR_ORDER)


@dataclass(frozen=True)
class TableGrid:
    """The static description of an EMCCD table's two grids (``_emccd_table``'s constants).

    Parameters
    ----------
    xi0, xi_step : float
        First node and step of the log lam axis.
    n_xi : int
        Nodes along log lam.
    eta0, eta_step : float
        First node and step of the bulk grid's count axis ``eta = v(t) - sqrt(lam)``.
    n_eta : int
        Nodes along eta.
    tau0, tau_step : float
        First node and step of the near grid's count axis ``tau = t / r``.
    n_tau : int
        Nodes along tau.
    near_offset : int
        Row of the first near-grid cell in the coefficient array.
    near : float
        The near grid serves ``|t| < near r``; counts below ``-near r`` are off both grids.
    lam_min, lam_max : float
        The log lam axis' ends.
    small_lam_reach : float
        Below ``lam_min`` the small-lam expansion serves ``lam (|t| + r) <= small_lam_reach``.
    """

    xi0: float
    n_xi: int
    xi_step: float
    eta0: float
    n_eta: int
    eta_step: float
    tau0: float
    n_tau: int
    tau_step: float
    near_offset: int
    near: float
    lam_min: float
    lam_max: float
    small_lam_reach: float

    @classmethod
    def from_arrays(cls, table: dict) -> TableGrid:
        """The grid of ``EMCCD.law_arrays()["table"]``.

        Parameters
        ----------
        table : dict
            The table's entry of ``law_arrays``.

        Returns
        -------
        TableGrid
        """
        return cls(**{name: table[name] for name in cls.__dataclass_fields__})


def xlogy(k, lam):
    """``k log lam`` with ``0 log 0 = 0``; its derivative by lam is 0 where ``k == 0``."""
    zero = k == 0
    return jnp.where(zero, 0.0, k * jnp.log(jnp.where(zero, 1.0, lam)))


def poisson_log_pmf(k, lam):
    """``k log lam - lam - log k!`` (``cameras.photon.poisson_log_pmf``), real ``k >= 0``."""
    return xlogy(k, lam) - lam - special.gammaln(k + 1.0)


def log_normal_pdf(t, r: float):
    """Log density of ``Normal(0, r)`` at ``t`` (``r > 0`` a number)."""
    return -0.5 * (t / r) ** 2 - np.log(r) - LOG_SQRT_2PI


def log_0f1_2(w):
    """``log 0F1(; 2; w) = log(I1(2 sqrt w) / sqrt w)`` for ``w >= 0`` (``i1e``); the series
    ``w/2 - w**2/24`` below 1e-8."""
    small = w < 1e-8
    ws = jnp.where(small, 1.0, w)
    wt = jnp.where(small, w, 0.0)
    z = 2.0 * jnp.sqrt(ws)
    big = jnp.log(special.i1e(z)) + z - 0.5 * jnp.log(ws)
    return jnp.where(small, wt * (0.5 - wt / 24.0), big)


def log_high_gain(t, x, lam):
    """The readout-free law (``_emccd_law.log_high_gain``): the atom's log mass ``-lam`` at
    ``x == 0``, the amplified part's log density for ``x > 0`` and ``lam > 0``, else ``-inf``.
    ``x = counts - offset`` classifies the point (same sign as ``t``)."""
    positive = (x > 0) & (lam > 0)
    ts = jnp.where(positive, t, 1.0)
    ls = jnp.where(positive, lam, 1.0)
    amplified = -ls - ts + jnp.log(ls) + log_0f1_2(ls * ts)
    continuous = jnp.where(positive, amplified, -jnp.inf)
    return jnp.where(x == 0, -lam, continuous)


def log_high_gain_readout(t, x, lam, r: float):
    """The ``high-gain`` tier with readout ``r > 0``: the zero-electron atom convolved with the
    readout exactly, the amplified part readout-free (``EMCCD._log_high_gain``)."""
    continuous = jnp.where(x == 0, -jnp.inf, log_high_gain(t, x, lam))
    atom = -lam + log_normal_pdf(t, r)
    return jnp.logaddexp(atom, continuous)


def log_readout_free(t, x, lam, log_jacobian: float):
    """The readout-free law per ADU: the atom at the offset is a mass (no Jacobian)."""
    amplified = log_high_gain(t, x, lam)
    return jnp.where(x == 0, amplified, amplified + log_jacobian)


def log_gaussian(t, x, lam, r: float):
    """``Normal(lam, 2 lam + r**2)`` in gain units (``_emccd_law.gaussian_log_pdf``); the
    degenerate ``lam = r = 0`` is the atom at the offset."""
    var = 2.0 * lam + r * r
    degenerate = var == 0
    v = jnp.where(degenerate, 1.0, var)
    log_pdf = -0.5 * (t - lam) ** 2 / v - 0.5 * jnp.log(2.0 * np.pi * v)
    return jnp.where(degenerate, jnp.where(x == 0, 0.0, -jnp.inf), log_pdf)


def log_poisson_tier(t, x, lam):
    """The ``poisson`` tier: photons ``t`` scored by the Poisson pmf, ``-inf`` below zero."""
    return jnp.where(x >= 0, poisson_log_pmf(jnp.maximum(t, 0.0), lam), -jnp.inf)


@jax.custom_jvp
def log_quadratic(lam, atom, first, second):
    """``log(exp(atom) + lam exp(first) + lam**2 exp(second))`` for ``lam > 0``, evaluated as
    ``logaddexp(logaddexp(atom, log lam + first), 2 log lam + second)``.

    Its derivatives are written without ``1 / lam`` (``d/dlam = exp(first - out) + 2 lam
    exp(second - out)``), so that they stay finite at the smallest lam, where those of
    ``log lam`` overflow.
    """
    log_lam = jnp.log(lam)
    return jnp.logaddexp(jnp.logaddexp(atom, log_lam + first), 2.0 * log_lam + second)


@log_quadratic.defjvp
def _log_quadratic_jvp(primals, tangents):
    lam, atom, first, second = primals
    d_lam, d_atom, d_first, d_second = tangents
    out = log_quadratic(lam, atom, first, second)
    w1, w2 = jnp.exp(first - out), jnp.exp(second - out)
    tangent = (
        jnp.exp(atom - out) * d_atom
        + lam * w1 * d_first
        + lam * lam * w2 * d_second
        + (w1 + 2.0 * lam * w2) * d_lam
    )
    return out, tangent


def log_small_lam(t, lam, r: float):
    """The law with readout to second order in ``lam > 0`` (``_emccd_law.log_small_lam``)."""
    x = (t - r * r) / r
    shift = 0.5 * r * r - t
    atom = log_normal_pdf(t, r)
    first = shift + log_ndtr(x)
    reached = x > -5.0
    xs = jnp.where(reached, x, 0.0)
    bracket = jnp.exp(-0.5 * xs * xs) / np.sqrt(2.0 * np.pi) + xs * special.ndtr(xs)
    second = jnp.where(reached, -np.log(2.0) + shift + np.log(r) + jnp.log(bracket), -jnp.inf)
    return -lam + log_quadratic(lam, atom, first, second)


def interpolate(t, lam, r: float, coef, grid: TableGrid):
    """The table's bicubic interpolant of ``log p`` (``_emccd_table._interpolate``) at
    ``lam > 0``, and where the point is on a grid.

    The cell index is held constant under differentiation, so the derivative by lam is the
    interpolant's own (the NumPy table's score); off the grids the cell is clamped and the
    value is not meaningful (the caller masks it).
    """
    root = jnp.sqrt(lam)
    eta = t / jnp.sqrt(jnp.sqrt(t * t + r * r)) - root
    row = (jnp.log(lam) - grid.xi0) / grid.xi_step
    near = jnp.abs(t) < grid.near * r
    col = jnp.where(near, (t / r - grid.tau0) / grid.tau_step, (eta - grid.eta0) / grid.eta_step)
    columns = jnp.where(near, grid.n_tau - 1, grid.n_eta - 1)
    first = jnp.where(near, grid.near_offset, 0)
    on = (row >= 0) & (row < grid.n_xi - 1) & (col >= 0) & (col < columns) & (t > -grid.near * r)
    i = jnp.clip(jnp.floor(jax.lax.stop_gradient(row)), 0, grid.n_xi - 2)
    j = jnp.clip(jnp.floor(jax.lax.stop_gradient(col)), 0, columns - 1)
    a = jnp.where(on, row - i, 0.0)
    s = jnp.where(on, col - j, 0.0)
    cell = first + i.astype(jnp.int64) * columns + j.astype(jnp.int64)
    c = jnp.take(coef, cell, axis=0, mode="clip")
    q0 = c[..., 0] + s * (c[..., 1] + s * (c[..., 2] + s * c[..., 3]))
    q1 = c[..., 4] + s * (c[..., 5] + s * (c[..., 6] + s * c[..., 7]))
    q2 = c[..., 8] + s * (c[..., 9] + s * (c[..., 10] + s * c[..., 11]))
    q3 = c[..., 12] + s * (c[..., 13] + s * (c[..., 14] + s * c[..., 15]))
    return q0 + a * (q1 + a * (q2 + a * q3)) - eta * eta, on


def log_table(t, x, lam, r: float, coef, grid: TableGrid):
    """The ``table`` tier with readout ``r`` in gain units (``_emccd_table.log_table``).

    On the grids, the interpolant; ``0 < lam < lam_min`` with ``lam (|t| + r)`` within reach,
    the small-lam expansion; ``lam == 0``, the readout alone; elsewhere (off the grids, where
    the NumPy tier integrates the exact law by quadrature) the ``high-gain`` closed form with
    readout.

    Points off the grids are rare (log p below about -50, or no background), and their closed
    forms (Bessel and normal-tail functions) cost many times the interpolant. On a CPU they are
    evaluated only at those points: up to ``SPARSE_SHARE`` of an array's points are gathered,
    computed and scattered back; an array with more of them computes every branch at every
    point (``jax.lax.cond``: one branch runs); the pixel law then costs a quarter of computing
    every branch everywhere (measured, 2 cores). On a GPU every branch is computed at every
    point (``jnp.where``): there the gather and scatter cost more than they save (measured on
    an H100: ``benchmarks/README.md``). The numbers are the same either way.
    """
    table, on = interpolate(t, jnp.where(lam >= grid.lam_min, lam, 1.0), r, coef, grid)
    on = on & (lam >= grid.lam_min)
    if t.size < SPARSE_MIN or jax.default_backend() != "cpu":
        return jnp.where(on, table, _off_grid(t, x, lam, r, grid))
    budget = max(SPARSE_MIN, int(t.size * SPARSE_SHARE))
    flat = [a.reshape(-1) for a in jnp.broadcast_arrays(t, x, lam, table)]
    off = ~on.reshape(-1)

    def sparse():
        index = jnp.nonzero(off, size=budget, fill_value=0)[0]
        fixed = _off_grid(flat[0][index], flat[1][index], flat[2][index], r, grid)
        chosen = jnp.where(off[index], fixed, flat[3][index])
        return flat[3].at[index].set(chosen).reshape(table.shape)

    def dense():
        return jnp.where(on, table, _off_grid(t, x, lam, r, grid))

    return jax.lax.cond(jnp.sum(off) <= budget, sparse, dense)


SPARSE_MIN = 4096  # arrays of fewer points compute every branch everywhere
SPARSE_SHARE = 1 / 64  # the share of an array's points the sparse path evaluates off the grids


def _off_grid(t, x, lam, r: float, grid: TableGrid):
    """``log_table`` at points off the grids: the small-lam expansion, the readout alone at
    ``lam == 0``, else the ``high-gain`` closed form with readout."""
    small = (lam > 0) & (lam < grid.lam_min) & (lam * (jnp.abs(t) + r) <= grid.small_lam_reach)
    far = (lam > 0) & ~small
    tiny = log_small_lam(t, jnp.where(small, lam, grid.lam_min), r)
    fallback = log_high_gain_readout(t, x, jnp.where(far, lam, 1.0), r)
    zero = -lam + log_normal_pdf(t, r)
    return jnp.where(small, tiny, jnp.where(far, fallback, zero))


def fisher_spline(lam, r: float, knots, coef, lo: float, hi: float):
    """The exact-law EMCCD Fisher information (``_emccd_fisher.fisher_information``) from the
    camera's spline of ``log(lam I)`` on ``log10 lam`` in ``[lo, hi]`` (the first and last
    ``knots``), the Gaussian limit above; ``inf`` at ``lam == 0`` and NaN for
    ``0 < lam < 10**lo`` (below the table, where the NumPy camera integrates the law by
    quadrature)."""
    last = knots.shape[0] - 2
    step = (hi - lo) / (last + 1)
    positive = lam > 0
    safe = jnp.where(positive, lam, 1.0)
    on = (safe >= 10.0**lo) & (safe <= 10.0**hi)
    # log10 of the grid's end values may round one ulp past the end knots: keep them on
    x = jnp.clip(jnp.log10(safe), lo, hi)
    i = jnp.clip(jnp.floor((x - lo) / step), 0, last).astype(jnp.int64)
    i = jnp.where(x < knots[i], i - 1, jnp.where((i < last) & (x >= knots[i + 1]), i + 1, i))
    i = jnp.clip(i, 0, last)
    d = x - knots[i]
    value = jnp.exp(((coef[0, i] * d + coef[1, i]) * d + coef[2, i]) * d + coef[3, i]) / safe
    v = 2.0 * safe + r * r
    gaussian = 1.0 / v + 2.0 / (v * v)
    out = jnp.where(on, value, jnp.where(safe > 10.0**hi, gaussian, jnp.nan))
    return jnp.where(positive, out, jnp.inf)
