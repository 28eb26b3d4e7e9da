"""Least squares, maximum likelihood and Laplace fits on simulated molecules; gain calibration."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import Scene, load_scene, simulate
from bayespsf.calibration import calibrate_gain
from bayespsf.inference import covariance, fit_lsq, fit_mle, fit_screened, start_values
from bayespsf.inference.lsq import lsq_first_order
from bayespsf.model import Model
from bayespsf.theory import crlb, scene_params

COLUMNS = ["x0", "y0", "s_x", "s_y", "N", "b"]


def fixed(name, **emitter):
    return load_scene(name).replace(emitter={"position": "fixed", **emitter})


@pytest.mark.parametrize("name", ["ideal", "emccd-typical"])
def test_lsq_spread_matches_its_first_order_prediction(name):
    # N = 5000: second-order terms are ~1/N; the SD's Monte Carlo SE is SD / sqrt(2 (n - 1));
    # allowed: 5 SE + 3% for the neglected higher orders
    scene = fixed(name, photons=5000.0)
    model = Model.from_scene(scene)
    limit, cov = lsq_first_order(model, scene_params(scene))
    counts, _ = simulate(scene, 2000, seed=31)
    fits = fit_lsq(counts, model)
    assert fits["converged"].all()
    est = fits[COLUMNS].to_numpy()
    sd_pred = np.sqrt(np.diag(cov))
    n = len(est)
    assert np.all(np.abs(est.mean(0) - limit) <= 5 * sd_pred / np.sqrt(n) + 1e-3 * sd_pred)
    se = est.std(0, ddof=1) / np.sqrt(2 * (n - 1))
    assert np.all(np.abs(est.std(0, ddof=1) - sd_pred) <= 5 * se + 0.03 * sd_pred)
    # the least-squares widths estimate the pixelated width, about sqrt(s0^2 + a^2 / 12)
    assert limit[2] > scene.emitter["s0x"]


@pytest.mark.parametrize("name", ["ideal", "emccd-typical"])
def test_mle_unbiased_and_at_the_crlb_at_high_n(name):
    # N = 1e4: MLE bias and excess variance are O(1/N) (~1e-4 relative here); 5 SE tolerances
    scene = fixed(name, photons=1e4)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 800, seed=32)
    fits = fit_mle(counts, model)
    assert fits["converged"].all()
    truth = scene_params(scene)
    bound = crlb(scene).to_numpy()
    est = fits[COLUMNS].to_numpy()
    n = len(est)
    assert np.all(np.abs(est.mean(0) - truth) <= 5 * bound / np.sqrt(n))
    se = bound / np.sqrt(2 * (n - 1))
    assert np.all(np.abs(est.std(0, ddof=1) - bound) <= 5 * se + 0.01 * bound)
    # the Laplace SDs of single molecules agree with the bound on average (within 3%)
    laplace = fits[[f"sd_{c}" for c in COLUMNS]].to_numpy().mean(0)
    assert np.allclose(laplace, bound, rtol=0.03)


HARD = {
    "N = 20": dict(emitter={"photons": 20.0}),
    "b = 0": dict(background={"kind": "none"}),
    "PSF on the ROI edge": dict(emitter={"x0": 700.0}),
    "a/s0 = 0.2": dict(geometry={"pixel_size": 26.0, "roi": 31}),
    "a/s0 = 3": dict(geometry={"pixel_size": 390.0, "roi": 7}),
}


@pytest.mark.parametrize("case", sorted(HARD))
def test_hard_cases_finite_or_flagged(case):
    scene = fixed("emccd-typical").replace(**HARD[case])
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 40, seed=33)
    for fits in (fit_lsq(counts, model), fit_mle(counts, model)):
        assert len(fits) == 40  # nothing dropped
        values = fits[COLUMNS].to_numpy()
        finite = np.all(np.isfinite(values), axis=1)
        assert np.all(finite | ~fits["converged"].to_numpy())
        assert fits["message"].map(lambda m: isinstance(m, str) and len(m) > 0).all()


def test_mle_with_the_exact_tier_matches_the_table_tier():
    # the exact tier's closed-form score on a 2-D ROI; the table tier is within 1e-4 of it in
    # log p, so the two maxima agree to a small fraction of the CRLB
    scene = fixed("emccd-typical")
    counts, _ = simulate(scene, 1, seed=35)
    exact = fit_mle(counts, Model.from_scene(scene, likelihood="exact"))
    table = fit_mle(counts, Model.from_scene(scene, likelihood="table"))
    assert exact["converged"].all() and table["converged"].all()
    bound = crlb(scene).to_numpy()
    assert np.all(np.abs(exact[COLUMNS].to_numpy() - table[COLUMNS].to_numpy()) < 0.02 * bound)


def test_all_zero_roi_is_refused_by_name():
    model = Model.from_scene(load_scene("ideal"))
    fits = fit_mle(np.zeros((2, 15, 15)), model)
    assert (fits["status"] == "refused").all() and fits["message"].str.contains("same value").all()
    with pytest.raises(ValueError, match="same value"):
        model.check_counts(np.zeros((2, 15, 15)))


def test_start_values_are_close_for_a_bright_spot():
    scene = fixed("ideal", photons=5000.0, x0=60.0, y0=-40.0)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 50, seed=34)
    start = start_values(model.to_photons(counts), model).mean(0)
    assert start[0] == pytest.approx(60.0, abs=15) and start[1] == pytest.approx(-40.0, abs=15)
    # second moments include the pixel (a^2/12) and background residue: within 30%
    assert start[2] == pytest.approx(130.0, rel=0.3) and start[4] == pytest.approx(5000, rel=0.2)


def test_bad_counts_are_named():
    model = Model.from_scene(load_scene("ideal"))
    with pytest.raises(ValueError, match="counts"):
        fit_lsq(np.zeros((2, 9, 9)), model)
    nan = fit_mle(np.full((15, 15), np.nan), model).iloc[0]
    assert nan["status"] == "refused" and "NaN or infinite" in nan["message"]
    with pytest.raises(ValueError, match=r"counts.*complex"):
        fit_mle(np.ones((15, 15)) + 1j, model)
    noiseless = Model.from_scene(Scene.from_dict({"camera": {"kind": "emccd", "gain": 100.0}}))
    below = fit_mle(np.arange(225.0).reshape(15, 15) - 1.0, noiseless).iloc[0]
    assert below["status"] == "refused" and "below the offset" in below["message"]


GAIN_SCENE = {
    "geometry": {"roi": 11, "pixel_size": 100.0},
    "emitter": {"s0x": 120.0, "s0y": 120.0},
    "background": {"kind": "poisson", "mean": 5.0},
    "camera": {
        "kind": "emccd",
        "gain": 100.0,
        "readout_sd": 30.0,
        "offset": 100.0,
        "e_per_adu": 5.0,
    },
}


@pytest.mark.parametrize("photons,pixels", [(2000.0, 9), (60.0, 1)])
def test_gain_calibration_recovers_adu_per_photon(photons, pixels):
    # 30 simulated movies of 500 frames; true M = gain / e_per_adu = 20 ADU per photon; the
    # mean of the estimates within 5 standard errors of 20 (Eq. photonConv is unbiased to first
    # order); at low SNR only the centre pixel is used
    scene = Scene.from_dict(
        {**GAIN_SCENE, "emitter": {**GAIN_SCENE["emitter"], "photons": photons}}
    )
    results = [calibrate_gain(simulate(scene, 500, seed=k)[0]) for k in range(30)]
    m = np.array([r.adu_per_photon for r in results])
    assert abs(m.mean() - 20.0) <= 5 * m.std(ddof=1) / np.sqrt(len(m))
    assert all(len(r.pixel_estimates) == pixels for r in results)
    assert all(r.centre == (5, 5) for r in results)


def test_gain_calibration_bad_movies():
    with pytest.raises(ValueError, match="movie"):
        calibrate_gain(np.zeros((2, 11, 11)))
    with pytest.raises(ValueError, match="movie"):
        calibrate_gain(np.ones((10, 11, 11)))  # nothing brighter than the background


def test_laplace_covariance_is_kept_with_the_sds():
    scene = load_scene("emccd-typical")
    counts, _ = simulate(scene, 2, seed=4)
    fits = fit_mle(counts, Model.from_scene(scene))
    cov = covariance(fits)
    assert cov.shape == (2, 6, 6)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2))
    sds = fits[[f"sd_{c}" for c in COLUMNS]].to_numpy()
    np.testing.assert_allclose(np.sqrt(np.diagonal(cov, axis1=1, axis2=2)), sds, rtol=1e-12)
    with pytest.raises(ValueError, match="laplace=True"):  # no SDs: named, not a KeyError
        covariance(fit_mle(counts, Model.from_scene(scene), laplace=False))
    for i, p in enumerate(COLUMNS):  # every entry from its table columns
        for j, q in enumerate(COLUMNS):
            corr = 1.0 if i == j else fits[f"corr_{COLUMNS[min(i, j)]}_{COLUMNS[max(i, j)]}"]
            expected = corr * fits[f"sd_{p}"] * fits[f"sd_{q}"]
            np.testing.assert_allclose(cov[:, i, j], expected, rtol=1e-14)


def test_a_screened_stack_is_fitted_as_fit_mle_fits_it(monkeypatch):
    """``fit_screened`` with the stack's own problems gives ``fit_mle``'s table, and does not
    judge the ROIs again (``sample_many`` screens once)."""
    scene = load_scene("emccd-typical")
    counts, _ = simulate(scene, 5, seed=6)
    counts[1] = 500.0  # constant: refused
    model = Model.from_scene(scene)
    expected = fit_mle(counts, model)
    problems = model.roi_problems(counts)

    def judged_again(self, counts):
        raise AssertionError("the stack was judged again")

    monkeypatch.setattr(Model, "roi_problems", judged_again)
    pd.testing.assert_frame_equal(fit_screened(counts, model, problems), expected)
    clean = np.delete(counts, 1, axis=0)  # problems None: every ROI passed
    pd.testing.assert_frame_equal(
        fit_screened(clean, model), expected.drop(index=1).reset_index(drop=True)
    )
    with pytest.raises(ValueError, match="problems must be one reason"):
        fit_screened(counts, model, problems[:-1])
    with pytest.raises(ValueError, match="problems must be one reason"):  # not a mask
        fit_screened(counts, model, [p is None for p in problems])
    with pytest.raises(ValueError, match="engine must be one of"):
        fit_screened(counts, model, problems, engine="newton")
    with pytest.raises(ValueError, match=r"stack must have shape \(n, roi, roi\)"):
        fit_screened(counts[0], model)
    with pytest.raises(ValueError, match="start must have one row x0 y0 s_x s_y N b per ROI"):
        fit_screened(counts, model, problems, start=np.ones((2, 6)))
    with pytest.raises(ValueError, match="start must have one row"):  # 5 columns, not 6
        fit_screened(counts, model, problems, start=np.ones((6 * len(counts) // 5, 5)))
    good = np.tile([0.0, 0.0, 120.0, 120.0, 1000.0, 10.0], (len(counts), 1))
    for column, value, name in ((2, -1.0, "s_x"), (4, 0.0, "N"), (5, -10.0, "b")):
        bad = good.copy()
        bad[1, column] = value
        with pytest.raises(ValueError, match=f"start's {name} must be"):
            fit_screened(counts, model, problems, start=bad)


def test_an_infinite_pixel_is_refused_without_a_warning_from_the_start_values():
    # start values are computed for the fitted ROIs only: an infinite pixel's moments would
    # warn (an error in this suite) before its ROI is refused
    scene = load_scene("emccd-typical")
    counts, _ = simulate(scene, 3, seed=1)
    counts[0, 0, 0] = np.inf
    fits = fit_mle(counts, Model.from_scene(scene))
    assert fits["status"].tolist() == ["refused", "converged", "converged"]


def test_a_bad_roi_is_a_row_not_an_exception_for_the_stack():
    # picasso fits the rest of a stack with a constant or saturated ROI; so do we, and say why
    scene = load_scene("emccd-typical")
    counts, _ = simulate(scene, 4, seed=4)
    counts[1] = 500.0  # constant
    counts[2, 7, 7] = scene.camera["saturation"]  # saturated
    model = Model.from_scene(scene)
    for fit in (fit_mle, fit_lsq):
        fits = fit(counts, model)
        assert fits["status"].tolist() == ["converged", "refused", "refused", "converged"]
        assert "same value" in fits.loc[1, "message"] and "saturated" in fits.loc[2, "message"]
        assert fits.loc[[1, 2], list(COLUMNS)].isna().all().all()
        assert fits.loc[[0, 3], list(COLUMNS)].notna().all().all()


def test_an_empty_stack_gives_an_empty_table_with_the_columns():
    # a frame without molecules: both fits give a table of no rows that concatenates with
    # others (fit_lsq raised KeyError: 'converged')
    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 1, seed=1)
    for fit in (fit_mle, fit_lsq):
        empty, one = fit(counts[:0], model), fit(counts, model)
        assert len(empty) == 0 and list(empty.columns) == list(one.columns)
        assert len(pd.concat([empty, one], ignore_index=True)) == 1


def test_fit_tables_print_concatenate_and_save(tmp_path):
    # repr() raised under pandas 2.3 (a NumPy array in attrs) and pd.concat of two results failed
    scene = load_scene("ideal")
    model = Model.from_scene(scene)
    a = fit_mle(simulate(scene, 2, seed=1)[0], model)
    b = fit_mle(simulate(scene, 3, seed=2)[0], model)
    both = pd.concat([a, b], ignore_index=True)
    assert len(both) == 5 and "x0" in repr(both) and not both.attrs
    both.to_csv(tmp_path / "fits.csv", index=False)
    back = pd.read_csv(tmp_path / "fits.csv")
    np.testing.assert_allclose(covariance(back), covariance(both), rtol=1e-12)


@pytest.mark.parametrize("engine", ["stack", "scipy"])
def test_a_roi_outside_the_tiers_support_says_which_pixels_and_is_not_converged(engine):
    # sCMOS 'huang' has no density where y + s^2 < 0 (y: counts in electrons above the
    # offset, s^2 = var / gain^2 = 1 here); pixels 1 readout SD below the offset fall there. The
    # scipy path reported such a ROI converged at a sentinel -log L of 1e300
    from bayespsf.cameras import SCMOS

    model = Model(15, 108.0, SCMOS(2.0, 100.0, 4.0, likelihood="huang"))
    rng = np.random.default_rng(1)
    truth = np.array([[0.0, 0.0, 130.0, 130.0, 1000.0, 2.0]])
    counts = 100 + 2.0 * rng.poisson(model.expected(truth)) + rng.normal(0, 2.0, (1, 15, 15))
    assert np.any((counts - 100) / 2.0 + 1.0 < 0)
    fit = fit_mle(counts, model, engine=engine).iloc[0]
    assert fit["status"] == "not converged" and fit["log_likelihood"] == -np.inf
    assert "the 'huang' likelihood gives zero density to" in fit["message"]
    assert "(row, column: (" in fit["message"] and "use a tier with full support" in fit["message"]


@pytest.mark.parametrize("laplace", [True, False])
def test_a_fit_whose_centre_is_not_identified_is_not_converged(laplace):
    # a spot of s0 = 30 nm on 100 nm pixels: some fits collapse to widths of 0.1 pixel, where
    # the centre can move within a pixel at no cost: a NaN Cramér-Rao bound and Laplace SDs of
    # x0 of 2-7e5 nm, where a chain's posterior SD is ~3 nm, are no converged fit
    scene = load_scene("emccd-typical").replace(emitter={"s0x": 30.0, "s0y": 30.0})
    counts, _ = simulate(scene, 30, seed=5)
    model = Model.from_scene(scene)
    fits = fit_mle(counts, model, laplace=laplace)
    side = model.roi * model.pixel_size
    done = fits[fits["status"] == "converged"]
    assert np.isfinite(done[["crlb_x0", "crlb_y0"]]).all().all()
    assert (done[["crlb_x0", "crlb_y0"]] < side).all().all()
    if laplace:
        assert (done[["sd_x0", "sd_y0"]] < side).all().all()
    collapsed = fits[["s_x", "s_y"]].min(axis=1) < 0.2 * model.pixel_size
    assert collapsed.sum() >= 3 and (fits.loc[collapsed, "status"] == "not converged").all()
    # the verdict names the centre where no earlier check of the fit (the iteration limit, the
    # observed information with the Laplace) has stopped it
    lost = fits["message"].str.startswith("the centre is not identified at the fit")
    assert lost.any() and (fits.loc[lost, "status"] == "not converged").all()
    assert (fits.loc[lost, ["s_x", "s_y"]].min(axis=1) < 0.2 * model.pixel_size).all()
    assert fits.loc[lost, "message"].str.contains("narrower than a pixel").all()
    # the same verdicts without the bound's columns (the step information's bound decides)
    bare = fit_mle(counts, model, laplace=laplace, crlb=False)
    assert (bare["status"] == fits["status"]).all() and bare["crlb_x0"].isna().all()


def test_a_model_that_is_not_a_model_and_a_flag_that_is_not_a_bool_are_named():
    # a string for the model failed as an AttributeError on its first use; laplace="no" ran
    # the Laplace (a non-empty string is true)
    from bayespsf import sample_many, sample_posterior

    scene = load_scene("ideal")
    counts, _ = simulate(scene, 2, seed=1)
    for call in (
        lambda: fit_mle(counts, "model"),
        lambda: sample_many(counts, "model", workers=1),
        lambda: sample_posterior(counts[0], "model"),
    ):
        with pytest.raises(ValueError, match=r"model must be a bayespsf.Model .*got str 'model'"):
            call()
    with pytest.raises(ValueError, match="laplace must be True or False, got 'no'"):
        fit_mle(counts, Model.from_scene(scene), laplace="no")


def test_a_rois_fit_does_not_depend_on_the_other_rois_of_its_stack():
    # each ROI's fit (with its Laplace SDs and Cramér-Rao bound) and least squares are the same,
    # to the last bit, in a stack of 203 as alone or in pieces: chunking a stack over workers
    # changes no result (BLAS's matrix-vector product, which rounds a row by its place in
    # the stack, once made the start values differ in the last bits)
    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, 203, seed=5)
    whole, squares = fit_mle(counts, model), fit_lsq(counts, model)
    pieces = [slice(0, 1), slice(1, 8), slice(8, 105), slice(105, 203)]
    alone = pd.concat([fit_mle(counts[s], model) for s in pieces], ignore_index=True)
    pd.testing.assert_frame_equal(alone, whole)
    lsq = pd.concat([fit_lsq(counts[s], model) for s in pieces], ignore_index=True)
    pd.testing.assert_frame_equal(lsq, squares)
    firsts = pd.concat([fit_mle(counts[i : i + 1], model) for i in range(12)], ignore_index=True)
    pd.testing.assert_frame_equal(firsts, whole.iloc[:12])
