"""Runs that cannot end usefully stop early and say why; settings that would never end (or never
start) a run are refused by name (nothing endless)."""

import numpy as np
import pytest

import bayespsf
from bayespsf import load_scene
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import diagnostics
from bayespsf.model import Model


@pytest.fixture(scope="module")
def typical():
    scene = load_scene("emccd-typical")
    counts, _ = bayespsf.simulate(scene, 1, seed=1)
    return scene, counts[0], Model.from_scene(scene)


@pytest.mark.parametrize(
    "setting,value,words",
    [
        ("ess", float("nan"), r"ess must be a number in \(0, 1e\+07\]"),
        ("ess", float("inf"), "ess must be"),
        ("ess", 0, "ess must be"),
        ("ess", -5, "ess must be"),
        ("ess", 0.01, r"ess must be a number in \[1, 1e\+07\]"),
        ("walkers", "32", "walkers must be an integer"),
        ("walkers", 13, "walkers must be an even number"),
        ("walkers", 32.0, "walkers must be an integer"),
        ("max_steps", 0, r"max_steps must be an integer in \[1, inf\]"),
        ("max_steps", -10, "max_steps must be"),
        ("max_seconds", float("nan"), "max_seconds must be"),
        ("max_seconds", 0, "max_seconds must be"),
        ("seed", -1, "seed must be"),
        ("method", "nuts", "method must be one of mcmc, auto, laplace, importance"),
    ],
)
def test_settings_that_would_never_end_are_refused_by_name(typical, setting, value, words):
    _, counts, model = typical
    with pytest.raises(BayespsfInputError, match=words):
        bayespsf.sample_posterior(counts, model, **{setting: value})


def test_one_step_is_a_run_not_a_crash(typical):
    _, counts, model = typical
    post = bayespsf.sample_posterior(counts, model, seed=0, max_steps=1)
    assert post.info["steps"] == 1 and not post.converged
    assert post.info["stopped"] == "max_steps" and "not converged" in post.info["diagnosis"]


def test_a_growing_autocorrelation_time_is_a_stall():
    # tau proportional to the chain's length: stalled; tau levelling off: not (yet) stalled
    growing = [(n, 0.05 * n) for n in (250, 500, 1000, 2000)]
    assert "tau grew" in diagnostics.stalled(growing, 4000, 200.0, 0, 32)
    levelling = [(n, t) for n, t in zip((250, 500, 1000, 2000), (15, 18, 20, 21), strict=True)]
    assert diagnostics.stalled(levelling, 4000, 21.5, 0, 32) is None
    assert diagnostics.stalled(growing, 2000, 100.0, 0, 32) is None  # too short to judge
    assert "no walker moves" in diagnostics.stalled([], 1000, np.nan, 32, 32)


def test_explanations_name_the_cause(typical):
    _, counts, model = typical
    fit = bayespsf.fit_mle(counts, model).iloc[0]
    assert diagnostics.explain(fit, model) == ""
    narrow = Model(
        15, 100.0, model.camera, prior={"N": {"kind": "log-uniform", "low": 1e6, "high": 1e7}}
    )
    assert "prior excludes the data: the maximum-likelihood N" in diagnostics.explain(fit, narrow)
    failed = fit.copy()
    failed["converged"], failed["message"] = False, "ABNORMAL"
    assert "fit failed (ABNORMAL)" in diagnostics.explain(failed, model)
    loose = fit.copy()
    loose["sd_s_x"] = fit["s_x"]
    assert "not identified" in diagnostics.explain(loose, model)


def test_a_prior_that_excludes_the_data_stops_early_with_a_diagnosis(typical, monkeypatch):
    # the tester's case: a prior on N orders of magnitude from the data ran for hours; the
    # stall rule is judged from 400 steps here (4000 by default) to keep the test short
    _, counts, model = typical
    monkeypatch.setattr(diagnostics, "STALL_MIN_STEPS", 400)
    prior = {"N": {"kind": "log-uniform", "low": 1e6, "high": 1e7}}
    narrow = Model(15, 100.0, model.camera, prior=prior)
    post = bayespsf.sample_posterior(counts, narrow, seed=0)
    assert post.info["stopped"] == "stalled" and not post.converged
    assert post.info["steps"] <= 1600
    assert "prior excludes the data" in post.info["diagnosis"]


def test_a_degenerate_prior_stops_without_warnings(typical):
    # b half-normal with scale 1e-300: overflow in the prior and a walker that cannot move in b
    # gave RuntimeWarnings and a 50 000-step run (warnings are errors in this suite)
    _, counts, model = typical
    tiny = Model(15, 100.0, model.camera, prior={"b": {"kind": "half-normal", "scale": 1e-300}})
    post = bayespsf.sample_posterior(counts, tiny, seed=0)
    assert post.info["stopped"] == "stalled" and post.info["steps"] <= 2000
    assert "half-normal prior" in post.info["diagnosis"]


def test_the_wall_clock_budget_stops_a_run(typical):
    _, counts, model = typical
    narrow = Model(
        15, 100.0, model.camera, prior={"N": {"kind": "log-uniform", "low": 1e6, "high": 1e7}}
    )
    post = bayespsf.sample_posterior(counts, narrow, seed=0, max_seconds=2.0)
    # without the budget this chain runs 6400 steps before the stall rule stops it
    assert post.info["stopped"] == "max_seconds" and not post.converged
    assert post.info["steps"] < 6400


# ------------------------------------------------------------------ ROIs the model refuses


@pytest.mark.parametrize("roi", [1, 3])
def test_rois_too_small_to_fit_are_refused_by_their_size(roi):
    with pytest.raises(
        BayespsfInputError, match=f"roi must be >= 5 pixels for inference, got {roi}"
    ):
        Model(roi, 100.0, bayespsf.cameras.Photon())


def test_counts_with_the_offset_subtracted_twice_are_refused(typical):
    scene, counts, model = typical
    with pytest.raises(BayespsfInputError, match="not in ADU above the offset"):
        model.check_counts(counts - 2 * scene.camera["offset"])
    model.check_counts(counts)  # the ROI itself is fine


def test_an_undeclared_saturation_plateau_is_refused():
    # a bright spot clipped at 20 000 ADU by a camera whose saturation the model does not know:
    # posteriors looked converged and were 2 SD off; now the plateau is named
    scene = load_scene("emccd-typical").replace(
        emitter={"photons": 3e4, "position": "fixed"}, camera={"saturation": 20000.0}
    )
    counts, _ = bayespsf.simulate(scene, 1, seed=0)
    assert np.count_nonzero(counts[0] == 20000.0) >= 3
    blind = Model.from_scene(scene.replace(camera={"saturation": 0.0}))
    with pytest.raises(BayespsfInputError, match=r"plateau .* Declare the camera.s saturation"):
        bayespsf.sample_posterior(counts[0], blind)
    with pytest.raises(BayespsfInputError, match="pixels are saturated"):
        Model.from_scene(scene).check_counts(counts[0])


def test_an_adc_full_scale_pair_is_a_plateau():
    roi = np.arange(49.0).reshape(7, 7)
    roi[3, 3] = roi[3, 4] = 4095.0
    assert bayespsf.model.saturation_plateau(roi.ravel()) == 2
    roi[3, 4] = 4094.0
    assert bayespsf.model.saturation_plateau(roi.ravel()) == 0


def test_bright_unsaturated_spots_raise_no_false_plateau():
    # 400 bright spots (N = 2e4, peaks near 30 000 ADU, integer ADU): none is called saturated
    scene = load_scene("emccd-typical").replace(
        emitter={"photons": 2e4}, camera={"saturation": 0.0}
    )
    counts, _ = bayespsf.simulate(scene, 400, seed=3)
    problems = Model.from_scene(scene).roi_problems(counts)
    assert problems == [None] * 400
