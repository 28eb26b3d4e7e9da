"""Hostile inputs: sizes that cannot fit in memory, the largest ROI the scene schema allows,
result files with a damaged attribute, and a goodness of fit in every posterior (without it,
two overlapping molecules give a confident single-spot posterior with nothing that says the
model does not fit)."""

import json
import os
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
from scipy import stats

from bayespsf import Model, Scene, load_scene, simulate
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import Posterior, bootstrap_check, fit_mle, sample_posterior
from bayespsf.inference.gof import FIT_KEYS, pearson
from bayespsf.inference.settings import MAX_CHAIN_WORK, check_chain_work, check_settings
from bayespsf.parallel import Store, sample_many
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.simulation import simulate_chunks
from bayespsf.simulation.pipeline import block_size

SCENE = load_scene("paper-fig3")
MODEL = Model.from_scene(SCENE)
COUNTS, TRUTH = simulate(SCENE, 2, seed=1)
HUGE = 10**12  # beyond any machine's memory at any ROI size

# ----------------------------------------------------------------------- sizes beyond memory
# each ended in NumPy's MemoryError (or worse, the out-of-memory killer) after part of the work


def test_walkers_beyond_memory_are_refused_by_name_before_any_work():
    words = rf"walkers = {HUGE} on 19 x 19 ROIs needs at least .* PB of memory at once"
    with pytest.raises(BayespsfInputError, match=words + ".*use fewer walkers"):
        sample_posterior(COUNTS[0], MODEL, walkers=HUGE)
    for method in ("mcmc", "auto"):  # auto: refused before the batched engine, too
        with pytest.raises(BayespsfInputError, match=words):
            sample_many(COUNTS, MODEL, walkers=HUGE, method=method, workers=1, progress=False)


def test_images_beyond_memory_are_refused_by_name_before_any_work():
    with pytest.raises(
        BayespsfInputError,
        match=rf"n = {HUGE} images of 19 x 19 pixels needs at least 2.95 PB of memory at once"
        r", more than this machine's .*: simulate fewer images \(n; -n on the command line\)",
    ):
        simulate(SCENE, HUGE, seed=1)
    with pytest.raises(BayespsfInputError, match=rf"chunk_size = {HUGE} images .*smaller chunk"):
        next(simulate_chunks(SCENE, HUGE, 1, chunk_size=HUGE))


def test_replicates_beyond_memory_are_refused_by_name():
    with pytest.raises(BayespsfInputError, match=rf"replicates = {HUGE} of 19 x 19 ROIs needs"):
        bootstrap_check(COUNTS, MODEL, replicates=HUGE)


# --------------------------------------------------------- the largest ROI the schema allows
# 401 x 401 pixels (1 um at the paper's smallest pixels, 2.5 nm). Every vectorised engine sized
# its batches for 15 x 15 ROIs: a simulation block of 1024 images (1.3 GB per array, and the
# work of 1024 images for one), 4096 scored draws per call (5.3 GB per array), 1024 ROIs per
# fit pass (a 7.9 GB Jacobian): a two-ROI run held 13.7 GB and swapped without end. And a chain
# scores 32 walkers x 160 801 pixels per step (0.1-0.2 s): 50 000 steps, 2-3 hours per ROI.

LARGEST = textwrap.dedent(
    """
    import json, resource
    import numpy as np, bayespsf

    with open("/proc/self/status") as status:
        data = next(int(line.split()[1]) for line in status if line.startswith("VmData"))
    limit = data * 1024 + 2**30  # 1 GiB of data above what the imports hold
    resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))
    out = {}
    background = {"kind": "poisson", "mean": 5.0}
    scene = bayespsf.Scene.from_dict({"geometry": {"roi": 401}, "background": background})
    counts, truth = bayespsf.simulate(scene, 1, seed=1)
    model = bayespsf.Model.from_scene(scene)
    table = bayespsf.sample_many(counts, model, seed=1, workers=1, progress=False)
    out["with background"] = table[["method", "status"]].iloc[0].tolist()
    try:
        bayespsf.sample_posterior(counts[0], model, method="mcmc")
    except bayespsf.errors.BayespsfInputError as error:
        out["chain"] = str(error)
    bare = bayespsf.Scene.from_dict({"geometry": {"roi": 401}})  # no background: b at 0
    counts, truth = bayespsf.simulate(bare, 1, seed=2)
    table = bayespsf.sample_many(
        counts, bayespsf.Model.from_scene(bare), seed=1, workers=1, progress=False
    )
    out["without background"] = table[["status", "message", "why"]].iloc[0].tolist()
    print(json.dumps(out))
    """
)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads /proc (Linux)")
def test_the_largest_roi_runs_in_bounded_memory_and_an_endless_chain_is_refused():
    done = subprocess.run(
        [sys.executable, "-W", "error", "-c", LARGEST],
        capture_output=True,
        text=True,
        timeout=300,  # it ran for hours (swapping, or a 50 000-step chain)
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    assert out["with background"] == ["importance", "converged"]
    assert out["chain"] == (
        "a chain on 401 x 401 ROIs may run max_steps = 50000 steps of walkers = 32: 2.6e+11 "
        "pixel evaluations, about 2.1 hours per ROI at 30 ns each, with no wall-clock budget; "
        "give max_seconds (--max-seconds on the command line), a budget per ROI, or "
        "max_steps <= 19433 (or use smaller ROIs)"
    )
    # importance weights that overflowed PSIS's tail fit ended the run in a ValueError (NaN
    # ESS); now a failed importance run, the chain refused by name, one row
    status, message, why = out["without background"]
    assert status == "failed" and message == out["chain"], out
    assert why.endswith(
        "chain: importance sampling from the Laplace Student-t failed "
        "(k-hat inf, ESS 0 of 520 draws)"
    )


def test_blocks_of_the_largest_roi_are_bounded_and_smaller_rois_keep_theirs():
    def scene(roi):
        return Scene.from_dict({"geometry": {"roi": roi}})

    assert block_size(scene(401)) == 26  # was 1024
    assert [block_size(scene(roi)) for roi in (15, 31, 63)] == [1024] * 3  # images unchanged
    assert block_size(scene(65)) * 65**2 <= 2**22


def test_the_chain_budget_refuses_only_large_unbounded_chains():
    defaults = check_settings()
    check_chain_work(defaults, 249)  # the largest odd ROI the defaults pass
    with pytest.raises(BayespsfInputError, match="max_steps <= 49602"):
        check_chain_work(defaults, 251)
    check_chain_work(check_settings(max_seconds=60.0), 401)  # a budget bounds it
    check_chain_work(check_settings(max_steps=19_433), 401)
    assert 19_433 * 32 * 401**2 <= MAX_CHAIN_WORK


# -------------------------------------------------------- a result file's damaged attributes


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("post") / "molecule-000000.nc"
    post = sample_posterior(COUNTS[0], MODEL, seed=1, method="auto", truth=TRUTH.iloc[0])
    post.tree.attrs["summary_row"] = json.dumps({"molecule": 0})
    post.save(path)
    return path


@pytest.mark.parametrize(
    ("key", "damage", "why"),
    [
        ("sampler", lambda text: text[: len(text) // 2], "not valid JSON"),
        ("summary_row", lambda text: text[:-1], "not valid JSON"),
        ("tau", lambda text: "[1, 2]", "not a table of numbers per parameter"),
        ("truth", lambda text: '{"x0": "near the centre"}', "not a table of numbers"),
        ("camera", lambda text: "", "not valid JSON"),
        ("geometry", lambda text: "17", "not a JSON table"),
    ],
)
def test_a_damaged_attribute_is_named_with_the_file_at_load(
    result_file, tmp_path, key, damage, why
):
    # Posterior.load returned, and post.info (or summary(), or truth) raised a JSONDecodeError
    path = tmp_path / "damaged.nc"
    path.write_bytes(result_file.read_bytes())
    with h5py.File(path, "r+") as file:
        file.attrs[key] = damage(file.attrs[key])
    with pytest.raises(
        BayespsfInputError, match=rf"^{path}: its attribute '{key}' is damaged: {why}"
    ) as caught:
        Posterior.load(path).info  # noqa: B018 - the old failure was here
    assert "sample this molecule again" in str(caught.value)


def test_an_attribute_damaged_in_memory_is_named_too():
    post = sample_posterior(COUNTS[0], MODEL, seed=1, method="laplace")
    post.tree.attrs["sampler"] = "{"
    with pytest.raises(BayespsfInputError, match="the posterior: its attribute 'sampler'"):
        post.info  # noqa: B018 - the property decodes the attribute


def test_an_intact_result_file_loads_as_before(result_file):
    post = Posterior.load(result_file)
    assert post.info["method"] == "importance" and post.truth is not None
    assert set(FIT_KEYS) <= set(post.info)


# --------------------------------------------------------- goodness of fit in every result


def _scene(background: float) -> Scene:
    return Scene.from_dict(
        {
            "geometry": {"roi": 15},
            "emitter": {"photons": 1000.0, "position": "pixel"},
            "background": {"kind": "poisson", "mean": background},
        }
    )


@pytest.mark.parametrize(
    "scene",
    [
        _scene(20.0),
        load_scene("emccd-typical").replace(emitter={"position": "pixel", "photons": 1000.0}),
    ],
    ids=["photon-b20", "emccd-typical"],
)
def test_the_fit_p_value_is_near_uniform_on_rois_the_model_describes(scene):
    # 200 ROIs: P(chi2_p <= 0.1) = 0.1 with a binomial SE of 0.021 (4 SE: 0.085), and a KS
    # test of uniformity at 1e-3 (measured 0.080, KS p 0.07; 0.100, KS p 0.33)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 200, seed=5)
    table = sample_many(counts, model, seed=1, workers=1, progress=False)
    p = table["chi2_p"].to_numpy()
    assert np.isfinite(p).all() and (table["chi2_dof"] == 15 * 15 - 6).all()
    assert abs(np.mean(p <= 0.1) - 0.1) < 4 * np.sqrt(0.1 * 0.9 / 200)
    assert stats.kstest(p, "uniform").pvalue > 1e-3


def test_two_overlapping_molecules_are_flagged_though_their_posterior_converges():
    # the case: two 1000-photon spots 400 nm apart, read as one converged wide spot;
    # Pearson's chi-square at the fit flags it at p <= 0.01 in >= 90% of 40 ROIs (all, measured)
    scene = load_scene("emccd-typical").replace(emitter={"position": "pixel", "photons": 1000.0})
    model = Model.from_scene(scene)
    one = np.array([-200.0, 0.0, 120.0, 120.0, 1000.0, scene.background["mean"]])
    two = one.copy()
    two[0], two[5] = 200.0, 0.0
    lam = model.expected(one) + model.expected(two) - model.clock_induced_charge
    counts = model.camera.sample(np.broadcast_to(lam, (40, *lam.shape)), np.random.default_rng(3))
    table = sample_many(counts, model, seed=2, workers=1, progress=False)
    assert table["converged"].all()  # the posterior alone says nothing is wrong
    assert np.mean(table["chi2_p"] <= 0.01) >= 0.9, table["chi2_p"].describe()
    post = sample_posterior(counts[0], model, seed=2, method="mcmc")
    assert post.converged and post.info["chi2_p"] <= 0.01 and post.info["chi2_at"] == "mle"


def test_the_statistic_is_pearsons_at_the_fit_and_changes_no_draw():
    fits = fit_mle(COUNTS[:1], MODEL)
    theta = fits[list(PARAMETER_NAMES)].to_numpy(float)
    expected = float(pearson(MODEL, COUNTS[:1], theta)[0])
    for method in ("laplace", "importance", "mcmc"):
        post = sample_posterior(COUNTS[0], MODEL, seed=1, method=method)
        info = post.info
        assert info["chi2"] == pytest.approx(expected, rel=1e-9), method
        assert info["chi2_dof"] == 19 * 19 - 6 and info["chi2_at"] == "mle"
        assert info["chi2_p"] == pytest.approx(stats.chi2.sf(expected, 19 * 19 - 6))
    # a chain from a given start has no MLE: judged at its posterior mean
    start = np.random.default_rng(0).normal(MODEL.to_unconstrained(theta[0]), 1e-3, (32, 6))
    post = sample_posterior(COUNTS[0], MODEL, seed=1, start=start, max_steps=200)
    mean = post.draws().mean().to_numpy()
    assert post.info["chi2_at"] == "posterior mean"
    assert post.info["chi2"] == pytest.approx(float(pearson(MODEL, COUNTS[:1], mean[None])[0]))


def test_every_summary_row_and_its_file_carry_the_statistic(tmp_path):
    table = sample_many(COUNTS, MODEL, seed=1, workers=1, progress=False, store=tmp_path / "store")
    assert list(table.columns[-5:]) == [*FIT_KEYS, "photon_unit"]  # added last
    for k in range(2):
        post = Store(tmp_path / "store").posterior(k)
        row = json.loads(post.tree.attrs["summary_row"])
        assert {key: row[key] for key in FIT_KEYS} == {key: post.info[key] for key in FIT_KEYS}
    resumed = sample_many(
        COUNTS, MODEL, seed=1, workers=1, progress=False, store=tmp_path / "store"
    )
    assert resumed[list(FIT_KEYS)].equals(table[list(FIT_KEYS)])
