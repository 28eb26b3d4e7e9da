"""The emcee driver and the Posterior: exactness on a closed-form target, reproducibility,
flagged caps, agreement with the Cramér–Rao bound at high N, result files."""

import json

import numpy as np
import pytest
import xarray as xr

from bayespsf import Scene, load_scene, simulate
from bayespsf.inference import Posterior, sample_posterior
from bayespsf.model import Model
from bayespsf.theory import crlb

MEAN = np.array([10.0, -5.0, np.log(120.0), np.log(110.0), np.log(800.0), 4.0])
COV = np.diag([8.0, 8.0, 0.06, 0.05, 0.04, 0.2]) ** 2
COV[2, 4] = COV[4, 2] = 0.5 * 0.06 * 0.04  # correlated width and photons
PREC = np.linalg.inv(COV)


class GaussianModel(Model):
    """A model whose posterior in sampling coordinates is a known correlated Gaussian."""

    def log_posterior(self, z, counts):
        d = np.asarray(z) - MEAN
        return -0.5 * np.einsum("...i,ij,...j->...", d, PREC, d)


DUMMY = np.arange(225.0).reshape(15, 15)  # counts the Gaussian target ignores (not constant)


def gaussian_model():
    return GaussianModel.from_scene(load_scene("ideal"))


def start(seed=0, walkers=32):
    rng = np.random.default_rng(seed)
    return MEAN + rng.standard_normal((walkers, 6)) * np.sqrt(np.diag(COV))


def test_closed_form_posterior_mean_and_sd():
    # means within 5 Monte Carlo SEs (SE = sd / sqrt(ESS)), SDs within 5 SEs of an SD
    # (sd / sqrt(2 ESS)), in the sampling coordinates where the target is exactly Gaussian
    model = gaussian_model()
    post = sample_posterior(DUMMY, model, seed=3, start=start(), ess=1000)
    assert post.converged
    z = model.to_unconstrained(post.draws().to_numpy())
    ess = post.summary()["ess_bulk"].to_numpy()
    sd = np.sqrt(np.diag(COV))
    assert np.all(np.abs(z.mean(0) - MEAN) <= 5 * sd / np.sqrt(ess))
    assert np.all(np.abs(z.std(0) - sd) <= 5 * sd / np.sqrt(2 * ess))
    assert np.all(ess >= 1000 * 0.5)  # arviz's ESS on thinned draws vs the tau-based target
    assert np.corrcoef(z[:, 2], z[:, 4])[0, 1] == pytest.approx(0.5, abs=0.1)


def test_same_seed_same_draws_and_independent_streams():
    model = gaussian_model()
    counts = DUMMY
    a = sample_posterior(counts, model, seed=5, start=start(), ess=100).draws()
    b = sample_posterior(counts, model, seed=5, start=start(), ess=100).draws()
    c = sample_posterior(counts, model, seed=6, start=start(), ess=100).draws()
    assert a.equals(b) and not a.equals(c)


def test_step_cap_is_flagged_not_hidden(capsys):
    post = sample_posterior(
        DUMMY,
        gaussian_model(),
        seed=1,
        start=start(),
        ess=1e6,
        max_steps=600,
        progress=True,
    )
    assert not post.converged and post.info["steps"] == 600
    assert "sampling: 600 steps" in capsys.readouterr().err


@pytest.mark.slow
def test_posterior_sd_of_s_x_near_the_crlb_at_high_n():
    # EMCCD (table tier), N = 5000: averaged over 3 molecules, posterior SD of s_x within 10%
    # of sqrt(CRLB) (the tolerance; the posterior SD's own Monte Carlo error at ESS 400
    # is ~3.5%, and O(1/N) departures from the Gaussian limit are ~1%)
    scene = load_scene("emccd-typical").replace(emitter={"photons": 5000.0, "position": "fixed"})
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 3, seed=40)
    ratios = []
    for k in range(3):
        post = sample_posterior(counts[k], model, seed=k)
        assert post.converged
        ratios.append(post.sd()["s_x"] / crlb(scene)["s_x"])
    assert abs(np.mean(ratios) - 1) <= 0.10


def test_result_file_is_self_describing(tmp_path):
    scene = load_scene("paper-fig3")
    model = gaussian_model()
    truth = np.exp(MEAN) * [0, 0, 1, 1, 1, 0] + MEAN * [1, 1, 0, 0, 0, 1]
    post = sample_posterior(DUMMY, model, seed=2, start=start(), ess=100, truth=truth, scene=scene)
    path = post.save(tmp_path / "one.nc")
    plain = xr.open_datatree(path)  # no bayespsf needed to read it
    assert set(plain["posterior"].data_vars) == {"x0", "y0", "s_x", "s_y", "N", "b"}
    assert plain["posterior"]["s_x"].dims == ("chain", "draw")
    assert plain["observed_data"]["counts"].dims == ("row", "column")
    assert Scene.loads(plain.attrs["scene"]) == scene
    assert json.loads(plain.attrs["sampler"])["seed"] == 2
    loaded = Posterior.load(path)
    assert np.allclose(loaded.summary().to_numpy(), post.summary().to_numpy())
    assert np.allclose(loaded.truth.to_numpy(), truth)
    figure = loaded.corner()
    assert len(figure.axes) == 36
    assert len(loaded.trace().axes) >= 12  # a trace and a density per parameter


def test_summary_interval_and_bad_input():
    post = sample_posterior(DUMMY, gaussian_model(), seed=4, start=start(), ess=100)
    s = post.summary()
    assert list(s.index) == ["x0", "y0", "s_x", "s_y", "N", "b"]
    expected = ["mean", "sd", "hdi68_lb", "hdi68_ub", "hdi95_lb", "hdi95_ub"]
    expected += ["ess_bulk", "ess_tail", "r_hat", "tau"]
    assert set(expected) <= set(s.columns)
    assert np.all(s["hdi95_lb"] < s["hdi68_lb"]) and np.all(s["hdi68_ub"] < s["hdi95_ub"])
    central = post.interval(0.95)
    assert np.all(central["lower"] < s["mean"]) and np.all(s["mean"] < central["upper"])
    with pytest.raises(ValueError, match="prob"):
        post.interval(1.5)
    model = Model.from_scene(load_scene("ideal"))
    with pytest.raises(ValueError, match="one ROI"):
        sample_posterior(np.stack([DUMMY, DUMMY]), model)
    with pytest.raises(ValueError, match="counts"):
        sample_posterior(DUMMY[:9, :9], model)
    with pytest.raises(ValueError, match="seed"):
        sample_posterior(DUMMY, model, seed=-1)


def test_demo_runs(tmp_path):
    from bayespsf.cli import demo

    table, post, text = demo.run(tmp_path, seed=1)
    assert post.converged and (tmp_path / "corner.png").exists()
    assert (tmp_path / "posterior.nc").exists() and "Eq. sigma2dp3" in text
    assert np.all(table["ess_bulk"] >= 400)


HARD = {
    "N = 30": dict(emitter={"photons": 30.0}),
    "b = 0": dict(background={"kind": "none"}),
    "b = 500": dict(background={"kind": "poisson", "mean": 500.0}),
    "PSF centred on the ROI edge": dict(emitter={"x0": 750.0}),
    "s0 much larger than the ROI": dict(emitter={"s0x": 3000.0, "s0y": 3000.0}),
    "a/s0 = 0.2": dict(geometry={"pixel_size": 26.0, "roi": 31}),
    "a/s0 = 3": dict(geometry={"pixel_size": 390.0, "roi": 7}),
    "EM gain 1000, readout 100 e-": dict(camera={"gain": 1000.0, "readout_sd": 100.0}),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(HARD))
def test_hard_cases_give_a_finite_flagged_posterior(case):
    # bounded work (ESS 100, at most 4000 steps); the result is finite or says it is not converged
    scene = load_scene("emccd-typical").replace(emitter={"position": "fixed"}).replace(**HARD[case])
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 1, seed=50)
    post = sample_posterior(counts[0], model, seed=1, ess=100, max_steps=4000)
    draws = post.draws().to_numpy()
    assert np.all(np.isfinite(draws)) or not post.converged
    assert np.all(draws[:, 2:5] > 0) and np.all(draws[:, 5] >= 0)
    assert isinstance(post.converged, bool) and post.info["steps"] <= 4000


def test_saturated_pixels_are_a_clear_error():
    scene = load_scene("emccd-typical").replace(emitter={"photons": 1e7, "position": "fixed"})
    counts, _ = simulate(scene, 1, seed=0)
    assert counts.max() == 65535.0
    with pytest.raises(ValueError, match="saturated"):
        sample_posterior(counts[0], Model.from_scene(scene))


def test_prior_that_excludes_the_mle_still_starts_inside_it():
    # data with s0 = 130 nm and a prior that allows only 150-200 nm and a 20 nm box around the
    # centre: the walkers start inside the support and every draw stays there
    scene = load_scene("ideal")
    counts, _ = simulate(scene, 1, seed=4)
    narrow = scene.replace(
        prior={
            "s_x": {"kind": "log-uniform", "low": 150.0, "high": 200.0},
            "x0": {"kind": "uniform", "low": 60.0, "high": 80.0},
        }
    )
    post = sample_posterior(counts[0], Model.from_scene(narrow), seed=1, max_steps=1000)
    draws = post.draws()
    assert draws["s_x"].between(150.0, 200.0).all()
    assert draws["x0"].between(60.0, 80.0).all()
    assert np.all(np.isfinite(draws.to_numpy()))


def test_roi_outside_a_tiers_support_is_named():
    # the huang tier has no density where counts + readout variance < 0 (no clipping): a
    # pixel 10 readout SDs below the offset makes every parameter value impossible
    from bayespsf.errors import BayespsfInputError

    scene = load_scene("scmos-typical")
    counts, _ = simulate(scene, 1, seed=6)
    roi = counts[0].copy()
    roi[2, 3] = scene.camera["offset"] - 10 * np.sqrt(scene.camera["variance"])
    model = Model.from_scene(scene, likelihood="huang")
    with pytest.raises(BayespsfInputError, match=r"'huang' likelihood .*\(2, 3\)"):
        sample_posterior(roi, model, seed=0, max_steps=500)


def test_a_stuck_walker_is_counted_not_a_warning():
    # a walker that never moves (a local mode) has no autocorrelation function: it is left out
    # of tau (which stays finite, from the others) and counted, so the run cannot converge
    from bayespsf.inference.sampling import _autocorrelation_time

    rng = np.random.default_rng(2)
    segment = np.cumsum(rng.standard_normal((400, 16, 6)), axis=0) * 0.01
    segment[:, 5, :] = 3.0
    tau, stuck = _autocorrelation_time(segment)
    assert stuck == 1 and np.all(np.isfinite(tau))
    tau, stuck = _autocorrelation_time(np.ones((50, 16, 6)))
    assert stuck == 16 and np.all(np.isnan(tau))


def test_integrated_time_equals_emcee_estimator():
    # the vectorised estimator is emcee's (tol=0) to rounding, on chains with real correlation
    import emcee

    from bayespsf.inference.sampling import integrated_time

    rng = np.random.default_rng(5)
    for steps in (37, 128, 501):
        noise = rng.standard_normal((steps, 16, 6))
        chain = np.empty_like(noise)
        chain[0] = noise[0]
        for t in range(1, steps):  # AR(1) with coefficient 0.8: tau = 9
            chain[t] = 0.8 * chain[t - 1] + noise[t]
        expected = emcee.autocorr.integrated_time(chain, tol=0)
        np.testing.assert_allclose(integrated_time(chain), expected, rtol=1e-12)


def test_independence_move_accepts_everything_when_it_proposes_the_target():
    # target density == proposal density: the Metropolis-Hastings ratio is exactly 1, so a
    # wrong sign of the proposal correction would show as rejections
    import emcee

    from bayespsf.inference.sampling import IndependenceMove

    move = IndependenceMove(MEAN, COV, dof=5.0)
    sampler = emcee.EnsembleSampler(16, 6, move.log_density, vectorize=True, moves=move)
    sampler.random_state = np.random.RandomState(1).get_state()
    sampler.run_mcmc(start(walkers=16), 200)
    assert np.all(sampler.acceptance_fraction == 1.0)


def test_independence_move_is_exact_with_a_misplaced_proposal():
    # a skewed target (z0 ~ Gamma(3, 1), the rest N(0, 1)) and a t proposal centred 0.5 off
    # with 0.8x the target's SD: the chain's mean and variance of z0 match the exact 3 and 3
    # within 5 Monte Carlo SEs (SE from the chain's own autocorrelation time)
    import emcee

    from bayespsf.inference.sampling import IndependenceMove, integrated_time

    def log_target(z):
        z = np.atleast_2d(z)
        with np.errstate(divide="ignore", invalid="ignore"):
            gamma = np.where(z[:, 0] > 0, 2.0 * np.log(z[:, 0]) - z[:, 0], -np.inf)
        return gamma - 0.5 * np.sum(z[:, 1:] ** 2, axis=1)

    centre = np.array([2.5, 0.3, 0, 0, 0, 0])
    scale = np.diag([0.8**2 * 3.0, 0.64, 0.64, 0.64, 0.64, 0.64])
    sampler = emcee.EnsembleSampler(
        32, 6, log_target, vectorize=True, moves=IndependenceMove(centre, scale)
    )
    sampler.random_state = np.random.RandomState(2).get_state()
    walkers = centre + 0.1 * np.random.default_rng(2).standard_normal((32, 6))
    walkers[:, 0] = np.abs(walkers[:, 0])
    sampler.run_mcmc(walkers, 3000)
    chain = sampler.get_chain(discard=200)
    x = chain[..., 0]
    ess = x.size / integrated_time(chain)[0]
    assert np.abs(x.mean() - 3.0) <= 5 * np.sqrt(3.0 / ess)
    # the variance of a sample variance of Gamma(3): (mu4 - sigma^4) / n with mu4 = 3*3*(3+2)
    assert np.abs(x.var() - 3.0) <= 5 * np.sqrt((45.0 - 9.0) / ess)
