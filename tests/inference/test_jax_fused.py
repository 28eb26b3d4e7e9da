"""The JAX backend's interpolated law (``jax_fused``) against the law itself, its check, the
programs' fallback to the law where the check fails, and the Gaussian round's sizes.

Tolerance, as for the NumPy scorer (``tests/inference/test_fused.py``): each pixel's
interpolant is checked against the law to ``fused.TOLERANCE`` (1e-6 in log p) at its check
points, and between them a degree-8 Chebyshev interpolant of a smooth function errs by the same
order, so a draw's sum over a 15 x 15 ROI is held to ``roi**2 * TOLERANCE`` (2.25e-4) and its
median to 1e-6. Measured on 100 emccd-typical ROIs x 500 draws: median 2e-8 (Laplace draws) and
4e-8 (Student-t), largest 2.7e-7 and 1.6e-6; 100 and 98 of the ROIs pass the check.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fused import laplace_draws  # the NumPy scorer's test cases

from bayespsf import load_scene, simulate
from bayespsf.inference import fit_mle, fused, jax_fused, jax_sampling
from bayespsf.inference.importance import MIN_BATCH
from bayespsf.inference.jax_model import JaxModel
from bayespsf.inference.settings import check_settings
from bayespsf.model import Model


def draws(scene_name: str, n_rois: int, n_draws: int, student: bool):
    """The NumPy scorer's test cases (Laplace or Student-t draws about each ROI's fit) as
    parameters, a point inside the prior in place of draws outside it (as the programs do)."""
    model, counts, z = laplace_draws(scene_name, n_rois, n_draws, student, seed=4)
    p = model.from_unconstrained(np.stack(z))
    inside = np.isfinite(model.log_prior(p.reshape(-1, 6))).reshape(n_rois, n_draws)
    p[~inside] = p[inside][0]
    return model, counts, p


@pytest.mark.parametrize(("scene_name", "student"), [("emccd-typical", True), ("ideal", False)])
def test_the_interpolated_law_is_the_law_within_its_check(scene_name, student):
    model, counts, p = draws(scene_name, 12, 150, student)
    jm = JaxModel.from_model(model)
    got, usable = jax.jit(lambda c, q: jax_fused.log_likelihood(jm, c, q))(counts, p)
    want = jm.log_likelihood(jnp.asarray(counts)[:, None], p)
    usable = np.asarray(usable)
    assert usable.sum() >= 10  # the check passes on nearly every ROI (measured: all 12)
    error = np.abs(np.asarray(got - want))[usable]
    assert error.max() <= model.roi**2 * fused.TOLERANCE
    assert np.median(error) <= 1e-6


def test_the_check_refuses_a_range_it_cannot_interpolate():
    # draws from N = 10 to 10**6 photons: each pixel's law over a range of ~300 in sqrt(lam)
    # is far from a degree-8 polynomial, so the check must flag the ROI
    model, counts, p = draws("ideal", 2, 64, False)
    p[:, :, 4] = np.geomspace(10, 1e6, 64)
    jm = JaxModel.from_model(model)
    _, usable = jax.jit(lambda c, q: jax_fused.log_likelihood(jm, c, q))(counts, p)
    assert not np.asarray(usable).any()


def test_rois_that_fail_the_check_are_scored_by_the_law_itself(monkeypatch):
    # with a tolerance no interpolant meets, every ROI's programs run again with the law
    # itself: the same draws (from each ROI's key), so the posteriors differ from the
    # interpolated run's only by the interpolation (weights within roi**2 * 1e-6 in log).
    # One program (the Student-t round) suffices: the fallback is the same for each.
    scene = load_scene("ideal")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 6, seed=8)
    fits = fit_mle(counts, model, backend="jax")
    settings = check_settings(method="importance", ess=100)
    seeds = list(range(6))
    interpolated = jax_sampling.posteriors(counts, model, fits, seeds, settings)
    calls = []
    original = jax_sampling._program

    def spy(kind, keep=True, **static):
        calls.append(static.get("exact"))
        return original(kind, keep, **static)

    monkeypatch.setattr(jax_fused, "TOLERANCE", -1.0)
    monkeypatch.setattr(jax_sampling, "_program", spy)
    original.cache_clear()  # retrace: the compiled programs hold the tolerance
    try:
        exact = jax_sampling.posteriors(counts, model, fits, seeds, settings)
    finally:
        original.cache_clear()
    assert True in calls
    assert (exact["method"] == interpolated["method"]).all()
    np.testing.assert_allclose(exact["ess"], interpolated["ess"], rtol=1e-3)
    scale = interpolated["sd"]
    assert np.max(np.abs(exact["mean"] - interpolated["mean"]) / scale) < 1e-2


def test_the_gaussian_rounds_sizes():
    needed = np.linspace(1, 5000, 2000)
    sizes = jax_sampling.round_size(needed)
    assert [jax_sampling.round_size(k) for k in needed[::97]] == sizes[::97].tolist()
    assert (sizes >= np.maximum(needed, MIN_BATCH // 2)).all()
    assert (sizes <= np.maximum(needed, MIN_BATCH // 2) * jax_sampling.ROUND_STEP + 1).all()
    assert len(np.unique(sizes)) <= 8 * np.log2(5000 / (MIN_BATCH // 2)) + 2  # few programs
