"""The batched posteriors (bayespsf.inference.batched through sample_many): the same numbers as
one ROI at a time, the Laplace's acceptance rule and its promised accuracy, per-ROI outcomes,
and calibration on simulated ROIs."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import load_scene, simulate
from bayespsf.inference import sample_posterior
from bayespsf.inference.batched import LAPLACE_WEIGHT_SD, _weight_sds, random_stream
from bayespsf.inference.summary import coverage, molecule_row
from bayespsf.model import Model
from bayespsf.parallel import molecule_seed, sample_many
from bayespsf.psf import PARAMETER_NAMES

SUMMARY = ("_mean", "_sd", "_q0025", "_q0500", "_q0975", "_rank")


def scene_at(photons):
    return load_scene("emccd-typical").replace(emitter={"photons": float(photons)})


@pytest.fixture(scope="module")
def dim():
    """Dim ROIs: importance sampling from the Laplace for most, from a fitted mixture for some
    (the Laplace Student-t's k-hat), never the Laplace."""
    scene = scene_at(200)
    counts, truth = simulate(scene, 24, seed=5)
    return counts, truth[list(PARAMETER_NAMES)].to_numpy(float), Model.from_scene(scene)


@pytest.fixture(scope="module")
def dim_auto(dim):
    counts, truths, model = dim
    return sample_many(
        counts, model, seed=7, workers=1, method="auto", truths=truths, max_steps=3000
    )


def test_each_row_says_which_method_ran_and_why(dim_auto):
    assert set(dim_auto["method"]) <= {"importance", "mcmc"}
    assert (dim_auto["method"] == "importance").sum() >= 12
    for method, why in zip(dim_auto["method"], dim_auto["why"], strict=True):
        assert "Laplace rejected (pilot weight SD" in why
        assert why.split("; ")[-1].startswith("importance" if method == "importance" else "chain")


@pytest.mark.parametrize("method", ["auto", "importance", "laplace"])
def test_a_stack_gives_what_each_roi_gives_alone(dim, dim_auto, method):
    # same seeds, same streams, and a fit that does not depend on the other ROIs of its stack:
    # a ROI's posterior is the same alone as in a stack, to the last bit
    counts, truths, model = dim
    table = (
        dim_auto
        if method == "auto"
        else sample_many(
            counts[:6], model, seed=7, workers=1, method=method, truths=truths[:6], max_steps=3000
        )
    )
    picks = [0, 1, 2]
    if method == "auto":  # and a ROI whose Student-t failed: a fitted mixture's round ran
        fitted = dim_auto["why"].str.contains("fitted to the weighted draws, round")
        picks.append(int(np.flatnonzero(fitted & (dim_auto["method"] == "importance"))[0]))
    for i in picks:
        seed = molecule_seed(7, i)
        alone = sample_posterior(
            counts[i], model, seed=seed, method=method, truth=truths[i], max_steps=3000
        )
        row = molecule_row(alone, i, seed)
        assert row["method"] == table.loc[i, "method"]
        for name in PARAMETER_NAMES:
            for suffix in SUMMARY:
                np.testing.assert_array_equal(table.loc[i, name + suffix], row[name + suffix])


def test_results_do_not_depend_on_the_number_of_workers(dim, dim_auto):
    counts, truths, model = dim
    two = sample_many(
        counts, model, seed=7, workers=2, method="auto", truths=truths, max_steps=3000
    )
    cols = [c for c in dim_auto.columns if c != "seconds"]
    pd.testing.assert_frame_equal(two[cols], dim_auto[cols])


def test_random_stream_is_the_sequence_sample_posterior_spawns():
    # made from its spawn key, each stream is the one spawning the tree gives, so a ROI's
    # draws are those of sample_posterior
    for seed in (0, 7, 2**40):
        start, chain = np.random.SeedSequence(seed).spawn(2)
        spawned = dict(zip(("draws", "resample", "laplace", "adapt"), chain.spawn(4), strict=True))
        for name, sequence in {"start": start, "chain": chain, **spawned}.items():
            np.testing.assert_array_equal(
                random_stream(seed, name).generate_state(8), sequence.generate_state(8)
            )


def test_weight_sd_of_lognormal_weights():
    # log w ~ N(0, s^2): the weights normalised to mean 1 have sd sqrt(exp(s^2) - 1) exactly;
    # from 10^6 draws per row the estimate is within 1% (its relative SE here is ~1e-3)
    rng = np.random.default_rng(0)
    s = np.array([0.01, 0.05, 0.2])
    sds = _weight_sds(s[:, None] * rng.standard_normal((3, 1_000_000)))
    np.testing.assert_allclose(sds, np.sqrt(np.expm1(s * s)), rtol=0.01)
    # a row with a draw outside the support is inf, and does not touch its neighbours
    rows = np.array([[0.0, -np.inf, 0.0], [0.0, 0.1, -0.1], [0.0, np.nan, 0.0]])
    sds = _weight_sds(rows)
    assert sds[0] == np.inf and sds[2] == np.inf
    w = np.exp(rows[1] - 0.1)
    assert sds[1] == pytest.approx(np.std(w / w.mean(), ddof=1), rel=1e-12)


@pytest.fixture(scope="module")
def bright():
    scene = scene_at(30_000)
    counts, truth = simulate(scene, 4, seed=2)
    return counts, truth[list(PARAMETER_NAMES)].to_numpy(float), Model.from_scene(scene)


def test_auto_uses_the_laplace_where_its_bound_promises_accuracy(bright):
    # Cauchy-Schwarz: with pilot weight SD w <= 0.05 every mean is within w posterior SDs of
    # the exact (importance, ESS 20 000) posterior's and every SD within w/sqrt(2); the
    # tolerance adds 4 Monte Carlo SEs of the Laplace draws and of the reference
    counts, _, model = bright
    laplaced = 0
    for i, roi in enumerate(counts):
        auto = sample_posterior(roi, model, seed=i, method="auto")
        if auto.info["method"] != "laplace":
            assert auto.info["weight_sd"] > LAPLACE_WEIGHT_SD
            continue
        laplaced += 1
        w = auto.info["weight_sd"]
        assert w <= LAPLACE_WEIGHT_SD and auto.info["converged"]
        exact = sample_posterior(roi, model, seed=i, method="importance", ess=20_000)
        a, b = auto.draws().to_numpy(), exact.draws().to_numpy()
        sd = b.std(axis=0)
        se = np.sqrt(1 / len(a) + 1 / len(b))
        assert np.all(np.abs(a.mean(axis=0) - b.mean(axis=0)) <= (w + 4 * se) * sd)
        assert np.all(np.abs(a.std(axis=0) / sd - 1) <= w / np.sqrt(2) + 4 * se / np.sqrt(2))
    assert laplaced >= 2


def test_laplace_requested_is_used_and_flagged_when_its_pilot_fails(dim):
    counts, _, model = dim
    post = sample_posterior(counts[0], model, seed=1, method="laplace", ess=200)
    assert post.info["method"] == "laplace" and post.info["weight_sd"] > LAPLACE_WEIGHT_SD
    assert not post.info["converged"] and f"> {LAPLACE_WEIGHT_SD}" in post.info["why"]
    assert len(post.draws()) == 200


def test_bad_and_unfittable_rois_are_rows_the_rest_is_sampled(dim):
    counts, _, model = dim
    stack = counts[:4].copy()
    stack[1] = stack[1].mean()  # constant: refused before any work
    table = sample_many(stack, model, seed=1, workers=1, method="auto", max_steps=2000)
    assert table.loc[1, "status"] == "refused" and "same value" in table.loc[1, "message"]
    assert table.drop(index=1)["method"].isin(["importance", "mcmc"]).all()


def _auto_posteriors(n_photons: float, simulation_seed: int, seed: int):
    """480 emccd-typical ROIs at ``n_photons`` and their auto posteriors with truths."""
    scene = scene_at(n_photons)
    counts, truth = simulate(scene, 480, seed=simulation_seed)
    truths = truth[list(PARAMETER_NAMES)].to_numpy(float)
    return sample_many(
        counts, Model.from_scene(scene), seed=seed, workers=1, method="auto", truths=truths
    )


def _assert_calibrated(rows) -> None:
    """The central 68% and 95% intervals of every parameter cover the truth within 3
    binomial SEs."""
    for prob in (0.68, 0.95):
        cov = coverage(rows, prob)
        se = np.sqrt(prob * (1 - prob) / len(rows))
        assert np.all(np.abs(cov["coverage"] - prob) <= 3 * se), cov


def test_batched_auto_posteriors_are_calibrated():
    # 480 ROIs of emccd-typical at N = 1000 with their truths: the central 68% and 95%
    # intervals of every parameter cover the truth within 3 binomial SEs (SE 2.1% and 1.0%)
    table = _auto_posteriors(1000, simulation_seed=21, seed=4)
    assert (table["status"] == "converged").mean() > 0.95
    _assert_calibrated(table)


def test_laplace_branch_posteriors_are_calibrated():
    # 480 ROIs at N = 20 000, where auto takes the Laplace for most (418 here; 80% measured by
    # benchmarks/auto.py): over all ROIs and over those the Laplace made, the central 68% and
    # 95% intervals of every parameter cover the truth within 3 binomial SEs (the other
    # calibration test, at N = 1 000, never reaches the Laplace)
    table = _auto_posteriors(20_000, simulation_seed=22, seed=5)
    laplace = table[table["method"] == "laplace"]
    assert len(laplace) >= 0.5 * len(table)
    _assert_calibrated(table)
    _assert_calibrated(laplace)


def test_auto_goes_on_from_the_laplace_gaussian_where_its_pilot_is_near():
    # At N = 1 000 every pilot weight SD is 0.12-0.2: auto continues the pilot with the
    # Laplace Gaussian as proposal. Its posterior means must agree with method="importance"
    # (the Student-t proposal, other random streams): each has a Monte Carlo SD of at most
    # sd / sqrt(400), so their difference has SD <= 0.071 posterior SDs; 5 of those (0.35)
    # bounds all 40 x 4 differences (chance of a false failure ~1e-4). An SD from ESS 400 has a
    # relative MC error of ~1/sqrt(800) = 3.5%, a ratio of two ~5%: 0.8-1.25 is 4.5 SDs
    scene = scene_at(1000)
    counts, _ = simulate(scene, 40, seed=31)
    model = Model.from_scene(scene)
    auto = sample_many(counts, model, seed=3, workers=1, method="auto")
    t = sample_many(counts, model, seed=3, workers=1, method="importance")
    assert (auto["method"] == "importance").all()
    assert auto["why"].str.contains("importance sampling from the Laplace Gaussian").all()
    assert t["why"].str.contains("importance sampling from the Laplace Student-t").all()
    for name in ("x0", "s_x", "N", "b"):
        difference = (auto[f"{name}_mean"] - t[f"{name}_mean"]) / t[f"{name}_sd"]
        assert difference.abs().max() <= 0.35, (name, difference.abs().max())
        sd_ratio = auto[f"{name}_sd"] / t[f"{name}_sd"]
        assert sd_ratio.between(0.8, 1.25).all(), (name, sd_ratio.min(), sd_ratio.max())
