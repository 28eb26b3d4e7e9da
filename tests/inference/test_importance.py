"""Pareto-smoothed importance sampling from the Laplace approximation: the weights and their
k-hat on targets with known tails, agreement with MCMC on a real ROI, and the fallback."""

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.inference import sample_posterior
from bayespsf.inference.importance import (
    CHAINS,
    KHAT_MAX,
    ImportanceRun,
    IndependenceMove,
    first_batch,
    psis,
    systematic_resample,
)
from bayespsf.inference.sampling import _start
from bayespsf.model import Model
from bayespsf.parallel import sample_many


def test_psis_of_nearly_equal_ratios_is_nearly_uniform():
    log_ratio = 0.01 * np.random.default_rng(0).standard_normal(4000)
    weights, khat = psis(log_ratio)
    assert weights.sum() == pytest.approx(1.0)
    assert khat < 0.5 and 1.0 / np.sum(weights**2) > 0.99 * 4000


def test_psis_flags_a_proposal_narrower_than_the_target():
    # target N(0, 1), proposal N(0, 0.4^2): the ratios have a Pareto tail of shape
    # k = 1 - 0.4^2 = 0.84 (Vehtari et al. 2024, sec. 3), beyond the 0.7 limit
    x = 0.4 * np.random.default_rng(1).standard_normal(8000)
    log_ratio = -0.5 * x**2 + 0.5 * (x / 0.4) ** 2
    _, khat = psis(log_ratio)
    assert khat > KHAT_MAX


def test_systematic_resampling_keeps_the_weights():
    # each draw is taken floor(n w) or ceil(n w) times: the resampled mean is the weighted mean
    rng = np.random.default_rng(2)
    weights = rng.random(500)
    weights /= weights.sum()
    index = systematic_resample(weights, 10_000, rng)
    counts = np.bincount(index, minlength=500)
    assert np.all(np.abs(counts - 10_000 * weights) < 1.0 + 1e-9)


@pytest.fixture(scope="module")
def roi():
    scene = load_scene("emccd-typical").replace(emitter={"photons": 1000.0})
    counts, _ = simulate(scene, 1, seed=8)
    return counts[0], Model.from_scene(scene)


def test_importance_posterior_agrees_with_mcmc(roi):
    # both are exact methods: means within 5 combined Monte Carlo SEs (sd / sqrt(ESS)), SDs
    # within 5 SEs of an SD (sd / sqrt(2 ESS)), for every parameter
    counts, model = roi
    a = sample_posterior(counts, model, seed=1, ess=2000, method="importance")
    b = sample_posterior(counts, model, seed=1, ess=2000)
    assert a.info["method"] == "importance" and a.info["why"].startswith("importance")
    assert a.info["khat"] <= KHAT_MAX and a.info["ess"] >= 2000
    assert len(a.draws()) == CHAINS * int(a.info["ess"] // CHAINS)
    sa, sb = a.summary(), b.summary()
    ess_a, ess_b = a.info["ess"], sb["ess_bulk"].to_numpy()
    sd = sb["sd"].to_numpy()
    assert np.all(np.abs(sa["mean"] - sb["mean"]) <= 5 * sd * np.sqrt(1 / ess_a + 1 / ess_b))
    assert np.all(np.abs(sa["sd"] / sb["sd"] - 1) <= 5 * np.sqrt(1 / (2 * ess_a) + 1 / (2 * ess_b)))


def test_same_seed_same_importance_draws(roi):
    counts, model = roi
    a = sample_posterior(counts, model, seed=4, ess=200, method="importance")
    b = sample_posterior(counts, model, seed=4, ess=200, method="importance")
    np.testing.assert_array_equal(a.draws().to_numpy(), b.draws().to_numpy())


def test_a_poor_proposal_stops_on_its_khat_and_a_given_start_runs_the_chain(roi):
    counts, model = roi
    c = model.check_counts(counts)
    _, _, proposal = _start(c, model, 32, np.random.default_rng(0))
    narrow = IndependenceMove(proposal.centre, 1e-4 * proposal.cholesky @ proposal.cholesky.T)
    run = ImportanceRun(narrow, 400.0, 20_000, np.random.RandomState(0))
    while not run.done:
        run.take(model.log_posterior(run.propose(), c))
    # a proposal 100x too narrow: its ratios have a heavy tail, seen in the first batch
    assert run.khat > KHAT_MAX and len(run.weights) == first_batch(400.0)
    start = proposal.centre + 1e-3 * np.random.default_rng(1).standard_normal((32, 6))
    post = sample_posterior(c, model, seed=0, start=start, method="importance", max_steps=100)
    assert "a start was given" in post.info["why"] and post.info["steps"] == 100
    assert post.info["method"] == "mcmc" and post.info["requested"] == "importance"


def test_an_importance_run_adds_draws_until_its_ess_target(roi):
    counts, model = roi
    c = model.check_counts(counts)
    _, _, proposal = _start(c, model, 32, np.random.default_rng(0))
    run = ImportanceRun(proposal, 3000.0, 150_000, np.random.RandomState(1))
    rounds = 0
    while not run.done:
        run.take(model.log_posterior(run.propose(), c))
        rounds += 1
    assert run.achieved >= 3000 and run.khat <= KHAT_MAX
    # the first batch (ess / 0.77 draws) rarely suffices; the second is sized to finish
    assert rounds <= 3 and len(run.weights) < 2 * first_batch(3000.0)


def test_sample_many_rows_say_the_method(roi):
    counts, model = roi
    table = sample_many(counts[None], model, seed=2, workers=1, ess=300, method="importance")
    assert table.loc[0, "method"] == "importance"
    assert table.loc[0, "s_x_ess"] >= 300
    with pytest.raises(ValueError, match="method"):
        sample_posterior(counts, model, method="nuts")
