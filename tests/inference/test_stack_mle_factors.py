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
    if case == "sampled":
        scene, model = _sampled()
    elif case == "incident":
        scene, model = _incident_photons()
    else:
        scene = load_scene(case)
        model = Model.from_scene(scene)
    counts, truth = simulate(scene, 5, seed=3)
    p = truth[NAMES].to_numpy() * [1.0, 1.0, 1.1, 0.9, 1.2, 1.0] + [7.0, -5.0, 0, 0, 0, 0.5]
    lam, jac = model.expected_and_jacobian(p)
    got_lam, x, y = solver._expected_and_factors(model, p)
    np.testing.assert_array_equal(got_lam, lam)  # the same arithmetic: bit for bit
    score = model.camera._score(counts, lam)
    fisher = model.camera._fisher_information(lam)
    grad, metric = solver._reduce(model, p, x, y, score, fisher)
    want_grad, want_metric = solver._contract(jac, score), solver._information(jac, fisher)
    grad_scale = solver._contract(np.abs(jac), np.abs(score))
    assert np.all(np.abs(grad - want_grad) <= 1e-12 * grad_scale)
    diagonal = np.sqrt(np.einsum("nkk->nk", want_metric))
    scale = diagonal[:, :, None] * diagonal[:, None, :]
    assert np.all(np.abs(metric - want_metric) <= 1e-12 * scale)
    assert np.all(metric == np.swapaxes(metric, 1, 2))
