"""z from the widths' posterior pushed through the calibration: the cheap way to z.

Each posterior draw of ``(s_x, s_y)`` is mapped to the z whose calibrated widths are nearest
in the metric of the widths' covariance ``S`` (generalised least squares,
``r' S^-1 r`` with ``r = s - w(z)``; by default ``S`` is the draws' own covariance): a grid over
``z_range`` finds the nearest grid point and a golden-section search between its neighbours
refines it (Gauss-Newton steps, tried first, could end further from the optimum than they
started, up to 1.8 nm off the curve). Near the curve the z draws then spread as the
delta method says, ``1 / sqrt(g' S^-1 g)`` with ``g = dw/dz``, which is z's Cramér-Rao bound
when ``S`` is the widths' (``bayespsf.axial.bounds``). It is a projection, not z's posterior
under a model of z: the widths' posterior also spreads off the curve, and ``nearest_z``
returns that distance (in nm with the identity metric, in widths' SDs with ``S``).

Where both axes are even about one plane ``c`` (both in focus at ``c``, no odd term: the
paper's symmetric curve is one), the widths cannot tell ``c + d`` from ``c - d``. Each draw then
gets one of the two at random, among those inside ``z_range``: under a prior symmetric about
``c`` the posterior is exactly symmetric, so both modes are reported, never one by chance.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bayespsf._validate import as_generator, broadcast_pair, finite_array, scalar_in_range
from bayespsf.axial.bounds import precision
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

GRID_STEP = 2.0  # nm
BLOCK = 4096  # width pairs per grid search
GOLDEN_STEPS = 50  # shrink the bracket by 0.618^50 ~ 3e-11


def widths(s_x: ArrayLike, s_y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``s_x`` and ``s_y`` as finite arrays > 0 of one shape (broadcast), or a named error."""
    s_x = finite_array("s_x", s_x)
    s_y = finite_array("s_y", s_y)
    if np.any(s_x <= 0) or np.any(s_y <= 0):
        raise BayespsfInputError("s_x and s_y must be > 0 nm")
    return broadcast_pair("s_x", s_x, "s_y", s_y)


def check_z_range(z_range: tuple[float, float]) -> tuple[float, float]:
    """The support of z's uniform prior, checked.

    Parameters
    ----------
    z_range : (float, float)
        ``(low, high)`` in nm.

    Returns
    -------
    (float, float)
        ``(low, high)`` as floats, finite, with low < high.

    Raises
    ------
    BayespsfInputError
        Naming ``z_range``: not two numbers, not finite, or not low < high.
    """
    try:
        low, high = z_range
    except (TypeError, ValueError):
        raise BayespsfInputError(
            f"z_range must be two numbers (low, high), got {z_range!r}"
        ) from None
    low = scalar_in_range("z_range low", low, -np.inf)
    high = scalar_in_range("z_range high", high, -np.inf)
    if not low < high:
        raise BayespsfInputError(f"z_range must have low < high; got {z_range!r}")
    return low, high


def nearest_z(
    defocus: Defocus,
    s_x: ArrayLike,
    s_y: ArrayLike,
    z_range: tuple[float, float] = (-800.0, 800.0),
    covariance: ArrayLike | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per width pair, the z whose calibrated widths are nearest, and that distance.

    Parameters
    ----------
    defocus : Defocus
        The widths' curves.
    s_x, s_y : array_like
        Width pairs, nm (> 0; broadcast together).
    z_range : (float, float), default (-800.0, 800.0)
        The z searched, ``(low, high)`` nm.
    covariance : array_like, shape (2, 2), optional
        ``S``: the distance is measured in the metric ``S^-1`` (in the widths' SDs); default
        the identity (distances in nm).

    Returns
    -------
    z : numpy.ndarray
        The nearest z in ``z_range`` (nm), the widths' shape.
    distance : numpy.ndarray
        ``sqrt(r' S^-1 r)`` with ``r = s - w(z)`` at that z.

    Raises
    ------
    BayespsfInputError
        Widths that are not finite and > 0, a bad ``z_range``, or a ``covariance`` that is
        not a finite, positive definite 2 x 2 matrix.

    See Also
    --------
    z_draws : z of every posterior draw of the widths.

    Notes
    -----
    A grid ``GRID_STEP`` nm apart finds the nearest grid point; a golden-section search on
    its two neighbouring intervals refines it to 1e-9 of a grid step (module docstring).
    """
    s_x, s_y = widths(s_x, s_y)
    low, high = check_z_range(z_range)
    metric = np.eye(2) if covariance is None else precision(covariance)

    def distance2(z):
        wx, wy = defocus.widths(z)
        rx, ry = s_x - wx, s_y - wy
        return metric[0, 0] * rx * rx + 2 * metric[0, 1] * rx * ry + metric[1, 1] * ry * ry

    grid = np.linspace(low, high, int(np.ceil((high - low) / GRID_STEP)) + 1)
    wx, wy = defocus.widths(grid)
    flat_x, flat_y = s_x.ravel(), s_y.ravel()
    nearest = np.empty(flat_x.size, dtype=np.int64)
    for first in range(0, flat_x.size, BLOCK):  # memory: BLOCK x grid, not draws x grid
        part = slice(first, first + BLOCK)
        rx, ry = flat_x[part, None] - wx, flat_y[part, None] - wy
        on_grid = metric[0, 0] * rx * rx + 2 * metric[0, 1] * rx * ry + metric[1, 1] * ry * ry
        nearest[part] = np.argmin(on_grid, axis=-1)
    z = grid[nearest].reshape(s_x.shape)
    # golden-section search on the grid point's two neighbouring intervals (the distance is
    # unimodal there at this grid step), to 1e-9 of a grid step
    a, b = np.maximum(z - GRID_STEP, low), np.minimum(z + GRID_STEP, high)
    inner = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(GOLDEN_STEPS):
        left, right = b - inner * (b - a), a + inner * (b - a)
        lower = distance2(left) < distance2(right)
        a, b = np.where(lower, a, left), np.where(lower, right, b)
    z = 0.5 * (a + b)
    f = distance2(z)
    return z, np.sqrt(f)


def symmetry_plane(defocus: Defocus) -> float | None:
    """The plane ``c`` about which both axes' widths are even (both in focus at ``c``, no
    odd term ``A``), or None: there z = c + d and c - d give the same widths."""
    x, y = defocus.x.even_plane(), defocus.y.even_plane()
    return x if x is not None and x == y else None


def z_draws(
    defocus: Defocus,
    s_x: ArrayLike,
    s_y: ArrayLike,
    rng: np.random.Generator | int,
    z_range: tuple[float, float] = (-800.0, 800.0),
    covariance: ArrayLike | None = None,
) -> np.ndarray:
    """Draws of z from draws of the widths, each at its nearest z on the curves.

    Parameters
    ----------
    defocus : Defocus
        The widths' curves.
    s_x, s_y : array_like
        Posterior draws of the widths, nm (> 0).
    rng : numpy.random.Generator or int
        Picks one of two mirror values where the curves are even about a plane (a Generator
        or an integer seed).
    z_range : (float, float), default (-800.0, 800.0)
        The z searched, ``(low, high)`` nm.
    covariance : array_like, shape (2, 2), optional
        The metric's ``S``; default the draws' own covariance, or the identity where they do
        not spread in both widths.

    Returns
    -------
    numpy.ndarray
        One z per draw (nm), the widths' shape.

    Raises
    ------
    BayespsfInputError
        As ``nearest_z``.

    See Also
    --------
    nearest_z : the projection of one width pair.
    z_posterior : z's posterior under a model of z.
    symmetry_plane : the plane of a curve's mirror symmetry.

    Notes
    -----
    A projection, not z's posterior under a model of z (module docstring). Where the curve
    is even about a plane (``symmetry_plane``), each draw gets one of its two mirror values
    inside ``z_range`` at random: under a prior symmetric about the plane both modes are
    reported, never one by chance.
    """
    s_x, s_y = widths(s_x, s_y)
    low, high = check_z_range(z_range)
    if covariance is None and s_x.size > 2:
        covariance = np.cov(np.stack([s_x.ravel(), s_y.ravel()]))
        if not np.all(np.linalg.eigvalsh(covariance) > 0):
            covariance = None  # draws that do not spread in 2-D: any metric gives one answer
    c = symmetry_plane(defocus)
    if c is None or not low < c < high:
        return nearest_z(defocus, s_x, s_y, (low, high), covariance)[0]
    half, _ = nearest_z(defocus, s_x, s_y, (c, c + max(high - c, c - low)), covariance)
    d = half - c
    below_fits, above_fits = c - d >= low, c + d <= high
    pick_below = as_generator(rng).random(np.shape(d)) < 0.5
    below = np.where(below_fits & above_fits, pick_below, below_fits)
    return np.where(below, c - d, c + d)


__all__ = ["check_z_range", "nearest_z", "symmetry_plane", "z_draws"]
