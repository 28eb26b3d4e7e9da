"""Pareto-smoothed importance sampling from the Laplace approximation: the weights and their
k-hat on targets with known tails, agreement with MCMC on a real ROI, and the fallback."""

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.inference import sample_posterior
from bayespsf.inference.importance import (
    CHAINS,
    KHAT_MAX,
    DefensiveMixture,
    ImportanceRun,
    IndependenceMove,
    first_batch,
    fitted_t,
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


def test_a_defensive_mixture_is_the_normalised_mixture_of_its_parts():
    # against scipy's normalised multivariate t densities: the mixture's log density differs
    # from log(0.7 t1 + 0.3 t2) by one constant at every point (to rounding), and its draws
    # come from the parts in its shares (binomial: 0.7 of 20 000 within 4 SE = 0.013)
    from scipy import stats

    rng = np.random.default_rng(3)
    a = rng.standard_normal((6, 6))
    parts = IndependenceMove(np.zeros(6), np.eye(6)), IndependenceMove(np.ones(6), a @ a.T + 0.5)
    mixture = DefensiveMixture(parts, (0.7, 0.3))
    z, log_g = mixture.draw(20_000, np.random.RandomState(4))
    exact = np.log(
        0.7 * stats.multivariate_t(np.zeros(6), np.eye(6), df=5).pdf(z)
        + 0.3 * stats.multivariate_t(np.ones(6), a @ a.T + 0.5, df=5).pdf(z)
    )
    np.testing.assert_allclose(log_g - exact, (log_g - exact)[0], atol=1e-9)
    np.testing.assert_allclose(mixture.log_density(z), log_g)
    # the stream: the parts' counts, then each part's draws in turn
    again = np.random.RandomState(4)
    counts = again.multinomial(20_000, (0.7, 0.3))
    assert abs(counts[0] / 20_000 - 0.7) <= 4 * np.sqrt(0.7 * 0.3 / 20_000)
    pairs = zip(parts, counts, strict=True)
    expected = np.concatenate([part.draw(int(k), again)[0] for part, k in pairs])
    np.testing.assert_array_equal(z, expected)


def test_a_fitted_t_has_the_weighted_moments():
    rng = np.random.default_rng(5)
    draws, weights = rng.standard_normal((1000, 6)), rng.random(1000)
    weights /= weights.sum()
    fitted = fitted_t(draws, weights)
    mean = weights @ draws
    np.testing.assert_allclose(fitted.centre, mean)
    cov = np.cov(draws.T, aweights=weights, bias=True)
    np.testing.assert_allclose(fitted.cholesky @ fitted.cholesky.T, cov, rtol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        fitted_t(draws, np.eye(1000)[0])  # all the weight on one draw: no covariance


def test_the_rois_the_student_t_fails_are_sampled_from_a_fitted_mixture_as_the_chain_does():
    # emccd-typical at N = 250: the Laplace Student-t fails on ~1% of ROIs (k-hat > 0.7: a
    # skewed posterior of widths and photons), which a t fitted to its weighted draws, mixed
    # with it, then samples. Against the chain (ESS 2 000) on the first two: every posterior
    # mean within 4 combined Monte Carlo SEs (sd / sqrt(ESS)) and every SD within 4 combined
    # SEs of an SD, sd sqrt((kurtosis - 1) / (4 ESS)) from the chain's own draws (these
    # posteriors are far from Gaussian, whose kurtosis, 3, gives the usual 1 / sqrt(2 ESS))
    from scipy import stats

    from bayespsf.psf import PARAMETER_NAMES

    scene = load_scene("emccd-typical").replace(emitter={"photons": 250.0})
    counts, _ = simulate(scene, 480, seed=3)
    model = Model.from_scene(scene)
    table = sample_many(counts, model, seed=9, workers=1, method="importance")
    fitted = table["why"].str.contains("fitted to the weighted draws")
    assert 1 <= fitted.sum() <= 20 and (table.loc[fitted, "method"] == "importance").all()
    assert table.loc[fitted, "why"].str.contains("Laplace Student-t failed").all()
    for i in np.flatnonzero(fitted)[:2]:
        chain = sample_posterior(counts[i], model, seed=1, method="mcmc", ess=2000)
        draws, ess_chain = chain.draws(), chain.summary()["ess_bulk"]
        for name in PARAMETER_NAMES:
            mean, sd = table.loc[i, f"{name}_mean"], table.loc[i, f"{name}_sd"]
            ess = table.loc[i, f"{name}_ess"]
            chain_sd = draws[name].std()
            se = chain_sd * np.sqrt(1 / ess + 1 / ess_chain[name])
            assert abs(mean - draws[name].mean()) <= 4 * se, (i, name)
            kurtosis = stats.kurtosis(draws[name], fisher=False)
            rel = np.sqrt((kurtosis - 1) / 4 * (1 / ess + 1 / ess_chain[name]))
            assert abs(sd / chain_sd - 1) <= 4 * rel, (i, name, sd / chain_sd, rel)
