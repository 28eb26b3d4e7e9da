"""Pixel-integrated elliptical Gaussian spot: expected photons per pixel and its derivatives.

Conventions (DESIGN.md): positions and widths in nm; x runs along columns (last axis), y along
rows; (0, 0) is the centre of the ROI's central pixel, so pixel ``k`` of an odd ROI of size ``R``
has its centre at ``(k - (R - 1) / 2) * pixel_size``. Parameters always come in the order
``x0, y0, s_x, s_y, N, b`` (``PARAMETER_NAMES``): N is the spot's total photons on the
infinite plane and b the background photons per pixel.

The expected count of pixel (i, j) is ``N * Py[i] * Px[j] + b`` where ``Px[j]`` is the
probability that a photon of the 1-D Gaussian lands in column j: the spot is separable, so an
image is an outer product of two 1-D integrals. The sampled (non-integrated) Gaussian of the
paper's Eq. A3.1 is given for comparison (DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)).
"""

from __future__ import annotations

import math
from numbers import Real

import numba
import numpy as np
from numpy.typing import ArrayLike

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError

PARAMETER_NAMES: tuple[str, ...] = ("x0", "y0", "s_x", "s_y", "N", "b")

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def pixel_centres(roi: int, pixel_size: float) -> np.ndarray:
    """Centres of the ``roi`` pixels along one axis, the central pixel at 0.

    Parameters
    ----------
    roi : int
        Odd side length of the region of interest, in pixels.
    pixel_size : float
        Pixel side ``a`` in nm (object space), > 0.

    Returns
    -------
    ndarray, shape (roi,)
        ``(k - (roi - 1) / 2) * pixel_size`` in nm, for ``k = 0 .. roi - 1``.

    Raises
    ------
    BayespsfInputError
        If ``roi`` is not an odd positive integer or ``pixel_size`` not a finite number > 0.

    Examples
    --------
    >>> from bayespsf.psf import pixel_centres
    >>> pixel_centres(5, 100.0)
    array([-200., -100.,    0.,  100.,  200.])
    """
    return _centres(*check_geometry(roi, pixel_size))


def _centres(roi: int, a: float) -> np.ndarray:
    return (np.arange(roi) - (roi - 1) / 2.0) * a


def check_geometry(roi: int, pixel_size: float) -> tuple[int, float]:
    """Check a ROI's geometry and return it as ``(int, float)``.

    Parameters
    ----------
    roi : int
        Side length in pixels; must be an odd positive integer (the central pixel is the
        origin).
    pixel_size : float
        Pixel side in nm; a finite real number > 0.

    Returns
    -------
    roi : int
        ``roi`` as a Python int.
    pixel_size : float
        ``pixel_size`` as a Python float, in nm.

    Raises
    ------
    BayespsfInputError
        If either value is outside its domain (the message names it).
    """
    if isinstance(roi, bool) or not isinstance(roi, int | np.integer) or roi < 1 or roi % 2 == 0:
        raise BayespsfInputError(f"roi must be an odd positive integer, got {roi!r}")
    if isinstance(pixel_size, bool) or not isinstance(pixel_size, Real):
        raise BayespsfInputError(f"pixel_size must be a number in nm, got {pixel_size!r}")
    a = float(pixel_size)
    if not (np.isfinite(a) and a > 0):
        raise BayespsfInputError(f"pixel_size must be > 0 nm and finite, got {pixel_size!r}")
    return int(roi), a


def check_pixel_model(pixel_model: str) -> str:
    """Check that ``pixel_model`` is one of ``PIXEL_MODELS``.

    Parameters
    ----------
    pixel_model : str
        ``"integrated"`` (the spot integrated over each pixel) or ``"sampled"`` (the density
        at pixel centres times the pixel area, Eq. A3.1).

    Returns
    -------
    str
        ``pixel_model`` unchanged.

    Raises
    ------
    BayespsfInputError
        If it is not one of ``PIXEL_MODELS``.
    """
    if pixel_model not in PIXEL_MODELS:
        raise BayespsfInputError(
            f"pixel_model must be one of {', '.join(PIXEL_MODELS)}; got {pixel_model!r}"
        )
    return pixel_model


def _check_params(params) -> np.ndarray:
    p = finite_array("params", params)
    if p.ndim == 0 or p.shape[-1] != 6:
        raise BayespsfInputError(
            f"params must have shape (..., 6) in the order {', '.join(PARAMETER_NAMES)}; "
            f"got shape {p.shape}"
        )
    for k, name in ((2, "s_x"), (3, "s_y")):
        if np.any(p[..., k] <= 0):
            raise BayespsfInputError(f"params[..., {k}] ({name}) must be > 0 nm")
    for k, name in ((4, "N"), (5, "b")):
        if np.any(p[..., k] < 0):
            raise BayespsfInputError(f"params[..., {k}] ({name}) must be >= 0 photons")
    return p


@numba.njit(cache=True, nogil=True, inline="always")
def pixel_mass(near: float, far: float, near_tail: float, far_tail: float) -> float:
    """A pixel's share of a 1-D Gaussian from its standardised edges and the tails beyond them.

    Parameters
    ----------
    near, far : float
        The pixel's edges minus the centre, over the width, ``near < far``.
    near_tail, far_tail : float
        The upper tail beyond each, ``Q(|z|) = erfc(|z| / sqrt(2)) / 2``.

    Returns
    -------
    float
        The probability mass between the edges. A pixel wholly on one side of the centre is a
        difference of the tails on that side, which keeps full relative precision at any
        distance (a difference of ``erf`` values far from the centre is all cancellation).

    Notes
    -----
    A numba function (``inline="always"``), for compiled loops over pixels and draws.
    """
    if near >= 0.0:
        return near_tail - far_tail
    if far <= 0.0:
        return far_tail - near_tail
    return 1.0 - near_tail - far_tail


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def _integrated(centre, width, roi, a, out):
    """The integrated axis for flat ``centre`` and ``width`` (n,): ``out[d, 0]`` the mass in
    each of the ``roi`` pixels (``pixel_mass``) and, where ``out`` has three rows, its
    derivatives by the centre, ``(phi(near) - phi(far)) / w``, and by the width,
    ``(near phi(near) - far phi(far)) / w``. One ``erfc`` and one ``exp`` per edge (an edge is
    the far side of one pixel and the near side of the next), ~3x faster than the same in
    NumPy; contraction to fused multiply-adds is the only fast-math rule."""
    derivatives = out.shape[1] == 3
    for d in range(centre.shape[0]):
        c, inv_w = centre[d], 1.0 / width[d]
        near = (-0.5 * roi * a - c) * inv_w
        near_tail = 0.5 * math.erfc(abs(near) * _INV_SQRT2)
        near_phi = _INV_SQRT_2PI * math.exp(-0.5 * near * near)
        for j in range(roi):
            far = ((j + 1.0 - 0.5 * roi) * a - c) * inv_w
            far_tail = 0.5 * math.erfc(abs(far) * _INV_SQRT2)
            out[d, 0, j] = pixel_mass(near, far, near_tail, far_tail)
            if derivatives:
                far_phi = _INV_SQRT_2PI * math.exp(-0.5 * far * far)
                out[d, 1, j] = (near_phi - far_phi) * inv_w
                out[d, 2, j] = (near * near_phi - far * far_phi) * inv_w
                near_phi = far_phi
            near, near_tail = far, far_tail


def expected_counts(params: ArrayLike, roi: int, pixel_size: float) -> np.ndarray:
    """Expected photons per pixel of a pixel-integrated elliptical Gaussian plus background.

    Parameters
    ----------
    params : array_like, shape (..., 6)
        ``x0, y0, s_x, s_y, N, b`` in nm, nm, nm, nm, photons, photons per pixel. Leading
        dimensions (walkers, molecules) broadcast.
    roi : int
        Odd side length of the square region of interest, in pixels.
    pixel_size : float
        Pixel side ``a`` in nm (object space).

    Returns
    -------
    ndarray, shape (..., roi, roi)
        ``N * Py[i] * Px[j] + b`` in photons: rows are y, columns are x.

    Raises
    ------
    BayespsfInputError
        If ``params`` is not finite with last axis 6, a width is <= 0, N or b is < 0, or the
        geometry is invalid (``check_geometry``).

    See Also
    --------
    expected_counts_and_jacobian : the same counts and their derivatives.
    sampled_gaussian : the sampled (non-integrated) Gaussian of Eq. A3.1.
    pixel_centres : where the pixel centres lie.

    Notes
    -----
    ``Px[j]`` is the probability that a photon of the 1-D Gaussian of centre ``x0`` and SD
    ``s_x`` lands in column ``j``; pixels wholly on one side of the centre are computed as
    differences of upper-tail probabilities in log space, which keeps full relative precision
    far from the spot. The result is the integral of the paper's Eq. A3.1 over each pixel; its
    variance per axis tends to ``s0**2 + a**2 / 12`` (Eq. tophat).

    References
    ----------
    .. [1] M. C. DeSantis, S. H. DeCenzo, J.-L. Li and Y. M. Wang, "Precision analysis for
       standard deviation measurements of immobile single fluorescent molecule images",
       Opt. Express 18, 6563-6576 (2010).

    Examples
    --------
    >>> from bayespsf.psf import expected_counts
    >>> mu = expected_counts([0.0, 0.0, 120.0, 120.0, 1000.0, 2.0], roi=11, pixel_size=100.0)
    >>> mu.shape
    (11, 11)
    >>> round(float(mu.sum() - 2.0 * 11 * 11), 1)  # the spot's photons inside the ROI
    1000.0
    """
    roi, a = check_geometry(roi, pixel_size)
    return expected_counts_unchecked(_check_params(params), roi, a)


PIXEL_MODELS = ("integrated", "sampled")


def _axis(centre, width, roi: int, a: float, pixel_model: str, derivatives: bool):
    """One axis of the separable spot, ``(..., k, roi)``: the fraction of the spot's photons in
    each pixel and, with ``derivatives`` (``k = 3``), its derivatives by the centre and the
    width.

    ``integrated``: the 1-D Gaussian's probability mass in each pixel (``_integrated``).
    ``sampled``: its density at the pixel centre times ``a`` (the paper's Eq. A3.1), with
    ``d/dcentre = m z / w`` and ``d/dwidth = m (z**2 - 1) / w`` for ``z = (c - centre) / w``.
    """
    centre, width = np.broadcast_arrays(np.asarray(centre, float), np.asarray(width, float))
    if pixel_model == "integrated":
        out = np.empty((centre.size, 3 if derivatives else 1, roi))
        _integrated(centre.ravel(), width.ravel(), roi, float(a), out)
        return out.reshape(*centre.shape, *out.shape[1:])
    w = width[..., None]
    z = (_centres(roi, a) - centre[..., None]) / w
    mass = (a * _INV_SQRT_2PI) * np.exp(-0.5 * z * z) / w
    return np.stack((mass, mass * z / w, mass * (z * z - 1.0) / w) if derivatives else (mass,), -2)


def expected_counts_unchecked(
    p: np.ndarray, roi: int, a: float, pixel_model: str = "integrated"
) -> np.ndarray:
    """``expected_counts`` (or ``sampled_gaussian``) without input validation.

    For hot loops whose parameters are already known to be valid (inside the prior's
    support).

    Parameters
    ----------
    p : ndarray, shape (..., 6)
        ``x0, y0, s_x, s_y, N, b`` (nm, nm, nm, nm, photons, photons per pixel), finite, widths
        > 0; not checked.
    roi : int
        Odd ROI side in pixels; not checked.
    a : float
        Pixel side in nm; not checked.
    pixel_model : {"integrated", "sampled"}, optional
        ``"integrated"`` gives ``expected_counts``, ``"sampled"`` gives ``sampled_gaussian``.

    Returns
    -------
    ndarray, shape (..., roi, roi)
        Expected photons per pixel.

    See Also
    --------
    expected_counts : the checked version.
    """
    px = _axis(p[..., 0], p[..., 2], roi, a, pixel_model, False)[..., 0, :]
    py = _axis(p[..., 1], p[..., 3], roi, a, pixel_model, False)[..., 0, :]
    n = p[..., 4][..., None, None]
    b = p[..., 5][..., None, None]
    return n * py[..., :, None] * px[..., None, :] + b


def expected_counts_and_jacobian(
    params: ArrayLike, roi: int, pixel_size: float, pixel_model: str = "integrated"
) -> tuple[np.ndarray, np.ndarray]:
    """Expected counts and their analytic derivatives with respect to all six parameters.

    Parameters
    ----------
    params : array_like, shape (..., 6)
        ``x0, y0, s_x, s_y, N, b`` in nm, nm, nm, nm, photons, photons per pixel.
    roi : int
        Odd side length of the ROI, in pixels.
    pixel_size : float
        Pixel side ``a`` in nm.
    pixel_model : {"integrated", "sampled"}, optional
        ``"integrated"`` (default): of ``expected_counts``; ``"sampled"``: of
        ``sampled_gaussian``.

    Returns
    -------
    mu : ndarray, shape (..., roi, roi)
        Expected photons per pixel.
    jac : ndarray, shape (..., 6, roi, roi)
        ``jac[..., k, i, j] = d mu[..., i, j] / d params[..., k]`` in the parameter order.

    Raises
    ------
    BayespsfInputError
        For the inputs ``expected_counts`` refuses, or an unknown ``pixel_model``.

    See Also
    --------
    expected_counts : the counts alone.

    Notes
    -----
    With ``z`` the standardised pixel edges and ``phi`` the standard normal density,
    ``dPx/dx0 = -(phi(z_hi) - phi(z_lo)) / s_x`` and
    ``dPx/ds_x = -(z_hi phi(z_hi) - z_lo phi(z_lo)) / s_x`` (differentiating the erf
    differences under the integral of Eq. A3.1).
    """
    roi, a = check_geometry(roi, pixel_size)
    p = _check_params(params)
    check_pixel_model(pixel_model)
    px, dpx_dx0, dpx_ds = np.moveaxis(_axis(p[..., 0], p[..., 2], roi, a, pixel_model, True), -2, 0)
    py, dpy_dy0, dpy_ds = np.moveaxis(_axis(p[..., 1], p[..., 3], roi, a, pixel_model, True), -2, 0)
    n = p[..., 4][..., None, None]
    n_py, n_dpy, n_dpys = n * py[..., :, None], n * dpy_dy0[..., :, None], n * dpy_ds[..., :, None]
    px, dpx_dx0, dpx_ds = px[..., None, :], dpx_dx0[..., None, :], dpx_ds[..., None, :]
    jac = np.empty((*p.shape[:-1], 6, roi, roi))
    # each product written straight into its slice (no temporaries of the Jacobian's size)
    np.multiply(n_py, dpx_dx0, out=jac[..., 0, :, :])
    np.multiply(n_dpy, px, out=jac[..., 1, :, :])
    np.multiply(n_py, dpx_ds, out=jac[..., 2, :, :])
    np.multiply(n_dpys, px, out=jac[..., 3, :, :])
    np.multiply(py[..., :, None], px, out=jac[..., 4, :, :])
    jac[..., 5, :, :] = 1.0
    mu = n_py * px + p[..., 5][..., None, None]
    return mu, jac


def axis_factors(
    params: ArrayLike, roi: int, pixel_size: float, pixel_model: str = "integrated"
) -> tuple[np.ndarray, np.ndarray]:
    """The two 1-D factors of the separable spot and their derivatives, from which
    ``expected_counts_and_jacobian`` forms its outer products.

    Parameters
    ----------
    params : array_like, shape (..., 6)
        ``x0, y0, s_x, s_y, N, b`` in nm, nm, nm, nm, photons, photons per pixel.
    roi : int
        Odd side length of the ROI, in pixels.
    pixel_size : float
        Pixel side ``a`` in nm.
    pixel_model : {"integrated", "sampled"}, optional
        As for ``expected_counts_and_jacobian``.

    Returns
    -------
    x, y : ndarray, shape (..., 3, roi)
        Along x (columns) ``Px``, ``dPx/dx0``, ``dPx/ds_x``; along y (rows) ``Py``,
        ``dPy/dy0``, ``dPy/ds_y``. The expected counts are ``N Py[i] Px[j] + b``; the Jacobian
        rows by ``x0, y0, s_x, s_y, N, b`` are ``N Py dPx/dx0``, ``N dPy/dy0 Px``,
        ``N Py dPx/ds_x``, ``N dPy/ds_y Px``, ``Py Px`` and 1.

    Raises
    ------
    BayespsfInputError
        For the inputs ``expected_counts_and_jacobian`` refuses.

    See Also
    --------
    expected_counts_and_jacobian : the same numbers as full ``(..., roi, roi)`` images.
    """
    roi, a = check_geometry(roi, pixel_size)
    p = _check_params(params)
    check_pixel_model(pixel_model)
    x = axis_factor(p[..., 0], p[..., 2], roi, a, pixel_model)
    return x, axis_factor(p[..., 1], p[..., 3], roi, a, pixel_model)


def axis_factor(
    centre: np.ndarray, width: np.ndarray, roi: int, a: float, pixel_model: str = "integrated"
) -> np.ndarray:
    """One axis of ``axis_factors`` without input validation (for hot loops whose parameters
    are known to be valid): the fraction of the spot's photons in each pixel, its derivative
    by the centre and by the width, shape ``(..., 3, roi)``, for centres and widths (nm) of
    shape ``(...)``, an odd ``roi`` and pixel side ``a`` (nm)."""
    return _axis(centre, width, roi, a, pixel_model, True)


def axis_curvature(
    centre: np.ndarray, width: np.ndarray, roi: int, a: float, pixel_model: str = "integrated"
) -> np.ndarray:
    """The second derivatives of ``axis_factor``'s fractions, unvalidated: by the centre twice,
    by the centre and the width, and by the width twice, shape ``(..., 3, roi)``.

    Integrated, per pixel edge ``z`` (edge minus centre, over the width ``w``) and taken as the
    pixel's far edge's value minus its near edge's: ``-z phi(z) / w**2``,
    ``(1 - z**2) phi(z) / w**2`` and ``z (2 - z**2) phi(z) / w**2``. Sampled, with ``m`` the
    fraction and ``u`` the pixel centre's standardised position: ``m (u**2 - 1) / w**2``,
    ``m u (u**2 - 3) / w**2`` and ``m (u**4 - 5 u**2 + 2) / w**2``.
    """
    w2 = (width * width)[..., None]
    if pixel_model == "integrated":
        z = ((np.arange(roi + 1) - roi / 2.0) * a - centre[..., None]) / width[..., None]
        phi = _INV_SQRT_2PI * np.exp(-0.5 * z * z)
        edges = (-z * phi, (1.0 - z * z) * phi, z * (2.0 - z * z) * phi)
        return np.stack([(e[..., 1:] - e[..., :-1]) / w2 for e in edges], axis=-2)
    u = (_centres(roi, a) - centre[..., None]) / width[..., None]
    m = (a * _INV_SQRT_2PI) * np.exp(-0.5 * u * u) / width[..., None]
    u2 = u * u
    curvatures = (u2 - 1.0, u * (u2 - 3.0), u2 * u2 - 5.0 * u2 + 2.0)
    return np.stack([m * c / w2 for c in curvatures], axis=-2)


def sampled_gaussian(params: ArrayLike, roi: int, pixel_size: float) -> np.ndarray:
    """The paper's Eq. A3.1: the Gaussian density sampled at pixel centres times ``a**2``.

    Parameters
    ----------
    params : array_like, shape (..., 6)
        ``x0, y0, s_x, s_y, N, b`` in nm, nm, nm, nm, photons, photons per pixel.
    roi : int
        Odd side length of the ROI, in pixels.
    pixel_size : float
        Pixel side ``a`` in nm.

    Returns
    -------
    ndarray, shape (..., roi, roi)
        Expected photons per pixel: rows are y, columns are x.

    Raises
    ------
    BayespsfInputError
        For the inputs ``expected_counts`` refuses.

    See Also
    --------
    expected_counts : the pixel-integrated spot, as a camera records it.

    Notes
    -----
    ``N a**2 / (2 pi s_x s_y) exp(-(x - x0)**2 / (2 s_x**2) - (y - y0)**2 / (2 s_y**2)) + b``;
    the pixel model the closed forms of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)
    are derived from.
    """
    roi, a = check_geometry(roi, pixel_size)
    return expected_counts_unchecked(_check_params(params), roi, a, "sampled")
