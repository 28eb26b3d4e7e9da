"""The JAX backend (``backend="jax"``) against the NumPy backend on the same ROIs: the same MLE
to 1e-6, posterior summaries within Monte Carlo error, coverage on simulations, results that
do not depend on the chunking, PSIS equal to arviz_stats', and the command line. JAX runs on
the CPU here; ``benchmarks/gpu.py`` runs the same comparison on a GPU."""

import numpy as np
import pandas as pd
import pytest
from arviz_stats.base.array import array_stats

from bayespsf import load_scene, simulate
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle, jax_sampling
from bayespsf.inference.jax_model import JaxModel
from bayespsf.inference.psis import psis as array_psis
from bayespsf.inference.settings import check_settings
from bayespsf.inference.summary import coverage
from bayespsf.model import Model
from bayespsf.parallel import Store, sample_many
from bayespsf.parallel.seeds import molecule_seed
from bayespsf.psf import PARAMETER_NAMES

P = list(PARAMETER_NAMES)


def simulated(name: str, n: int = 48):
    scene = load_scene(name)
    counts, truth = simulate(scene, n, seed=21)
    return counts, truth[P].to_numpy(float), Model.from_scene(scene)


@pytest.fixture(scope="module")
def rois():
    """The EMCCD table tier (the default for EMCCD scenes): the posterior tests' ROIs."""
    return simulated("emccd-typical")


@pytest.fixture(scope="module")
def both(rois):
    counts, truths, model = rois
    run = {"seed": 5, "workers": 1, "truths": truths}
    return (
        sample_many(counts, model, **run),
        sample_many(counts, model, backend="jax", **run),
    )


@pytest.mark.parametrize("scene", ["emccd-typical", "ideal"])
def test_the_mle_is_the_numpy_engines_to_1e6(scene):
    # both engines run the same Levenberg-Marquardt to a Newton decrement of 1e-10: the same
    # optimum to far below 1e-6 relative. Both take the Laplace's Hessian by the chain rule
    # through the expected counts; the law's curvature is the same closed form for the EMCCD
    # table tier (its interpolant: the SDs agree to ~1e-15), and in the NumPy engine a central
    # difference of the score for the photon camera (~1e-8 relative), so 1e-7; the CRLB is
    # the same expected information, to rounding.
    counts, _, model = simulated(scene)
    a, b = fit_mle(counts, model), fit_mle(counts, model, backend="jax")
    assert list(a.columns) == list(b.columns)
    assert (a["status"] == b["status"]).all() and a["converged"].all()
    for columns, rel in (
        (P, 1e-6),
        ([f"sd_{p}" for p in P], 1e-7),
        ([f"crlb_{p}" for p in P], 1e-8),
    ):
        np.testing.assert_allclose(b[columns], a[columns], rtol=rel)
    np.testing.assert_allclose(b["log_likelihood"], a["log_likelihood"], rtol=1e-10)


@pytest.mark.parametrize(
    ("scene", "tier"),
    [("emccd-typical", None), ("emccd-typical", "high-gain"), ("emccd-typical", "gaussian"),
     ("emccd-typical", "poisson"), ("ideal", None)],
)  # fmt: skip
def test_the_laplace_by_the_chain_rule_is_jaxs_hessian(scene, tier):
    # the Laplace's information from the law's two derivatives per pixel and the expected
    # counts' Jacobian and second derivatives: the Hessian of the whole log-likelihood, to
    # rounding (entries within 1e-8 relative of their matrix's largest)
    import jax
    import jax.numpy as jnp

    from bayespsf.inference import jax_mle

    counts, truths, _ = simulated(scene, 8)
    model = Model.from_scene(load_scene(scene), **({} if tier is None else {"likelihood": tier}))
    jm = JaxModel.from_model(model)
    p = jnp.asarray(truths * [1.0, 1.0, 1.05, 0.95, 1.1, 1.0])  # not at the optimum: l' != 0
    cov, definite = jax_mle._compiled(model.roi)[1](jm, jnp.asarray(counts), p)

    def information(c, q):
        return jax.hessian(lambda v: -jm.log_likelihood(c, v))(q)

    want = np.asarray(jax.vmap(information)(jnp.asarray(counts), p))
    got = np.linalg.inv(np.asarray(cov))
    assert np.asarray(definite).all()
    scale = np.abs(want).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(got / scale, want / scale, atol=1e-8)


def test_without_background_the_laplace_is_the_numpy_engines():
    # at b = 0 most pixels expect under a photon, where the table's interpolant's second
    # derivative by lam carries its own error times 1 / lam^2 (curvatures of +-2 500 against
    # ~0.1): both engines take a difference of the score there, and agree. With the
    # interpolant's, the JAX engine called 16 of these 30 ROIs' information not positive
    # definite. Their SDs agree within 6e-5 relative (b's, on its bound); held to 1e-3.
    scene = load_scene("emccd-typical").replace(
        emitter={"photons": 100.0}, background={"kind": "none"}
    )
    counts, _ = simulate(scene, 30, seed=5)
    model = Model.from_scene(scene)
    a, b = fit_mle(counts, model), fit_mle(counts, model, backend="jax")
    assert a["converged"].all() and b["converged"].all()
    np.testing.assert_allclose(b[[f"sd_{p}" for p in P]], a[[f"sd_{p}" for p in P]], rtol=1e-3)


def test_the_poisson_tier_converges_as_on_the_numpy_engine():
    # the EMCCD's poisson tier scores counts as Poisson photons: the fit's metric is that
    # law's information, 1/lam, not the camera's (half of it, with which the steps overshot
    # twofold and most fits at N = 5 000 cycled to the iteration limit). Every ROI it can
    # score converges, to the NumPy engine's optimum; the CRLB stays the camera's
    scene = load_scene("emccd-typical").replace(emitter={"photons": 5000.0})
    counts, _ = simulate(scene, 40, seed=4)
    model = Model.from_scene(scene, likelihood="poisson")
    a, b = fit_mle(counts, model), fit_mle(counts, model, backend="jax")
    scored = np.isfinite(a["log_likelihood"])  # a count below the offset: -inf, named
    assert a.loc[~scored, "message"].str.contains("'poisson' likelihood gives zero density").all()
    assert scored.sum() >= 30 and (b["message"] == a["message"]).all()
    assert a.loc[scored, "converged"].all() and b.loc[scored, "converged"].all()
    np.testing.assert_allclose(b.loc[scored, P], a.loc[scored, P], rtol=1e-6)
    crlb = [f"crlb_{p}" for p in P]
    np.testing.assert_allclose(b.loc[scored, crlb], a.loc[scored, crlb], rtol=1e-8)


def compiled(function) -> tuple:
    """``function()``, and how many programs JAX compiled while it ran (``jax.monitoring``)."""
    import jax

    events = []

    def listen(name, seconds, **_):
        if name.endswith("backend_compile_duration"):
            events.append(name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        value = function()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return value, len(events)


def test_a_fit_does_not_depend_on_the_lanes_gathered_into_smaller_chunks(monkeypatch):
    # the fit moves its still-active ROIs into smaller chunks once 7/8 have finished; each
    # ROI's arithmetic is the same in any chunk, so the fits are those of one chunk run to
    # the end (COMPACT = 1: no lane is ever moved) bit for bit. How many lanes are moved
    # depends on the ROIs, the chunks they move to do not: other ROIs compile nothing new
    # (a dataset streamed block by block compiles its programs once, not in every block)
    from bayespsf.inference import jax_mle

    counts, _, model = simulated("emccd-typical", 256)
    moved = jax_mle.maximise(model, counts, None, False, False)
    others, _ = simulate(load_scene("emccd-typical"), 256, seed=22)
    _, count = compiled(lambda: jax_mle.maximise(model, others, None, False, False))
    assert count == 0
    monkeypatch.setattr(jax_mle, "COMPACT", 1)
    jax_mle._compiled.cache_clear()
    try:
        whole = jax_mle.maximise(model, counts, None, False, False)
    finally:
        jax_mle._compiled.cache_clear()
    for key in ("params", "log_likelihood", "converged", "message", "u"):
        np.testing.assert_array_equal(moved[key], whole[key])


def test_released_programs_give_back_their_memory_maps(rois):
    # each compiled program holds hundreds of the process's memory maps (Linux); a process
    # that runs many configurations releases them between configurations (the frontier does),
    # and the programs compile again on their next call
    from bayespsf.inference.backends import release_programs

    counts, _, model = rois

    def maps() -> int:
        with open("/proc/self/maps", encoding="utf-8") as lines:
            return sum(1 for _ in lines)

    settings = check_settings(method="auto", ess=100)
    fits = fit_mle(counts[:4], model, backend="jax")
    first = jax_sampling.posteriors(counts[:4], model, fits, range(4), settings)
    before, table = maps(), JaxModel.from_model(model).table
    release_programs()
    assert maps() < before - 100
    assert JaxModel.from_model(model).table is not table  # the camera's table let go too
    again = jax_sampling.posteriors(counts[:4], model, fits, range(4), settings)
    np.testing.assert_array_equal(again["mean"], first["mean"])


def test_start_values_on_the_device_are_the_hosts(rois):
    # fit_mle(backend="jax") computes the starting values on the device from the same
    # formulas (start_values with xp=jax.numpy): the same numbers to rounding (absolute
    # 1e-9 nm for a centroid near 0, a difference of sums)
    import jax.numpy as jnp

    from bayespsf.inference import start_values
    from bayespsf.inference.backends import start_jax

    counts, _, model = rois
    start_jax()  # float64
    photons = model.to_photons(counts)
    device = start_values(jnp.asarray(photons), model, xp=jnp)
    want = start_values(photons, model)
    np.testing.assert_allclose(np.asarray(device), want, rtol=1e-12, atol=1e-9)


def test_posterior_summaries_agree_within_monte_carlo_error(both):
    # two independent runs at ESS 400 differ in a posterior mean by ~sqrt(2/400) = 0.071
    # posterior SDs; over 48 ROIs x 6 parameters the spread of that difference is known to
    # ~4%, so 0.1 (7 SE above 0.071) fails only where the backends' posteriors differ
    a, b = both
    assert list(a.columns) == list(b.columns)
    # the same dtypes too: the SBC ranks are whole numbers on both
    assert (a.dtypes == b.dtypes).all(), a.dtypes[a.dtypes != b.dtypes]
    # and each ROI's own seed, whole (64-bit seeds, some above 2**63, some below)
    assert [int(s) for s in b["seed"]] == [molecule_seed(5, i) for i in range(len(b))]
    assert (a["seed"] == b["seed"]).all() and (a["status"] == b["status"]).all()
    z = np.concatenate([(a[f"{p}_mean"] - b[f"{p}_mean"]) / a[f"{p}_sd"] for p in P])
    assert abs(np.mean(z)) < 0.03 and np.std(z) < 0.1
    ratio = np.concatenate([b[f"{p}_sd"] / a[f"{p}_sd"] for p in P])
    assert abs(np.mean(ratio) - 1) < 0.02  # an SD's Monte Carlo error: ~1/sqrt(2 x 400)
    assert set(b["method"]) <= {"laplace", "importance", "mcmc"}
    assert b["why"].str.contains("k-hat|pilot weight SD").all()
    assert (b["draws"] >= 400).all() and b[[f"{p}_rank" for p in P]].notna().all().all()


def test_the_unchecked_laplace_agrees_with_the_numpy_backends(rois):
    # method="laplace": both backends draw from the same Laplace Gaussian, so their means
    # differ by Monte Carlo error, ~sqrt(2 / 100) = 0.14 posterior SDs at ESS 100; over 24 ROIs
    # x 6 parameters that spread is known to ~6%, so 0.2 fails only where the draws differ
    counts, _, model = rois
    run = {"seed": 5, "workers": 1, "method": "laplace", "ess": 100}
    a = sample_many(counts[:24], model, **run)
    b = sample_many(counts[:24], model, backend="jax", **run)
    assert (a["method"] == "laplace").all() and (b["method"] == "laplace").all()
    z = np.concatenate([(a[f"{p}_mean"] - b[f"{p}_mean"]) / a[f"{p}_sd"] for p in P])
    assert abs(np.mean(z)) < 0.06 and np.std(z) < 0.2
    assert (b["draws"] == a["draws"]).all()


def test_coverage_through_the_jax_backend(both):
    # the calibration study's statistic: 90% intervals hold the truth in 90% of ROIs, within
    # 3 binomial SEs (48 ROIs: SE 0.043) per parameter
    _, b = both
    table = coverage(b, 0.9)
    assert (np.abs(table["coverage"] - 0.9) <= 3 * np.sqrt(0.09 / len(b))).all()


def test_a_rois_posterior_does_not_depend_on_the_other_rois(rois):
    # each ROI is one lane of a vmapped program with its own key: the same numbers whatever
    # shares its chunk (the chunk's size is a batch dimension, which changes no lane's
    # arithmetic). The device sees only the programs' fixed shapes, never one set by how many
    # ROIs a stage holds: a part of the stack compiles nothing new
    # Nor on the others' seeds: the part's seeds are all below 2**63, the whole stack's not
    counts, truths, model = rois
    settings = check_settings(method="auto")
    fits = fit_mle(counts, model, backend="jax")
    seeds = [molecule_seed(5, i) for i in range(len(counts))]
    whole = jax_sampling.posteriors(counts, model, fits, seeds, settings, truths)
    part = [i for i, seed in enumerate(seeds) if seed < 2**63][:12]
    assert len(part) == 12 and max(seeds) >= 2**63
    chosen = [seeds[i] for i in part]
    alone, count = compiled(
        lambda: jax_sampling.posteriors(
            counts[part], model, fits.iloc[part], chosen, settings, truths[part]
        )
    )
    assert count == 0
    for key in ("mean", "sd", "quantiles", "ess", "weight_sd", "rank"):
        np.testing.assert_allclose(alone[key], whole[key][part], rtol=1e-12, atol=1e-12)
    assert (alone["method"] == whole["method"][part]).all()


@pytest.mark.parametrize("draws", [64, 520, 2048])
def test_psis_is_arviz_stats(draws):
    import jax.numpy as jnp

    from bayespsf.inference.backends import start_jax

    start_jax()  # the backend computes in float64, whichever test a worker ran first
    rng = np.random.default_rng(draws)
    for scale in (0.1, 1.0, 3.0):  # light to heavy tails: k-hat from < 0 to > 0.7
        log_ratio = scale * rng.standard_t(3, draws)
        log_w, khat = array_psis(jnp.asarray(log_ratio), xp=jnp)
        log_w_ref, khat_ref = array_stats.psislw(-log_ratio)  # arviz_stats smooths exp(-x)
        assert float(khat) == pytest.approx(float(khat_ref), rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(np.asarray(log_w), log_w_ref, rtol=0, atol=1e-9)


def test_a_store_made_on_the_device_reads_back_and_resumes(rois, tmp_path):
    counts, truths, model = rois
    store = tmp_path / "store"
    run = {"seed": 5, "workers": 1, "truths": truths[:4], "store": store, "backend": "jax"}
    table = sample_many(counts[:4], model, **run)
    post = Store(store).posterior(2)
    assert post.draws()["x0"].mean() == pytest.approx(table.loc[2, "x0_mean"], rel=1e-12)
    assert len(post.draws()) == table.loc[2, "draws"]
    again = sample_many(counts[:4], model, **run)  # resumes: read back, not sampled again
    pd.testing.assert_frame_equal(
        again[["molecule", "x0_mean", "s_x_q0975"]], table[["molecule", "x0_mean", "s_x_q0975"]]
    )
    with pytest.raises(BayespsfInputError, match="backend"):  # another backend's store
        sample_many(counts[:4], model, **{**run, "backend": "numpy"})


def test_named_refusals(tmp_path):
    scene = load_scene("scmos-typical")
    counts, _ = simulate(scene, 2, seed=1)
    with pytest.raises(BayespsfInputError, match="backend='numpy'"):
        fit_mle(counts, Model.from_scene(scene), backend="jax")
    with pytest.raises(BayespsfInputError, match="backend must be one of numpy, jax"):
        fit_mle(counts, Model.from_scene(scene), backend="cuda")
    with pytest.raises(BayespsfInputError, match="sCMOS camera law"):  # before any work
        sample_many(counts, Model.from_scene(scene), workers=1, backend="jax", store=tmp_path)
    assert not any(tmp_path.iterdir())  # no store was opened
    with pytest.raises(BayespsfInputError, match="engine='stack'"):
        fit_mle(counts, Model.from_scene(scene), backend="jax", engine="scipy")


def test_fit_on_the_command_line(tmp_path):
    import tifffile

    from bayespsf import cli

    counts, _ = simulate(load_scene("emccd-typical"), 4, seed=4)
    tifffile.imwrite(tmp_path / "rois.tif", counts.astype(np.float32), photometric="minisblack")
    out = tmp_path / "fit"
    args = ["fit", str(tmp_path / "rois.tif"), "--scene", "emccd-typical", "--backend", "jax"]
    assert cli.main([*args, "--out", str(out), "--workers", "1"]) == 0
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 4 and summary["converged"].all()
    assert set(summary["method"]) <= {"laplace", "importance"}


@pytest.mark.parametrize("scene", ["emccd-typical", "ideal"])
def test_pearsons_statistic_on_the_device_is_the_hosts(scene):
    # the same sum over pixels of the same camera mean and variance: equal to rounding
    from bayespsf.inference import gof

    counts, truths, model = simulated(scene, 8)
    np.testing.assert_allclose(
        jax_sampling.pearson(model, counts, truths), gof.pearson(model, counts, truths), rtol=1e-12
    )


def test_a_movie_analysed_on_the_jax_backend(tmp_path):
    # analyze's per-ROI posteriors through the device pass (its store included): every frame
    # of the molecule converges, as through the NumPy backend
    from bayespsf import Model, analyze, simulate_movie
    from bayespsf.movie import Rules

    scene = load_scene("paper-movie").replace(
        movie={"frames": 20, "height": 48, "width": 48, "molecules": 1, "dark_frames": 0,
               "bleach_mean": 12.0, "two_fluorophores": 0.0, "moving": 0.0}
    )  # fmt: skip
    made = simulate_movie(scene, seed=0, out=tmp_path / "m")
    result = analyze(
        made.files["movie"], Model.from_scene(scene), s0=120.0, out=tmp_path / "out",
        rules=Rules(min_valid_frames=8), workers=1, progress=False, backend="jax",
    )  # fmt: skip
    assert len(result.frames) >= 8 and (result.frames["status"] == "converged").all()
    assert set(result.frames["method"]) <= {"laplace", "importance"}
    assert len(Store(tmp_path / "out" / "posteriors").finished(10**6)) == len(result.frames)


def test_a_roi_whose_student_t_draws_the_prior_cuts_gets_more_rounds_not_the_chain():
    """Where the prior confines x0 and y0 to the central pixel (the calibration study's
    prior), the Student-t's ESS per draw falls to ~0.1, and 2 080 draws (three rounds) reach
    ESS 90-360. These three ROIs reach ESS 400 beyond the third round, as the NumPy engine's
    growing batches reach it, instead of going to the chain."""
    scene = load_scene("emccd-typical")
    half = 0.5 * scene.geometry["pixel_size"]
    box = {"kind": "uniform", "low": -half, "high": half}
    prior = {"x0": box, "y0": box, "s_x": {"kind": "log-uniform", "low": 100.0, "high": 180.0}}
    prior["s_y"] = prior["s_x"]
    prior["N"] = {"kind": "log-uniform", "low": 300.0, "high": 3000.0}
    prior["b"] = {"kind": "uniform", "low": 2.0, "high": 20.0}
    scene = scene.replace(prior=prior)
    model, rng = Model.from_scene(scene), np.random.default_rng(1001)
    truths = model.sample_prior(100, rng)
    exact = Model.from_scene(scene, likelihood="exact").camera
    counts = exact.sample(model.expected(truths), rng)[[1, 11, 18]]
    table = sample_many(counts, model, seed=1, workers=1, backend="jax", max_steps=10)
    assert (table["method"] == "importance").all(), table["why"].tolist()
    scored = table["why"].str.extract(r"ESS \d+ of (\d+) draws")[0].astype(int)
    assert (scored > 2080).all(), table["why"].tolist()  # beyond the third round


def test_a_roi_the_device_leaves_is_importance_sampled_on_the_host_before_the_chain():
    # N = 250: ROI 12 of this stack fails the device's Student-t rounds (k-hat 0.84). The host
    # samples it by the NumPy engine's importance path (the Student-t judged afresh, then the
    # fitted mixture's rounds) before any chain: its row says both, and it is a posterior
    scene = load_scene("emccd-typical").replace(emitter={"photons": 250.0})
    counts, _ = simulate(scene, 40, seed=12)
    model = Model.from_scene(scene)
    table = sample_many(counts, model, seed=2, workers=1, backend="jax", method="importance")
    host = table["why"].str.contains("; on the host: ")
    assert np.flatnonzero(host).tolist() == [12]
    row = table.loc[12]
    assert "Student-t failed" in row["why"].split("; on the host: ")[0]
    assert row["method"] == "importance"
    assert row["status"] == "converged" and row["s_x_ess"] >= 400
    assert (table["method"] == "importance").all()
