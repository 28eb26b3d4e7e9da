"""The stack engine's pixel sums from the spot's 1-D factors against the full Jacobian."""

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.inference import solver
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

NAMES = list(PARAMETER_NAMES)


def _incident_photons():
    scene = load_scene("emccd-typical")
    emccd = Model.from_scene(scene)
    return scene, Model(15, 100.0, emccd.camera, clock_induced_charge=0.02, quantum_efficiency=0.6)


def _case(case):
    """The scene and model of a test case: a shipped scene's, the sampled pixel model, or
    incident photons with CIC."""
    if case == "sampled":
        return _sampled()
    if case == "incident":
        return _incident_photons()
    scene = load_scene(case)
    return scene, Model.from_scene(scene)


def _sampled():
    scene = load_scene("ideal")
    base = Model.from_scene(scene)
    return scene, Model(base.roi, base.pixel_size, base.camera, pixel_model="sampled")


@pytest.mark.parametrize("case", ["emccd-typical", "scmos-typical", "sampled", "incident"])
def test_factor_sums_equal_the_full_jacobian_contractions(case):
    # _reduce forms J' score and J' diag(F) J from the separable factors without the
    # (n, 6, roi, roi) Jacobian; the reference is model.expected_and_jacobian's Jacobian
    # contracted by _contract / _information. Only the summation order differs, so the sums
    # agree to rounding: 1e-12 of each entry's scale (sum |J_k score| for the gradient,
    # sqrt(M_kk M_qq) for the metric; an off-diagonal entry that cancels to ~0 is judged
    # against that scale, not itself). Cases: two camera laws, the sampled pixel model, and
    # incident photons (a Jacobian scaled by the quantum efficiency) with CIC
    scene, model = _case(case)
    counts, truth = simulate(scene, 5, seed=3)
    p = truth[NAMES].to_numpy() * [1.0, 1.0, 1.1, 0.9, 1.2, 1.0] + [7.0, -5.0, 0, 0, 0, 0.5]
    lam, jac = model.expected_and_jacobian(p)
    got_lam, x, y = solver._expected_and_factors(model, p)
    np.testing.assert_array_equal(got_lam, lam)  # the same arithmetic: bit for bit
    score = model.camera.score_unchecked(counts, lam)
    fisher = model.camera.fisher_information_unchecked(lam)
    grad, metric = solver._reduce(model, p, x, y, score, fisher)
    want_grad, want_metric = solver._contract(jac, score), solver._information(jac, fisher)
    grad_scale = solver._contract(np.abs(jac), np.abs(score))
    assert np.all(np.abs(grad - want_grad) <= 1e-12 * grad_scale)
    diagonal = np.sqrt(np.einsum("nkk->nk", want_metric))
    scale = diagonal[:, :, None] * diagonal[:, None, :]
    assert np.all(np.abs(metric - want_metric) <= 1e-12 * scale)
    assert np.all(metric == np.swapaxes(metric, 1, 2))


@pytest.mark.parametrize("case", ["emccd-typical", "scmos-typical", "sampled", "incident"])
def test_observed_information_is_the_derivative_of_the_gradient(case):
    # the analytic Hessian (the law's curvature times J J' minus its score times the expected
    # count's second derivatives) against central differences of the analytic gradient with
    # steps of 1e-3 pixel and 1e-4 relative: both are within ~1e-7 of the exact Hessian (the
    # differences' O(h^2) and the law's curvature by a difference of its score), so 1e-5 of
    # each entry's scale sqrt(H_kk H_qq) holds with room and fails for a wrong term
    scene, model = _case(case)
    counts, truth = simulate(scene, 12, seed=7)
    counts = model.check_counts(counts)
    p = truth[NAMES].to_numpy(float)
    got = solver.observed_information(model, counts, p)
    steps = np.array([0.1, 0.1, 0.0, 0.0, 0.0, 0.0]) + 1e-4 * np.abs(p) * [0, 0, 1, 1, 1, 1]
    steps[:, 5] = np.maximum(steps[:, 5], 1e-4)
    want = np.empty_like(got)
    for k in range(6):
        up, down = p.copy(), p.copy()
        up[:, k] += steps[:, k]
        down[:, k] -= steps[:, k]
        want[:, k] = (solver.gradient(model, counts, up) - solver.gradient(model, counts, down)) / (
            2 * steps[:, k, None]
        )
    want = 0.5 * (want + np.swapaxes(want, 1, 2))
    diagonal = np.abs(np.diagonal(want, axis1=1, axis2=2))
    scale = np.sqrt(diagonal[:, :, None] * diagonal[:, None, :])
    assert np.all(np.abs(got - want) <= 1e-5 * scale)
