"""The fused scorer against ``Model.log_posterior``, the reference it stands in for.

Tolerance: the interpolant of each pixel is checked against the camera law to
``fused.TOLERANCE`` (1e-6 in log p) at its check points; between them the error of a degree-8
Chebyshev interpolant of a smooth function is of the same size, so a draw's sum over a 15 x 15
ROI is held to ``roi**2 * TOLERANCE`` (2.25e-4), and its median to 1e-6 (measured: ~3e-8).
ROIs whose interpolant misses the check are scored by ``Model.log_posterior`` itself, which
the last tests force and hold to 1e-9 (the same arithmetic, summed in another order).
"""

from __future__ import annotations

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.inference import fit_mle, fused, spot_factors
from bayespsf.inference.batched import laplace_in_z
from bayespsf.inference.importance import IndependenceMove
from bayespsf.model import Model
from bayespsf.psf import expected_counts, sampled_gaussian


def reference(model, stack, draws):
    return [model.log_posterior(z, stack[i]) for i, z in enumerate(draws)]


def laplace_draws(scene_name, n_rois, n_draws, student, seed=0, pixel_model="integrated"):
    scene = load_scene(scene_name)
    model = Model.from_scene(scene, pixel_model=pixel_model)
    counts, _ = simulate(scene, n_rois, seed=seed)
    stack = model.check_counts(counts)
    centre, cov = laplace_in_z(fit_mle(counts, model), model)
    random = np.random.RandomState(seed)
    draws = []
    for c, s in zip(centre, cov, strict=True):
        if student:  # the wider proposal of method="importance"
            draws.append(IndependenceMove(c, s).draw(n_draws, random)[0])
        else:
            draws.append(c + random.standard_normal((n_draws, 6)) @ np.linalg.cholesky(s).T)
    return model, stack, draws


@pytest.mark.parametrize(
    ("scene_name", "student", "pixel_model"),
    [
        ("emccd-typical", False, "integrated"),
        ("emccd-typical", True, "integrated"),
        ("scmos-typical", False, "integrated"),
        ("ideal", True, "integrated"),
        ("paper-fig3", False, "sampled"),
    ],
)
def test_fused_score_matches_the_log_posterior(scene_name, student, pixel_model):
    model, stack, draws = laplace_draws(scene_name, 12, 150, student, pixel_model=pixel_model)
    got = np.concatenate(fused.score(model, stack, draws))
    want = np.concatenate(reference(model, stack, draws))
    assert np.array_equal(np.isfinite(got), np.isfinite(want))  # the same prior support
    inside = np.isfinite(want)
    error = np.abs(got[inside] - want[inside])
    assert error.max() <= model.roi**2 * fused.TOLERANCE
    assert np.median(error) <= 1e-6


def test_draws_outside_the_prior_and_empty_batches():
    model, stack, draws = laplace_draws("emccd-typical", 3, 40, False)
    draws[0][:5, 4] = np.log(1e12)  # N above the prior's 1e8: -inf
    draws[1] = draws[1][:0]  # a ROI without draws
    draws[2][:, 5] = -5.0  # every draw below the background prior's 0
    got = fused.score(model, stack, draws)
    assert [len(g) for g in got] == [40, 0, 40]
    assert np.all(got[0][:5] == -np.inf) and np.all(np.isfinite(got[0][5:]))
    assert np.all(got[2] == -np.inf)
    want = model.log_posterior(draws[0][5:], stack[0])
    np.testing.assert_allclose(got[0][5:], want, rtol=0, atol=model.roi**2 * fused.TOLERANCE)


def test_rois_whose_interpolant_fails_the_check_get_the_law_itself():
    model, stack, draws = laplace_draws("emccd-typical", 2, 60, False)
    # spot photons from 10 to 10^6 in one batch: no degree-8 interpolant spans that range
    draws[0][:, 4] = np.log(np.geomspace(10.0, 1e6, 60))
    got = fused.score(model, stack, draws)
    np.testing.assert_allclose(got[0], model.log_posterior(draws[0], stack[0]), rtol=0, atol=1e-9)
    error = np.abs(got[1] - model.log_posterior(draws[1], stack[1]))
    assert 0 < error.max() <= model.roi**2 * fused.TOLERANCE  # interpolated, not exact


def spot_params(rng, n, spread):
    """``n`` spots around (300, -200) nm with widths around 130 nm; ``spread`` scales how far
    they scatter (a posterior's draws: ~0.05; any spot in the ROI: ~5)."""
    return np.column_stack(
        [
            300 + spread * 100 * rng.standard_normal(n),
            -200 + spread * 100 * rng.standard_normal(n),
            130 * np.exp(spread * 0.3 * rng.standard_normal(n)),
            130 * np.exp(spread * 0.3 * rng.standard_normal(n)),
            np.ones(n),
            np.zeros(n),
        ]
    )


@pytest.mark.parametrize(
    ("pixel_model", "spread"), [("integrated", 0.05), ("integrated", 5.0), ("sampled", 0.05)]
)
def test_spot_factors_match_the_psf(pixel_model, spread):
    """The 1-D factors give ``psf.expected_counts`` (or ``sampled_gaussian``) in every pixel,
    down to masses of 1e-12 and below, where a difference of two erf values would have lost
    every digit. Clustered draws take the interpolated tails (checked to 1e-9 in log Q, so at
    most 2e-9 relative in a mass; held to 4e-9); scattered ones, and the sampled spot, the
    direct formula (1e-12 expected)."""
    rng = np.random.default_rng(3)
    roi, a, per_roi = 11, 100.0, 60
    params = spot_params(rng, 3 * per_roi, spread)
    starts = np.arange(0, 3 * per_roi + 1, per_roi)
    sampled = pixel_model == "sampled"
    px = spot_factors.factors(params[:, 0], params[:, 2], roi, a, starts, sampled)
    py = spot_factors.factors(params[:, 1], params[:, 3], roi, a, starts, sampled)
    got = py.T[:, :, None] * px.T[:, None, :]
    spot = sampled_gaussian if sampled else expected_counts
    want = spot(params, roi, a)
    assert want.min() < 1e-12  # far tails are in the test
    np.testing.assert_allclose(got, want, rtol=4e-9, atol=0)


def test_kept_interpolants_serve_the_next_batch_within_the_tolerance():
    # a pilot of 64 draws, then 400 more from the same Gaussian: the pilot's interpolants,
    # widened, span most ROIs' second batch and are reused; either way every draw is within
    # the tolerance of the law
    model, stack, pilot = laplace_draws("emccd-typical", 10, 64, False, seed=4)
    _, _, more = laplace_draws("emccd-typical", 10, 400, False, seed=4)
    kept = [None] * 10
    fused.score(model, stack, pilot, kept)
    first = [None if k is None else k[2] for k in kept]
    assert sum(k is not None for k in kept) >= 8  # the widened interpolants pass the check
    got = fused.score(model, stack, more, kept)
    pairs = zip(kept, first, strict=True)
    reused = sum(k is not None and f is not None and np.array_equal(k[2], f) for k, f in pairs)
    assert reused >= 5, reused
    for g, w in zip(got, reference(model, stack, more), strict=True):
        assert np.abs(g - w).max() <= model.roi**2 * fused.TOLERANCE
