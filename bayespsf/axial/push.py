"""z from the widths' posterior pushed through the calibration (issue 16, item 3, the cheap way).

Each posterior draw of ``(s_x, s_y)`` is mapped to the z whose calibrated widths are nearest
in the metric of the widths' covariance ``S`` (generalised least squares,
``r' S^-1 r`` with ``r = s - w(z)``; by default ``S`` is the draws' own covariance): a grid over
``z_range`` finds the nearest grid point and Gauss-Newton steps refine it. Near the curve the
z draws then spread as the delta method says, ``1 / sqrt(g' S^-1 g)`` with ``g = dw/dz``, which
is z's Cramér-Rao bound when ``S`` is the widths' (``bayespsf.axial.bounds``). It is a
projection, not z's posterior under a model of z: the widths' posterior also spreads off the
curve, and ``distance`` says how far.

With the symmetric curve (``Defocus.symmetric``) the widths cannot tell z from -z. Each draw
then gets a sign at random: under a prior symmetric in z the posterior is exactly symmetric,
so both modes are reported, never one by chance. ``near`` gives each draw's distance from the
curve (nm), so that draws far off the calibration (a width pair the curve never makes) can be
seen (in units of the widths' SD along ``S``).
"""

from __future__ import annotations

import numpy as np

from bayespsf.axial.defocus import Defocus
from bayespsf.errors import BayespsfInputError

GRID_STEP = 2.0  # nm
NEWTON_STEPS = 8


def nearest_z(defocus: Defocus, s_x, s_y, z_range=(-800.0, 800.0), covariance=None):
    """Per width pair (n,), the z in ``z_range`` (nm) whose calibrated widths are nearest in
    the metric ``covariance^-1`` (2 x 2; default the identity, distances in nm), and that
    distance: ``(z, distance)``."""
    s_x, s_y = np.broadcast_arrays(np.asarray(s_x, float), np.asarray(s_y, float))
    low, high = map(float, z_range)
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise BayespsfInputError(f"z_range must be two finite numbers, low < high; got {z_range}")
    metric = np.eye(2) if covariance is None else _metric(covariance)

    def norm(rx, ry):
        return metric[0, 0] * rx * rx + 2 * metric[0, 1] * rx * ry + metric[1, 1] * ry * ry

    grid = np.arange(low, high + GRID_STEP, GRID_STEP)
    wx, wy = defocus.widths(grid)
    z = grid[np.argmin(norm(s_x[..., None] - wx, s_y[..., None] - wy), axis=-1)]
    for _ in range(NEWTON_STEPS):  # Gauss-Newton on f(z) = r' M r / 2, r = s - w(z)
        (wx, wy), (gx, gy) = defocus.widths(z), defocus.slopes(z)
        mr_x = metric[0, 0] * (s_x - wx) + metric[0, 1] * (s_y - wy)
        mr_y = metric[1, 0] * (s_x - wx) + metric[1, 1] * (s_y - wy)
        gradient = -(gx * mr_x + gy * mr_y)
        curvature = norm(gx, gy)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(curvature > 0, -gradient / curvature, 0.0)
        z = np.clip(z + np.clip(step, -GRID_STEP, GRID_STEP), low, high)
    wx, wy = defocus.widths(z)
    return z, np.sqrt(norm(s_x - wx, s_y - wy))


def _metric(covariance) -> np.ndarray:
    covariance = np.asarray(covariance, dtype=np.float64)
    if covariance.shape != (2, 2) or not np.all(np.isfinite(covariance)):
        raise BayespsfInputError(f"covariance must be a finite 2 x 2 matrix, got {covariance!r}")
    try:
        np.linalg.cholesky(covariance)
    except np.linalg.LinAlgError:
        raise BayespsfInputError("covariance must be positive definite") from None
    return np.linalg.inv(covariance)


def is_symmetric(defocus: Defocus) -> bool:
    """Whether the curve gives the same widths at z and -z (both axes in focus at 0, no odd
    term, the same curve on both axes)."""
    return defocus.x == defocus.y and defocus.x.c == 0.0 and defocus.x.A == 0.0


def z_draws(defocus: Defocus, s_x, s_y, rng=None, z_range=(-800.0, 800.0),
            covariance=None) -> np.ndarray:  # fmt: skip
    """Draws of z from draws of the widths (module docstring), each at its nearest z in the
    metric of ``covariance`` (default: the draws' own covariance, or the identity where they
    do not spread in both widths); the symmetric curve's
    draws get a random sign (``rng``, a Generator or seed)."""
    s_x, s_y = np.asarray(s_x, float), np.asarray(s_y, float)
    if covariance is None:
        covariance = np.cov(np.stack([s_x.ravel(), s_y.ravel()])) if s_x.size > 2 else None
        if covariance is not None and not np.all(np.linalg.eigvalsh(covariance) > 0):
            covariance = None  # draws that do not spread in 2-D: any metric gives one answer
    if is_symmetric(defocus):
        reach = max(abs(z_range[0]), abs(z_range[1]))
        z, _ = nearest_z(defocus, s_x, s_y, (0.0, reach), covariance)
        sign = np.where(np.random.default_rng(rng).random(z.shape) < 0.5, -1.0, 1.0)
        return sign * z
    return nearest_z(defocus, s_x, s_y, z_range, covariance)[0]


__all__ = ["is_symmetric", "nearest_z", "z_draws"]
