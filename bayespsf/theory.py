"""Closed forms, pixel sums and Cramér–Rao bounds for the precision of spot width and position.

Equation labels are those of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) ("the
paper"). Units: nm for s0, a, positions and the returned errors; photons for N, sigma_b
(background SD) and b_mean (mean background); every function broadcasts over its arguments.

The paper's variance of a pixel in photons is Eq. photonuncerts,
``sigma_i^2 = 2 N_i + sigma_b^2 + <b>``: the EMCCD's excess-noise factor 2 on the signal,
and the background's own variance plus the excess noise of its photons.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import optimize

from bayespsf import psf
from bayespsf.psf import PARAMETER_NAMES


def s_dagger(s0, a):
    """Eq. tophat: the width measured through pixels of side ``a``, ``sqrt(s0^2 + a^2/12)``."""
    return np.sqrt(np.asarray(s0, float) ** 2 + np.asarray(a, float) ** 2 / 12.0)


def delta_s_analytic(N, s0x, s0y, a, sigma_b, b_mean):
    """Eq. sigma2dp3: the rms error of s_x (nm) of a 2-D spot,

    ``<ds_x^2> = s'x^2 / N + 16 pi s'x^3 s'y (sigma_b^2 + <b>) / (3 a^2 N^2)`` with
    ``s' = sqrt(s0^2 + a^2/12)`` (Eq. tophat).
    """
    N, a = np.asarray(N, float), np.asarray(a, float)
    sx, sy = s_dagger(s0x, a), s_dagger(s0y, a)
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    return np.sqrt(sx**2 / N + 16 * np.pi * sx**3 * sy * background / (3 * a**2 * N**2))


def delta_s_1d(N, s0, a, sigma_b, b_mean):
    """Eq. 1DSDerror: rms width error in 1-D,
    ``s'^2 / N + 8 sqrt(pi) s'^3 (sigma_b^2 + <b>) / (3 a N^2)``, ``s' = sqrt(s0^2 + a^2/12)``."""
    return _delta_s_1d(N, s_dagger(s0, a), a, sigma_b, b_mean)


def delta_s_1d_no_pixel(N, s0, a, sigma_b, b_mean):
    """Eq. 1DSDerrorNoPixel: Eq. 1DSDerror with s0 in place of s' (no pixelation of the width)."""
    return _delta_s_1d(N, np.asarray(s0, float), a, sigma_b, b_mean)


def _delta_s_1d(N, s, a, sigma_b, b_mean):
    N, a = np.asarray(N, float), np.asarray(a, float)
    background = np.asarray(sigma_b, float) ** 2 + np.asarray(b_mean, float)
    return np.sqrt(s**2 / N + 8 * np.sqrt(np.pi) * s**3 * background / (3 * a * N**2))


def delta_x_analytic(N, s0x, s0y, a, sigma_b, b_mean):
    """Eq. centroiderror: rms error of x0 (nm),
    ``2 s'x^2 / N + 8 pi s'x^3 s'y (sigma_b^2 + <b>) / (a^2 N^2)``."""
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


def delta_s_numeric(N, s0x, s0y, a, sigma_b, b_mean, roi: int = 15, x0=0.0, y0=0.0):
    """Eq. pesum summed over the pixels of a ROI (the paper's "numerical integration"):
    ``N_i`` the pixel-integrated expected photons of the spot and ``N_i'`` its derivative in
    s_x (analytic), ``sigma_i^2`` from Eq. photonuncerts. Returns the rms error of s_x (nm).

    Unlike Eq. sigma2dp3 this keeps the intermediate regime and the exact pixel integrals; it
    is also the Cramér–Rao bound of s_x alone under the paper's Gaussian noise model.
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


def delta_s_numeric_1d(N, s0, a, sigma_b, b_mean, roi: int = 15, x0=0.0):
    """Eq. pesum in one dimension (pixel-integrated 1-D Gaussian of N photons over ``roi``
    pixels); the rms error of s (nm). Its limits are Eqs. 1Dphotonnoise and 1Dbgnoise."""
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


def optimal_pixel_ratio(N, sigma_b, b_mean, quantity: str = "width"):
    """The a/s0 (s0x = s0y) that minimises the closed form, in closed form.

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


def optimal_pixel_ratio_numeric(N, sigma_b, b_mean, quantity: str = "width") -> float:
    """Cross-check of ``optimal_pixel_ratio`` by bounded scalar minimisation (scalars)."""
    formula = {"width": delta_s_analytic, "centroid": delta_x_analytic}[quantity]
    result = optimize.minimize_scalar(
        lambda ratio: formula(N, 1.0, 1.0, ratio, sigma_b, b_mean),
        bounds=(0.05, 10.0),
        method="bounded",
        options={"xatol": 1e-10},
    )
    return float(result.x)


def axial_width(z, s0, depth: float = 400.0):
    """The Discussion's ``s(z) = s0 sqrt(1 + z^2 / D^2)`` (D ~ 400 nm, the imaging depth)."""
    return np.asarray(s0, float) * np.sqrt(1.0 + (np.asarray(z, float) / depth) ** 2)


def delta_z(delta_s, s0, s_z, depth: float = 400.0):
    """Axial error from the width error (the Discussion, by error propagation):
    ``dz = D / (s0 sqrt(1 - s0^2 / s(z)^2)) ds``; infinite in focus (s(z) = s0)."""
    s0, s_z = np.asarray(s0, float), np.asarray(s_z, float)
    if np.any(s_z < s0):
        raise ValueError("s_z must be >= s0 (the width grows away from focus)")
    with np.errstate(divide="ignore"):
        return depth / (s0 * np.sqrt(1.0 - (s0 / s_z) ** 2)) * np.asarray(delta_s, float)


def fisher_matrix(model, params, method: str = "exact") -> np.ndarray:
    """Fisher information matrix ``(..., 6, 6)`` of one ROI:
    ``sum_pixels I(lam_i) J_i J_i^T`` with I the camera's per-pixel information about the
    expected photons and J the PSF Jacobian (Kay, Fundamentals of Statistical Signal
    Processing I, eq. 3.31). ``method`` ("exact" or "excess-noise") is passed to EMCCD cameras.
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


def crlb(scene_or_model, params=None, method: str = "exact", free: str = "all") -> pd.Series:
    """sqrt of the Cramér–Rao bound of each parameter (nm, photons), as a Series.

    Parameters
    ----------
    scene_or_model
        A Scene (the model is built from it) or a Model.
    params
        The true parameters; default: the scene's declared spot (position (x0, y0) if fixed,
        else the ROI centre; widths s0x, s0y; N; b the background law's mean).
    method
        "exact": the camera's exact per-pixel information; "excess-noise": the EMCCD shortcut
        with F^2 = 2.
    free
        "all": all six parameters estimated jointly (the bound an unbiased estimator of the full
        model meets); "s_x": only s_x unknown, the rest known — Eq. pesum's situation — so the
        ratio of the two shows what the nuisance parameters cost.
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


def scene_params(scene) -> np.ndarray:
    """The declared spot of a scene as parameters ``x0 y0 s_x s_y N b`` (see ``crlb``); N and b
    in the scene's ``camera.photon_unit``."""
    from bayespsf.simulator import build_pipeline, truth_photon_factor

    truth = build_pipeline(scene)[0]  # EmitterTruth: the declared values, without randomness
    unit = truth_photon_factor(scene)
    return np.array(
        [truth.x0, truth.y0, truth.s_x, truth.s_y, truth.photons * unit, truth.background * unit]
    )
