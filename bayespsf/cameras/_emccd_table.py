"""The ``table`` tier: the exact EMCCD law precomputed once per camera, interpolated bicubically.

In gain units (``t = electrons / gain``, ``r = readout_sd / gain``) the law depends on
``(lam, r)`` only, so one table serves a camera. Two regular grids over ``xi = log lam``:

* the *near* grid, ``|t| < NEAR r``, in ``tau = t / r``: the readout peak at the offset and its
  crossover into the amplified part, which is sharp (a few readout SDs wide) and needs the
  resolution of ``tau``. It tabulates the full ``log p``.
* the *bulk* grid, ``t >= NEAR r``, in ``eta = v(t) - sqrt(lam)`` with the count coordinate
  ``v(t) = t (t^2 + r^2)^(-1/4)`` (sqrt-like, so the law's width in ``eta`` is ~1/sqrt(2) at any
  lam). It tabulates ``log J``, the readout-convolved amplified part; there the zero-electron
  atom is below ``exp(-40)`` of ``J`` for ``r <= R_MAX`` (``NEAR`` is chosen so), and is dropped.

What is interpolated is the smooth residual ``log p + eta**2`` (``log J + eta**2``): each cell
stores the 16 power-basis coefficients of a bicubic Hermite patch, with derivatives from cubic
splines along each axis. Interpolation costs one read of 16 contiguous numbers and ~40
arithmetic operations per pixel, with no special function, in a compiled (numba) loop. The
same pass can return the interpolant's exact derivative by lam (the score the MLE needs,
``log_and_score_table``), so a fit reads each pixel's patch once per iteration, and its second
derivative within the cell (the law's curvature in the Laplace's observed information).

Below LAM_MIN the law's second-order expansion in lam is used (``_emccd_law.log_small_lam``,
closed form; a spot without background has pixels there) where its neglected third-order term,
``(lam (|t| + r))**2 / 12`` relative, is below 1e-7 (``lam (|t| + r) <= SMALL_LAM_REACH``);
farther counts go to the quadrature. Points outside the grids (lam above LAM_MAX, counts more
than ETA_MAX above or below the bulk, counts more than NEAR readout SDs below the offset: all
with log p below about -50) and cameras with ``r`` outside ``[R_MIN, R_MAX]`` are computed by
the exact quadrature, so the tier is accurate everywhere and fast where data are. Below
``R_MIN`` the readout peak is so narrow that the bulk grid's lowest cells (counts within a few
``r`` of the offset) no longer resolve it: at ``r = 1e-3`` the interpolant is off by 8 in log p
at log p ~ -46, at ``r = 1e-12`` by 1e19 (measured). Spacings were chosen by
measurement against the exact tier; see benchmarks/README.md.
"""

from __future__ import annotations

import functools

import numba
import numpy as np
from scipy.interpolate import CubicSpline

from bayespsf.cameras import _emccd_law as law
from bayespsf.cameras import _table_cache

LAM_MIN, LAM_MAX = 1e-6, 1e5
XI_STEP = 0.05
ETA_MAX, ETA_STEP = 8.0, 0.05
NEAR, TAU_STEP = 12.0, 0.1
R_MIN, R_MAX = 0.01, 2.0  # readout/gain ratios the table serves (measured, benchmarks/README.md)
SMALL_LAM_REACH = 1e-3  # log_small_lam where lam (|t| + r) is below this
_HERMITE = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [-3, 3, -2, -1], [2, -2, 1, 1]], dtype=float)


def count_coordinate(t, r):
    """``v(t) = t (t^2 + r^2)^(-1/4)``: linear within ~r of zero, ``sign(t) sqrt|t|`` beyond."""
    return t / np.sqrt(np.sqrt(t * t + r * r))


def _t_from_v(v, r):
    v4 = v**4
    return np.sign(v) * np.sqrt(0.5 * (v4 + np.sqrt(v4 * v4 + 4.0 * v4 * r * r)))


def _patches(values: np.ndarray, xi: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Power-basis coefficients (cells, 16) of the bicubic Hermite interpolant of ``values``."""
    step1, step2 = xi[1] - xi[0], second[1] - second[0]
    d1 = CubicSpline(xi, values, axis=0)(xi, 1) * step1
    d2 = CubicSpline(second, values, axis=1)(second, 1) * step2
    d12 = CubicSpline(second, d1, axis=1)(second, 1) * step2

    def corners(a):
        top = np.stack([a[:-1, :-1], a[:-1, 1:]], axis=-1)
        bottom = np.stack([a[1:, :-1], a[1:, 1:]], axis=-1)
        return np.stack([top, bottom], axis=-2)

    hermite = np.block([[corners(values), corners(d2)], [corners(d1), corners(d12)]])
    return (_HERMITE @ hermite @ _HERMITE.T).reshape(-1, 16)


class Table:
    """Interpolated EMCCD log density for one readout/gain ratio ``R_MIN <= r <= R_MAX``."""

    def __init__(self, r: float):
        self.r = r
        self.xi = np.arange(np.log(LAM_MIN), np.log(LAM_MAX) + 0.5 * XI_STEP, XI_STEP)
        self.eta = np.arange(-ETA_MAX, ETA_MAX + 0.5 * ETA_STEP, ETA_STEP)
        self.tau = np.arange(-NEAR - 2.0, NEAR + 2.0 + 0.5 * TAU_STEP, TAU_STEP)
        cells = self.xi.size - 1
        self.near_offset = cells * (self.eta.size - 1)
        shape = (self.near_offset + cells * (self.tau.size - 1), 16)
        # built once per machine (seconds), then mapped from the on-disk cache: the processes
        # of a machine share one copy, and each reads only the cells its data touch
        name = f"emccd-table-{float(r).hex()}-{_SOURCE_DIGEST}"
        self.coef = _table_cache.load_or_compute(name, self._build, shape, mapped=True)
        self.nbytes = self.coef.nbytes

    def _build(self) -> np.ndarray:
        """The patches' coefficients, from the exact law on the two grids."""
        r = self.r
        lam = np.exp(self.xi)[:, None]
        root = np.sqrt(lam)
        t_bulk = _t_from_v(self.eta[None, :] + root, r)
        t_near = np.broadcast_to(self.tau[None, :] * r, (lam.size, self.tau.size))
        bulk = self._evaluate(law.log_convolved, t_bulk, lam)
        near = self._evaluate(law.log_exact, t_near, lam)
        bulk += (count_coordinate(t_bulk, r) - root) ** 2
        near += (count_coordinate(t_near, r) - root) ** 2
        return np.concatenate(
            [_patches(bulk, self.xi, self.eta), _patches(near, self.xi, self.tau)]
        )

    def _evaluate(self, log_density, t, lam):
        lam = np.broadcast_to(lam, t.shape)
        return log_density(t.ravel(), lam.ravel(), self.r).reshape(t.shape)

    def log_p(self, t: np.ndarray, lam: np.ndarray, score=None, curve=None):
        """``log p(t | lam)`` for 1-D ``t`` and ``lam > 0``: interpolated, exact outside.

        With ``score`` (an array like ``t``), also fills it with ``d log p / d lam`` of the
        interpolant, from the same patches in the same pass; NaN off the grids (where ``log p``
        is the exact quadrature); with ``curve`` as well, the second derivative (``_interpolate``).
        """
        out = np.empty(t.shape)
        misses = _interpolate(
            t,
            lam,
            np.log(lam),
            self.coef,
            self.xi[0],
            self.xi.size,
            self.eta[0],
            self.eta.size,
            self.tau[0],
            self.tau.size,
            self.near_offset,
            self.r,
            out,
            score,
            curve,
        )
        if misses:
            outside = np.isnan(out)
            out[outside] = law.log_exact(t[outside], lam[outside], self.r)
        return out


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def _interpolate(
    t,
    lam,
    log_lam,
    coef,
    xi0,
    n_xi,
    eta0,
    n_eta,
    tau0,
    n_tau,
    near_offset,
    r,
    out,
    score=None,
    curve=None,
):
    """Bicubic patch evaluation, one pixel at a time; NaN (and a count) for off-grid points.

    With ``score`` (an array like ``out``) also the interpolant's exact derivative by lam, from
    the same patch: with ``a``, ``s`` the cell coordinates of ``log lam`` and of the count
    (``tau``, or ``eta = v(t) - sqrt(lam)`` in the bulk), ``d/dlam = P_a / (lam XI_STEP) +
    (2 eta - P_s / ETA_STEP) / (2 sqrt(lam))`` in the bulk (``P_s`` term absent near the
    offset, where ``tau`` does not depend on lam). The patches are C1 across cells, so this is
    continuous; it is NaN where ``out`` is. With ``curve`` too, the second derivative by lam
    within the cell (the patches are C1, so it jumps across cells): the chain rule through
    ``a`` (``a' = 1 / (lam XI_STEP)``) and, in the bulk, ``s`` (``s' = -1 / (2 sqrt(lam)
    ETA_STEP)``), and ``-eta**2``'s ``-1 / (2 lam) - eta / (2 lam**1.5)``.

    A compiled loop: in NumPy the same arithmetic on 7 200 pixels is ~2.4x slower (16
    strided column passes; measured in benchmarks/README.md). The Horner chains are
    latency-bound, so fused multiply-adds (``fastmath={"contract"}``, which keeps inf, NaN
    and every other IEEE rule) and reciprocals taken once per pixel make the pass with the
    score 1.7x faster (41 to 24 ns per pixel on a 2-core x86_64; log p moves by < 5e-15).
    ``log_lam`` (``log(lam)``) comes from NumPy's vectorised loop: the C library's scalar
    ``log`` here costs 3 ns per pixel more (24 against 21). The count coordinate stays in the
    loop, where it costs 4 ns per pixel: a pass of its own costs 8 (its two square roots and
    division wait on the divider there, where here they overlap the rest).
    """
    misses = 0
    inv_xi = 1.0 / XI_STEP
    inv_eta = 1.0 / ETA_STEP
    inv_tau = 1.0 / TAU_STEP
    inv_r = 1.0 / r
    r2 = r * r
    for k in range(t.size):
        tk = t[k]
        lk = lam[k]
        root = np.sqrt(lk)
        eta = tk / np.sqrt(np.sqrt(tk * tk + r2)) - root
        row = (log_lam[k] - xi0) * inv_xi
        near = abs(tk) < NEAR * r
        if near:
            col = (tk * inv_r - tau0) * inv_tau
            columns = n_tau - 1
            first = near_offset
        else:
            col = (eta - eta0) * inv_eta
            columns = n_eta - 1
            first = 0
        if not (0.0 <= row < n_xi - 1 and 0.0 <= col < columns and tk > -NEAR * r):
            out[k] = np.nan
            if score is not None:
                score[k] = np.nan
            if curve is not None:
                curve[k] = np.nan
            misses += 1
            continue
        i = int(row)
        j = int(col)
        a = row - i
        s = col - j
        c = coef[first + i * columns + j]
        q0 = c[0] + s * (c[1] + s * (c[2] + s * c[3]))
        q1 = c[4] + s * (c[5] + s * (c[6] + s * c[7]))
        q2 = c[8] + s * (c[9] + s * (c[10] + s * c[11]))
        q3 = c[12] + s * (c[13] + s * (c[14] + s * c[15]))
        out[k] = q0 + a * (q1 + a * (q2 + a * q3)) - eta * eta
        if score is not None:
            inv_lam = 1.0 / lk
            d_row = (q1 + a * (2.0 * q2 + 3.0 * a * q3)) * (inv_lam * inv_xi)
            inv_root = root * inv_lam
            if near:
                score[k] = d_row + eta * inv_root
            else:
                d0 = c[1] + s * (2.0 * c[2] + 3.0 * s * c[3])
                d1 = c[5] + s * (2.0 * c[6] + 3.0 * s * c[7])
                d2 = c[9] + s * (2.0 * c[10] + 3.0 * s * c[11])
                d3 = c[13] + s * (2.0 * c[14] + 3.0 * s * c[15])
                d_col = d0 + a * (d1 + a * (d2 + a * d3))
                score[k] = d_row + (eta - (0.5 * inv_eta) * d_col) * inv_root
            if curve is not None:
                a1 = inv_lam * inv_xi  # da/dlam; d2a/dlam2 = -a1 / lam
                curve[k] = (
                    (2.0 * q2 + 6.0 * a * q3) * a1 * a1
                    - d_row * inv_lam
                    - 0.5 * inv_lam * (1.0 + eta * inv_root)
                )
                if not near:
                    s1 = -0.5 * inv_eta * inv_root  # ds/dlam; d2s/dlam2 = -s1 / (2 lam)
                    d_as = d1 + a * (2.0 * d2 + 3.0 * a * d3)
                    e0 = 2.0 * c[2] + 6.0 * s * c[3]
                    e1 = 2.0 * c[6] + 6.0 * s * c[7]
                    e2 = 2.0 * c[10] + 6.0 * s * c[11]
                    e3 = 2.0 * c[14] + 6.0 * s * c[15]
                    d_ss = e0 + a * (e1 + a * (e2 + a * e3))
                    curve[k] += (2.0 * d_as * a1 + d_ss * s1 - 0.5 * d_col * inv_lam) * s1
    return misses


_SOURCE_DIGEST = _table_cache.digest(law.__file__, __file__)


@functools.lru_cache(maxsize=16)
def table_for(r: float) -> Table:
    """The table for readout/gain ratio ``r``: read from the machine's on-disk cache
    (``_table_cache``), or built on the machine's first use (seconds) and stored there; kept in
    memory for the process."""
    return Table(r)


def table_arrays(r: float) -> dict:
    """The table of readout/gain ratio ``r`` (``R_MIN <= r <= R_MAX``) and its grids, as plain
    numbers and one array, for array backends that evaluate the same interpolant.

    Keys: ``coefficients`` (cells, 16), the patches' power-basis coefficients (``Table.coef``:
    the bulk grid's ``(n_xi - 1) (n_eta - 1)`` cells row by row, then the near grid's from
    ``near_offset``; entry ``4 m + n`` multiplies ``a**m s**n``, ``a`` and ``s`` the offsets in
    a cell along log lam and along the count coordinate); the grids' starts ``xi0`` (log lam),
    ``eta0``, ``tau0``, sizes ``n_xi``, ``n_eta``, ``n_tau`` and steps ``xi_step``,
    ``eta_step``, ``tau_step``; ``near_offset``; and the constants ``near`` (``NEAR``),
    ``eta_max``, ``lam_min``, ``lam_max`` and ``small_lam_reach`` of the module docstring.
    """
    table = table_for(float(r))
    return {
        "coefficients": table.coef,
        "xi0": float(table.xi[0]),
        "n_xi": int(table.xi.size),
        "xi_step": XI_STEP,
        "eta0": float(table.eta[0]),
        "n_eta": int(table.eta.size),
        "eta_step": ETA_STEP,
        "tau0": float(table.tau[0]),
        "n_tau": int(table.tau.size),
        "tau_step": TAU_STEP,
        "near_offset": int(table.near_offset),
        "near": NEAR,
        "eta_max": ETA_MAX,
        "lam_min": LAM_MIN,
        "lam_max": LAM_MAX,
        "small_lam_reach": SMALL_LAM_REACH,
    }


def log_table(t, lam, r):
    """Log density of the EMCCD law with readout ``r > 0`` (gain units), ``lam >= 0``."""
    return _log_table(t, lam, r, None)


def log_and_score_table(t, lam, r, curvature: bool = False):
    """``log_table`` and its derivative by lam where it interpolates (``R_MIN <= r <= R_MAX``,
    ``lam >= LAM_MIN``, the point on a grid): the patches' exact derivative, from the same
    compiled pass as the log density. The score is NaN elsewhere (quadrature, the small-lam
    expansion, the readout alone at ``lam == 0``), where the caller differentiates
    ``log_table`` numerically. With ``curvature``, also the second derivative by lam of the
    interpolant within its cell, from the same pass (NaN where the score is):
    ``(log p, score, curvature)``."""
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    score = np.full(t.shape, np.nan)
    curve = np.full(t.shape, np.nan) if curvature else None
    log_p = _log_table(t, lam, r, score, curve)
    return (log_p, score, curve) if curvature else (log_p, score)


def _log_table(t, lam, r, score, curve=None):
    """``log_table``, filling ``score`` and ``curve`` (arrays of the broadcast shape, or
    None) where the table interpolates."""
    if not R_MIN <= r <= R_MAX:
        return law.log_exact(t, lam, r)
    t, lam = np.broadcast_arrays(np.asarray(t, float), np.asarray(lam, float))
    shape = t.shape
    t, lam = np.ascontiguousarray(t).ravel(), np.ascontiguousarray(lam).ravel()
    flat = None if score is None else score.reshape(-1)  # views: filled in place
    flat_curve = None if curve is None else curve.reshape(-1)
    on_grid = lam >= LAM_MIN
    if on_grid.all():
        return table_for(float(r)).log_p(t, lam, flat, flat_curve).reshape(shape)
    out = -lam + law.log_normal_pdf(t, r)  # lam == 0: readout noise only
    part = None if score is None else np.empty(int(on_grid.sum()))
    part_curve = None if curve is None else np.empty(int(on_grid.sum()))
    out[on_grid] = table_for(float(r)).log_p(t[on_grid], lam[on_grid], part, part_curve)
    if score is not None:
        flat[on_grid] = part
    if curve is not None:
        flat_curve[on_grid] = part_curve
    # below the grid: closed form, not quadrature (a pixel far from a spot without background)
    below = (lam > 0) & ~on_grid
    tiny = below & (lam * (np.abs(t) + r) <= SMALL_LAM_REACH)
    out[tiny] = law.log_small_lam(t[tiny], lam[tiny], r)
    far = below & ~tiny
    if far.any():
        out[far] = law.log_exact(t[far], lam[far], r)
    return out.reshape(shape)
