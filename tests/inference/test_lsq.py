"""The paper's least squares for a stack at once: the minimum of the sum of squares, and
scipy's trust region where the stack stalls."""

import numpy as np
import pytest
from scipy import optimize

from bayespsf import Model, load_scene, simulate
from bayespsf.inference import fit_lsq, start_values
from bayespsf.inference import lsq as lsq_module
from bayespsf.inference.lsq import (
    LOWEST_WIDTH,
    STOPPED,
    _lsq_one,
    gauss2d,
    lsq_to_params,
    params_to_lsq,
)
from bayespsf.psf import PARAMETER_NAMES


@pytest.fixture(scope="module", params=["emccd-typical", "paper-fig3"])
def stack(request):
    scene = load_scene(request.param)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 60, seed=2)
    return counts, model


def test_the_stack_finds_the_minimum_of_the_sum_of_squares(stack):
    # at the minimum the gradient J^T r vanishes: each component, scaled by its column's norm
    # and the residual's, is below 1e-6 (a first-order stationarity check, independent of the
    # optimiser); scipy at tolerances of 1e-15 reaches the same point within 1e-5 of each
    # value (positions and b: of max(|value|, 1)); measured <= 5e-6
    counts, model = stack
    fits = fit_lsq(counts, model)
    assert (fits["message"] == STOPPED).all() and fits["converged"].all()
    photons = model.to_photons(counts)
    theta = params_to_lsq(fits[list(PARAMETER_NAMES)].to_numpy(float), model.pixel_size)
    lower = [-np.inf] * 3 + [LOWEST_WIDTH * model.pixel_size] * 2 + [-np.inf]
    for image, th in zip(photons[:20], theta[:20], strict=True):
        values, jac = gauss2d(th, model)
        residual, j = (values - image).ravel(), jac.reshape(6, -1)
        scaled = np.abs(j @ residual) / (np.linalg.norm(j, axis=1) * np.linalg.norm(residual))
        assert scaled.max() < 1e-6

        def residuals(t, y=image):
            return (gauss2d(t, model)[0] - y).ravel()

        def jacobian(t):
            return gauss2d(t, model)[1].reshape(6, -1).T

        exact = optimize.least_squares(
            residuals, th * 1.001, jac=jacobian, bounds=(lower, np.inf), method="trf",
            x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15,
        ).x  # fmt: skip
        np.testing.assert_allclose(th, exact, rtol=1e-5, atol=1e-5)


def test_where_the_stack_stalls_scipy_fits_the_roi(stack, monkeypatch):
    # with one step allowed no ROI stops in the stack: every one is scipy's fit, as it was
    # before the stack, with scipy's message
    counts, model = stack
    monkeypatch.setattr(lsq_module, "MAX_STEPS", 1)
    fits = fit_lsq(counts[:5], model)
    photons = model.to_photons(counts[:5])
    for k, (image, start) in enumerate(zip(photons, start_values(photons, model), strict=True)):
        res = _lsq_one(image, start, model)
        expected = lsq_to_params(res.x, model.pixel_size)
        assert np.array_equal(fits.loc[k, list(PARAMETER_NAMES)].to_numpy(float), expected)
        assert fits.loc[k, "message"] == res.message != STOPPED


def test_rois_without_a_spot_leave_the_others_alone():
    # ROIs of background alone (one photon in the spot): the sum of squares is flat in the
    # positions, steps are refused or singular and some stall (scipy fits those); no warning,
    # and the spots' estimates are those they get alone (to 1e-12: the batched sums may round
    # differently with the stack's size, ~1e-15 measured)
    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 3, seed=5)
    dark, _ = simulate(scene.replace(emitter={"photons": 1.0}), 6, seed=3)
    together = fit_lsq(np.concatenate([counts, dark]), model)
    alone = fit_lsq(counts, model)
    np.testing.assert_allclose(
        together.loc[:2, list(PARAMETER_NAMES)].to_numpy(float),
        alone[list(PARAMETER_NAMES)].to_numpy(float),
        rtol=1e-12,
    )
    assert (together.loc[3:, "message"] != STOPPED).any()  # stalled in the stack: scipy's
    assert not together.loc[3:, "converged"].all()  # widths that ran away beyond the ROI


def test_params_to_lsq_inverts_lsq_to_params():
    params = np.array([[3.0, -7.0, 131.0, 127.0, 1000.0, 10.0], [0.0, 0.0, 90.0, 150.0, 50.0, 0.5]])
    np.testing.assert_allclose(lsq_to_params(params_to_lsq(params, 100.0), 100.0), params)
