"""Closed forms, pixel sums and Cramér–Rao bounds for the precision of spot width and position.

Equation labels are those of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) ("the
paper"). Units: nm for s0, a, positions and the returned errors; photons for N, sigma_b
(background SD) and b_mean (mean background); every function broadcasts over its arguments.

The paper's variance of a pixel in photons is Eq. photonuncerts,
``sigma_i^2 = 2 N_i + sigma_b^2 + <b>``: the EMCCD's excess-noise factor 2 on the signal,
and the background's own variance plus the excess noise of its photons.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from scipy import optimize

from bayespsf import psf
from bayespsf.psf import PARAMETER_NAMES

if TYPE_CHECKING:
    from bayespsf.model import Model
    from bayespsf.scene import Scene


def s_dagger(s0: ArrayLike, a: ArrayLike) -> np.ndarray | float:
    """Eq. tophat: the width measured through pixels of side ``a``, ``sqrt(s0^2 + a^2/12)``.

    Parameters
    ----------
    s0, a : array_like
        The spot's SD and the pixel side, nm.

    Returns
    -------
    ndarray or float
        ``s'`` in nm, the broadcast shape of the arguments.
    """
    return np.sqrt(np.asarray(s0, float) ** 2 + np.asarray(a, float) ** 2 / 12.0)


def delta_s_analytic(
    N: ArrayLike,
    s0x: ArrayLike,
    s0y: ArrayLike,
    a: ArrayLike,
    sigma_b: ArrayLike,
    b_mean: ArrayLike,
) -> np.ndarray | float:
    """Eq. sigma2dp3: the rms error of s_x (nm) of a 2-D spot.

    Parameters
    ----------
    N, s0x, s0y, a, sigma_b, b_mean : array_like
        Photons in the spot; its SDs and the pixel side (nm); the SD and mean ``<b>`` of the
        background (photons per pixel). They broadcast against each other.

    Returns
    -------
    ndarray or float
        ``Delta s_x,rms`` in nm, the broadcast shape of the arguments.

    See Also
    --------
    delta_s_numeric : Eq. pesum summed over the ROI's pixels.
    delta_s_1d : the 1-D form, Eq. 1DSDerror.
    crlb : the Cramér–Rao bound of a scene under its camera.

    Notes
    -----
    ``<ds_x^2> = s'x^2 / N + 16 pi s'x^3 s'y (sigma_b^2 + <b>) / (3 a^2 N^2)`` with
    ``s' = sqrt(s0^2 + a^2/12)`` (Eq. tophat): the photon-noise and background-noise limits
    of Eq. pesum joined, under the paper's variance per pixel (Eq. photonuncerts).

    Examples
    --------
    The paper's Fig. 3 spot (N = 500, s0 = 120 nm, a = 79 nm, sigma_b = 1, <b> = 4):

    >>> from bayespsf.theory import delta_s_analytic
    >>> round(float(delta_s_analytic(500, 120.0, 120.0, 79.0, 1.0, 4.0)), 2)
    6.46
    """
    N, a = np.asarray(N, float), np.asarray(a, float)
    sx, sy = s_dagger(s0x, a), s_dagger(s0y, a)
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    return np.sqrt(sx**2 / N + 16 * np.pi * sx**3 * sy * background / (3 * a**2 * N**2))


def delta_s_1d(
    N: ArrayLike, s0: ArrayLike, a: ArrayLike, sigma_b: ArrayLike, b_mean: ArrayLike
) -> np.ndarray | float:
    """Eq. 1DSDerror: the rms width error (nm) of a 1-D spot.

    Parameters
    ----------
    N, s0, a, sigma_b, b_mean : array_like
        Photons in the spot; its SD and the pixel side (nm); the SD and mean of the
        background (photons per pixel).

    Returns
    -------
    ndarray or float
        ``Delta s_rms`` in nm, the broadcast shape of the arguments.

    Notes
    -----
    ``<ds^2> = s'^2 / N + 8 sqrt(pi) s'^3 (sigma_b^2 + <b>) / (3 a N^2)``,
    ``s' = sqrt(s0^2 + a^2/12)``.
    """
    return _delta_s_1d(N, s_dagger(s0, a), a, sigma_b, b_mean)


def delta_s_1d_no_pixel(
    N: ArrayLike, s0: ArrayLike, a: ArrayLike, sigma_b: ArrayLike, b_mean: ArrayLike
) -> np.ndarray | float:
    """Eq. 1DSDerrorNoPixel: Eq. 1DSDerror with s0 in place of s' (no pixelation of the width).

    Parameters
    ----------
    N, s0, a, sigma_b, b_mean : array_like
        Photons in the spot; its SD and the pixel side (nm); the SD and mean of the
        background (photons per pixel).

    Returns
    -------
    ndarray or float
        ``Delta s_rms`` in nm.
    """
    return _delta_s_1d(N, np.asarray(s0, float), a, sigma_b, b_mean)


def _delta_s_1d(N, s, a, sigma_b, b_mean):
    N, a = np.asarray(N, float), np.asarray(a, float)
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    return np.sqrt(s**2 / N + 8 * np.sqrt(np.pi) * s**3 * background / (3 * a * N**2))


def delta_x_analytic(
    N: ArrayLike,
    s0x: ArrayLike,
    s0y: ArrayLike,
    a: ArrayLike,
    sigma_b: ArrayLike,
    b_mean: ArrayLike,
) -> np.ndarray | float:
    """Eq. centroiderror: the rms error of x0 (nm) of a 2-D spot.

    Parameters
    ----------
    N, s0x, s0y, a, sigma_b, b_mean : array_like
        As for ``delta_s_analytic``.

    Returns
    -------
    ndarray or float
        ``Delta x_rms`` in nm, the broadcast shape of the arguments.

    Notes
    -----
    ``<dx^2> = 2 s'x^2 / N + 8 pi s'x^3 s'y (sigma_b^2 + <b>) / (a^2 N^2)``, with
    ``s' = sqrt(s0^2 + a^2/12)`` (Eq. tophat).
    """
    N, a = np.asarray(N, float), np.asarray(a, float)
    sx, sy = s_dagger(s0x, a), s_dagger(s0y, a)
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    return np.sqrt(2 * sx**2 / N + 8 * np.pi * sx**3 * sy * background / (a**2 * N**2))


def _pesum(signal, derivative, sigma_b, b_mean):
    """Eq. pesum: ``1 / sum_i (N_i'^2 / sigma_i^2)`` with Eq. photonuncerts' sigma_i^2."""
    var = (
        2.0 * signal
        + np.asarray(sigma_b, float)[..., None] ** 2
        + np.asarray(b_mean, float)[..., None]
    )
    return 1.0 / np.sum(derivative**2 / var, axis=-1)


def delta_s_numeric(
    N: ArrayLike,
    s0x: ArrayLike,
    s0y: ArrayLike,
    a: ArrayLike,
    sigma_b: ArrayLike,
    b_mean: ArrayLike,
    roi: int = 15,
    x0: ArrayLike = 0.0,
    y0: ArrayLike = 0.0,
) -> np.ndarray | float:
    """Eq. pesum summed over the pixels of a ROI (the paper's "numerical integration").

    Parameters
    ----------
    N, s0x, s0y, a, sigma_b, b_mean : array_like
        As for ``delta_s_analytic``.
    roi : int, optional
        Odd ROI side in pixels (default 15).
    x0, y0 : array_like, optional
        The spot's centre, nm from the centre of the central pixel.

    Returns
    -------
    ndarray or float
        The rms error of s_x in nm, the broadcast shape of the arguments.

    See Also
    --------
    delta_s_analytic : the closed form, Eq. sigma2dp3.

    Notes
    -----
    ``N_i`` is the pixel-integrated expected photons of the spot and ``N_i'`` its derivative
    in s_x (analytic), ``sigma_i^2`` from Eq. photonuncerts. Unlike Eq. sigma2dp3 this keeps
    the intermediate regime and the exact pixel integrals; it is also the Cramér–Rao bound of
    s_x alone under the paper's Gaussian noise model.
    """
    N, s0x, s0y, a, sigma_b, b_mean, x0, y0 = np.broadcast_arrays(
        *(np.asarray(v, float) for v in (N, s0x, s0y, a, sigma_b, b_mean, x0, y0))
    )
    out = np.empty(N.shape)
    for index in np.ndindex(N.shape):  # the pixel grid differs with a: one sum per point
        params = [x0[index], y0[index], s0x[index], s0y[index], N[index], 0.0]
        mu, jac = psf.expected_counts_and_jacobian(params, roi, a[index])
        out[index] = _pesum(mu.ravel(), jac[2].ravel(), sigma_b[index], b_mean[index])
    return np.sqrt(out)


def delta_s_numeric_1d(
    N: ArrayLike,
    s0: ArrayLike,
    a: ArrayLike,
    sigma_b: ArrayLike,
    b_mean: ArrayLike,
    roi: int = 15,
    x0: ArrayLike = 0.0,
) -> np.ndarray | float:
    """Eq. pesum in one dimension: a pixel-integrated 1-D Gaussian of N photons over ``roi``
    pixels.

    Parameters
    ----------
    N, s0, a, sigma_b, b_mean : array_like
        Photons in the spot; its SD and the pixel side (nm); the SD and mean of the
        background (photons per pixel).
    roi : int, optional
        Odd number of pixels (default 15).
    x0 : array_like, optional
        The spot's centre, nm.

    Returns
    -------
    ndarray or float
        The rms error of s in nm. Its limits are Eqs. 1Dphotonnoise and 1Dbgnoise.
    """
    N, s0, a, sigma_b, b_mean, x0 = np.broadcast_arrays(
        *(np.asarray(v, float) for v in (N, s0, a, sigma_b, b_mean, x0))
    )
    out = np.empty(N.shape)
    for index in np.ndindex(N.shape):
        # the x-profile of a spot whose y-extent is one huge pixel is the 1-D problem
        params = [x0[index], 0.0, s0[index], 1e-3, N[index], 0.0]
        mu, jac = psf.expected_counts_and_jacobian(params, roi, a[index])
        mu1, d1 = mu.sum(axis=0), jac[2].sum(axis=0)
        out[index] = _pesum(mu1, d1, sigma_b[index], b_mean[index])
    return np.sqrt(out)


def optimal_pixel_ratio(
    N: ArrayLike, sigma_b: ArrayLike, b_mean: ArrayLike, quantity: str = "width"
) -> np.ndarray | float:
    """The a/s0 (s0x = s0y) that minimises the closed form, in closed form.

    Parameters
    ----------
    N, sigma_b, b_mean : array_like
        Photons in the spot; SD and mean of the background, photons per pixel.
    quantity : {"width", "centroid"}, optional
        Minimise the width's error (Eq. sigma2dp3) or the centroid's (Eq. centroiderror);
        another value raises ``ValueError``.

    Returns
    -------
    ndarray or float
        The optimal pixel side over the spot's SD (dimensionless).

    Notes
    -----
    Width (Eq. sigma2dp3): ``(a/s0)^4 = 144 / (9 N / (4 pi (sigma_b^2 + <b>)) + 1)``, the
    paper's expression. Centroid (Eq. centroiderror), by the same differentiation:
    ``(a/s0)^4 = 144 / (3 N / (pi (sigma_b^2 + <b>)) + 1)``. Neither depends on s0.
    """
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    N = np.asarray(N, float)
    if quantity == "width":
        return (144.0 / (9.0 * N / (4.0 * np.pi * background) + 1.0)) ** 0.25
    if quantity == "centroid":
        return (144.0 / (3.0 * N / (np.pi * background) + 1.0)) ** 0.25
    raise ValueError(f"quantity must be 'width' or 'centroid', got {quantity!r}")


def optimal_pixel_ratio_numeric(
    N: float, sigma_b: float, b_mean: float, quantity: str = "width"
) -> float:
    """Cross-check of ``optimal_pixel_ratio`` by bounded scalar minimisation (scalars).

    Parameters
    ----------
    N, sigma_b, b_mean : float
        As for ``optimal_pixel_ratio``.
    quantity : {"width", "centroid"}, optional
        The closed form to minimise over a/s0 in [0.05, 10].

    Returns
    -------
    float
        The minimising a/s0.
    """
    formula = {"width": delta_s_analytic, "centroid": delta_x_analytic}[quantity]
    result = optimize.minimize_scalar(
        lambda ratio: formula(N, 1.0, 1.0, ratio, sigma_b, b_mean),
        bounds=(0.05, 10.0),
        method="bounded",
        options={"xatol": 1e-10},
    )
    return float(result.x)


def axial_width(z: ArrayLike, s0: ArrayLike, depth: float = 400.0) -> np.ndarray:
    """The Discussion's ``s(z) = s0 sqrt(1 + z^2 / D^2)`` (D ~ 400 nm, the imaging depth).

    Parameters
    ----------
    z, s0 : array_like
        Axial position from focus and in-focus SD, nm.
    depth : float, optional
        D in nm (default 400).

    Returns
    -------
    ndarray
        The width in nm.
    """
    return np.asarray(s0, float) * np.sqrt(1.0 + (np.asarray(z, float) / depth) ** 2)


def delta_z(delta_s: ArrayLike, s0: ArrayLike, s_z: ArrayLike, depth: float = 400.0) -> np.ndarray:
    """Axial error from the width error (the Discussion, by error propagation).

    Parameters
    ----------
    delta_s : array_like
        rms error of the width, nm.
    s0 : array_like
        In-focus SD, nm.
    s_z : array_like
        The width at the emitter's z, nm (>= s0).
    depth : float, optional
        D in nm (default 400).

    Returns
    -------
    ndarray
        ``dz = D / (s0 sqrt(1 - s0^2 / s(z)^2)) ds`` in nm; infinite in focus (s(z) = s0).
        ``s_z < s0`` raises ``ValueError``.
    """
    s0, s_z = np.asarray(s0, float), np.asarray(s_z, float)
    if np.any(s_z < s0):
        raise ValueError("s_z must be >= s0 (the width grows away from focus)")
    with np.errstate(divide="ignore"):
        return depth / (s0 * np.sqrt(1.0 - (s0 / s_z) ** 2)) * np.asarray(delta_s, float)


def fisher_matrix(model: Model, params: ArrayLike, method: str = "exact") -> np.ndarray:
    """Fisher information matrix of the six parameters for one ROI.

    Parameters
    ----------
    model : Model
        The model: geometry, camera and pixel model.
    params : array_like, shape (..., 6)
        ``x0 y0 s_x s_y N b`` (nm; N and b in the model's ``photon_unit``).
    method : str, optional
        ``"exact"``, or a method of ``model.camera.fisher_methods`` (``"excess-noise"`` for
        EMCCD cameras), passed to the camera's ``fisher_information``; else ``ValueError``.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        The information matrix in the parameter order.

    Notes
    -----
    ``sum_pixels I(lam_i) J_i J_i^T`` with I the camera's per-pixel information about the
    expected photons and J the PSF Jacobian (Kay, Fundamentals of Statistical Signal
    Processing I, eq. 3.31).
    """
    mu, jac = model.expected_and_jacobian(np.asarray(params, float))
    camera = model.camera
    if method not in camera.fisher_methods:
        raise ValueError(
            f"{camera!r} has no Fisher method {method!r} "
            f"(it has {', '.join(camera.fisher_methods)})"
        )
    info = (
        camera.fisher_information(mu)
        if method == "exact"
        else (camera.fisher_information(mu, method=method))
    )
    return np.einsum("...ixy,...jxy,...xy->...ij", jac, jac, info)


def crlb(
    scene_or_model: Scene | Model,
    params: ArrayLike | None = None,
    method: str = "exact",
    free: str = "all",
) -> pd.Series:
    """sqrt of the Cramér–Rao bound of each parameter (nm, photons), as a Series.

    Parameters
    ----------
    scene_or_model : Scene or Model
        A Scene (the model is built from it) or a Model.
    params : array_like, shape (6,), optional
        The true parameters; default (a Scene only): its declared spot (``scene_params``: (x0,
        y0) if fixed, else the ROI centre; widths s0x, s0y; N; b the background law's mean).
    method : {"exact", "excess-noise"}, optional
        "exact": the camera's exact per-pixel information; "excess-noise": the EMCCD shortcut
        with F^2 = 2.
    free : str, optional
        "all": all six parameters estimated jointly (the bound an unbiased estimator of the full
        model meets); a parameter name such as "s_x": only it unknown, the rest known — Eq.
        pesum's situation — so the ratio of the two shows what the nuisance parameters cost.

    Returns
    -------
    pandas.Series
        Named ``crlb``, indexed by ``x0 y0 s_x s_y N b`` (or by ``free`` alone): the bound's
        square root in nm for positions and widths, in ``photon_unit`` for N and b.

    Raises
    ------
    ValueError
        If ``free`` is not ``"all"`` or a parameter name, or the camera has no ``method``.

    See Also
    --------
    fisher_matrix : the information matrix.
    delta_s_analytic : the paper's closed form for s_x.

    Examples
    --------
    >>> from bayespsf import load_scene
    >>> from bayespsf.theory import crlb
    >>> crlb(load_scene("paper-fig3")).round(2).to_dict()
    {'x0': 10.33, 'y0': 10.33, 's_x': 9.31, 's_y': 9.31, 'N': 40.5, 'b': 0.16}
    """
    from bayespsf.model import Model

    model = (
        scene_or_model if isinstance(scene_or_model, Model) else Model.from_scene(scene_or_model)
    )
    if params is None:
        params = scene_params(scene_or_model)
    fisher = fisher_matrix(model, params, method)
    if free == "all":
        bound = np.sqrt(np.diag(np.linalg.inv(fisher)))
        return pd.Series(bound, index=list(PARAMETER_NAMES), name="crlb")
    if free in PARAMETER_NAMES:
        k = PARAMETER_NAMES.index(free)
        return pd.Series([1.0 / np.sqrt(fisher[k, k])], index=[free], name="crlb")
    raise ValueError(f"free must be 'all' or one of {PARAMETER_NAMES}, got {free!r}")


def scene_params(scene: Scene) -> np.ndarray:
    """The declared spot of a scene as parameters ``x0 y0 s_x s_y N b`` (see ``crlb``).

    Parameters
    ----------
    scene : Scene

    Returns
    -------
    ndarray, shape (6,)
        nm for positions (0 unless the position is fixed) and widths; N and b (the background
        law's mean) in the scene's ``camera.photon_unit``.
    """
    from bayespsf.simulation import build_pipeline
    from bayespsf.simulation.pipeline import truth_photon_factor

    truth = build_pipeline(scene)[0]  # EmitterTruth: the declared values, without randomness
    unit = truth_photon_factor(scene)
    return np.array(
        [truth.x0, truth.y0, truth.s_x, truth.s_y, truth.photons * unit, truth.background * unit]
    )
