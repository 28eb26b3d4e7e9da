"""The stack engine of fit_mle (every ROI advancing together) gives the numbers of the
one-ROI reference path (scipy's L-BFGS-B) to the optimisers' tolerance."""

import numpy as np
import pytest

from bayespsf import PARAMETER_NAMES, Model, load_scene, simulate, theory
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import covariance, fit_mle, solver

NAMES = list(PARAMETER_NAMES)


@pytest.mark.parametrize("name", ["emccd-typical", "ideal", "paper-fig3", "scmos-typical"])
def test_stack_engine_equals_the_scipy_path(name):
    # 40 ROIs per scene (20 of sCMOS, whose scipy path sums the exact law: ~0.15 s a ROI): the
    # optimum agrees to 1e-3 of the CRLB in every parameter (both
    # optimisers stop within ~1e-10 of the maximum log-likelihood; the CRLB sets the scale that
    # matters), the log-likelihood to 1e-6, and the Laplace SDs to 1e-3 relative (the observed
    # information is differenced at optima that differ by that much; correlations to 1e-3)
    scene = load_scene(name)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 20 if name == "scmos-typical" else 40, seed=7)
    stack = fit_mle(counts, model)
    reference = fit_mle(counts, model, engine="scipy")
    assert stack["converged"].tolist() == reference["converged"].tolist()
    ok = stack["converged"].to_numpy()
    assert ok.mean() > 0.9
    bound = theory.crlb(scene).to_numpy()
    shift = np.abs(stack.loc[ok, NAMES].to_numpy() - reference.loc[ok, NAMES].to_numpy()) / bound
    assert shift.max() < 1e-3
    np.testing.assert_allclose(
        stack["log_likelihood"][ok], reference["log_likelihood"][ok], atol=1e-6, rtol=0
    )
    sds = [f"sd_{n}" for n in NAMES]
    np.testing.assert_allclose(stack.loc[ok, sds], reference.loc[ok, sds], rtol=1e-3)
    corr = covariance(stack[ok]) / np.einsum("ni,nj->nij", *[stack.loc[ok, sds].to_numpy()] * 2)
    corr_ref = covariance(reference[ok]) / np.einsum(
        "ni,nj->nij", *[reference.loc[ok, sds].to_numpy()] * 2
    )
    np.testing.assert_allclose(corr, corr_ref, atol=1e-3)


def test_a_maximum_on_the_boundary_b_0_converges_there():
    # a spot without background: the maximum lies at b = 0, where the gradient still points out
    # of the box; the projected iteration holds b there and converges like the reference
    scene = load_scene("ideal").replace(background={"kind": "none"}, emitter={"photons": 800.0})
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 10, seed=3)
    stack = fit_mle(counts, model, laplace=False)
    reference = fit_mle(counts, model, laplace=False, engine="scipy")
    assert (stack["b"] == 0).sum() >= 5
    np.testing.assert_allclose(stack["log_likelihood"], reference["log_likelihood"], atol=1e-6)
    assert stack["message"].str.contains("iteration limit").sum() == 0


def test_engine_is_checked_by_name():
    model = Model.from_scene(load_scene("ideal"))
    with pytest.raises(BayespsfInputError, match="engine must be one of stack, scipy"):
        fit_mle(np.ones((15, 15)), model, engine="lm")


def test_crlb_columns_are_the_bound_at_the_fit():
    # at the true parameters the stack engine's bound is theory.crlb's (another code path: the
    # scene's Fisher information); at the fits of bright spots it scatters about it by ~1%
    scene = load_scene("emccd-typical").replace(emitter={"photons": 5000.0})
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 100, seed=9)

    params = truth[NAMES].to_numpy()
    expected = np.array([theory.crlb(scene, params=p).to_numpy() for p in params[:5]])
    np.testing.assert_allclose(solver.crlb(model, params[:5]), expected, rtol=1e-6)
    fits = fit_mle(counts, model, laplace=False)
    bound = fits[[f"crlb_{n}" for n in NAMES]].to_numpy()
    np.testing.assert_allclose(bound.mean(axis=0), theory.crlb(scene).to_numpy(), rtol=0.02)


@pytest.mark.parametrize("name", ["emccd-typical", "ideal", "scmos-typical"])
def test_one_pass_evaluation_equals_the_separate_ones(name):
    # the iteration evaluates -log L, gradient and metric together at each trial
    # (camera.log_likelihood_and_score_unchecked); the numbers are those of the separate
    # functions, and the gradient and metric are NaN (not formed) where -log L is not finite

    scene = load_scene(name)
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, 6, seed=4)
    p = truth[NAMES].to_numpy()
    f, grad, metric = solver.evaluate(model, counts, p)
    np.testing.assert_allclose(f, solver._objective(model, counts, p), rtol=1e-15)
    want_grad, want_metric = solver._gradient_and_metric(model, counts, p)
    np.testing.assert_allclose(grad, want_grad, rtol=1e-12, atol=0)
    np.testing.assert_allclose(metric, want_metric, rtol=1e-12, atol=0)
    if name == "ideal":  # a pixel with counts but no expected photons: -log L = inf
        far = p.copy()
        far[0] = (1e4, 1e4, 50.0, 50.0, 1000.0, 0.0)  # every pixel's lam underflows to 0
        f, grad, metric = solver.evaluate(model, counts, far)
        assert f[0] == np.inf and np.isnan(grad[0]).all() and np.isnan(metric[0]).all()
        assert np.isfinite(f[1:]).all() and np.isfinite(grad[1:]).all()


def test_contractions_of_no_rois_are_empty():
    # a block whose every ROI has -log L = inf (outside a tier's support) forms its gradient
    # and metric from no ROI at all: empty results, not a reshape error
    from bayespsf.inference.solver import _contract, _information

    assert _contract(np.empty((0, 6, 15, 15)), np.empty((0, 15, 15))).shape == (0, 6)
    assert _information(np.empty((0, 6, 15, 15)), np.empty((0, 15, 15))).shape == (0, 6, 6)


def test_a_step_that_overflows_is_refused_not_raised():
    # a frame of a paper-movie molecule under a provisional camera (bayespsf calibrate): a
    # Levenberg-Marquardt step became NaN and the stack MLE raised "params must be finite",
    # ending a whole calibration run; such a step is now refused like a worse one
    from pathlib import Path

    from bayespsf.cameras import EMCCD

    roi = np.load(Path(__file__).parents[1] / "data" / "overflowing_step_roi.npy")
    model = Model(15, 79.0, EMCCD(10.85, 4.17215, 99.9942, 1.0, likelihood="table"))
    fits = fit_mle(roi[None].astype(float), model, laplace=False)
    assert np.isfinite(fits[NAMES].to_numpy()).all()
    assert fits["status"].iloc[0] in ("converged", "not converged")


def test_crlb_columns_only_when_asked():
    scene = load_scene("scmos-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 3, seed=1)
    with_bound, without = fit_mle(counts, model), fit_mle(counts, model, crlb=False)
    assert np.isfinite(with_bound["crlb_s_x"]).all() and without["crlb_s_x"].isna().all()
    np.testing.assert_array_equal(with_bound["s_x"], without["s_x"])


def test_the_poisson_tier_converges_on_emccd_counts():
    # the EMCCD's poisson tier scores counts as Poisson photons, whose information (1/lam) is
    # twice the camera's: steered by the camera's, each step overshot twofold and at N = 5 000
    # 192 of 200 fits cycled about their maximum to the iteration limit. With the tier's own
    # information every ROI it can score converges, at the maximum of its log-likelihood
    scene = load_scene("emccd-typical").replace(emitter={"photons": 5000.0})
    counts, _ = simulate(scene, 60, seed=4)
    model = Model.from_scene(scene, likelihood="poisson")
    fits = fit_mle(counts, model)
    scored = np.isfinite(fits["log_likelihood"])  # a count below the offset: -inf
    assert scored.sum() >= 45
    assert fits.loc[scored, "converged"].all(), fits["message"].value_counts()
    scipy = fit_mle(counts[scored.to_numpy()], model, engine="scipy")
    assert (fits.loc[scored, "log_likelihood"].to_numpy() >= scipy["log_likelihood"] - 1e-6).all()
