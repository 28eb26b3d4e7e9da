"""The posterior of (x0, y0, z, N, b) with widths from the calibration."""

from __future__ import annotations

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.axial import crlb_z, z_posterior
from bayespsf.axial.posterior import _Problem
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.solver import gradient, maximise
from bayespsf.model import Model
from bayespsf.psf import Defocus

ASTIGMATIC = load_scene("astigmatic")
MODEL = Model.from_scene(ASTIGMATIC)
DEFOCUS = Defocus.from_table(ASTIGMATIC.axial, 130.0, 130.0)


def _at(z0: float, photons: float):
    """The astigmatic scene with the emitter at one z."""
    axial = {k: v for k, v in ASTIGMATIC.axial.items() if k not in ("z_low", "z_high")}
    return ASTIGMATIC.replace(
        axial={**axial, "z": "fixed", "z0": z0}, emitter={**ASTIGMATIC.emitter, "photons": photons}
    )


def test_log_posterior_is_the_camera_likelihood_at_the_curves_widths_plus_the_prior():
    counts, _ = simulate(ASTIGMATIC, 1, 0)
    problem = _Problem(MODEL.check_counts(counts[0]), MODEL, DEFOCUS, (-800.0, 800.0))
    v = np.array([[10.0, -20.0, 150.0, np.log(1800.0), 9.0], [0.0, 0.0, -700.0, np.log(50.0), 0.0]])
    s_x, s_y = DEFOCUS.widths(v[:, 2])
    params = np.column_stack([v[:, 0], v[:, 1], s_x, s_y, np.exp(v[:, 3]), v[:, 4]])
    # the model's priors of x0, y0 and b are uniform, N's log-uniform (-log N); + log N: d N
    expected = MODEL.log_likelihood(counts[0], params) - np.log(params[:, 4]) + v[:, 3]
    np.testing.assert_allclose(problem.log_posterior(v), expected, rtol=1e-12)
    outside = v.copy()
    outside[:, 2] = [-801.0, 900.0]
    assert np.all(problem.log_posterior(outside) == -np.inf)


def test_a_fit_with_held_widths_keeps_them_and_is_stationary_in_the_others():
    counts, truth = simulate(_at(100.0, 3000.0), 4, 1)
    starts = truth[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy() * [1, 1, 1.1, 0.9, 1, 1]
    held = np.array([False, False, True, True, False, False])
    fit, _, converged, _ = maximise(MODEL, MODEL.check_counts(counts), starts, held)
    assert converged.all()
    np.testing.assert_array_equal(fit[:, 2:4], starts[:, 2:4])
    g = gradient(MODEL, MODEL.check_counts(counts), fit)[:, [0, 1, 4, 5]]
    # d(-log L) per pixel of position, per unit of log N and per photon of b: ~0 at the fit
    assert np.all(np.abs(g[:, :2]) * MODEL.pixel_size < 1e-3)
    assert np.all(np.abs(g[:, 2] * fit[:, 4]) < 1e-3) and np.all(np.abs(g[:, 3]) < 1e-2)


def test_z_is_calibrated_on_an_astigmatic_psf():
    """40 molecules with z uniform in [-600, 600] nm at 2 000 photons: the z-scores of the
    posterior mean have SD 1 (within 0.75-1.3: the SD of 40 normal z-scores has SE 0.11, so
    this is +-2.5 SE) and 95% intervals cover at least 34 of 40 (P(<= 33) = 0.01 when
    calibrated)."""
    counts, truth = simulate(ASTIGMATIC, 40, 2)
    scores, covered = [], 0
    for k in range(40):
        post = z_posterior(counts[k], MODEL, DEFOCUS, seed=k, ess=300)
        assert post.info["converged"], post.info
        s = post.summary().loc["z"]
        scores.append((s["mean"] - truth["z"].iloc[k]) / s["sd"])
        covered += s["q2.5"] <= truth["z"].iloc[k] <= s["q97.5"]
    assert 0.75 < np.std(scores) < 1.3 and abs(np.mean(scores)) < 0.5
    assert covered >= 34


def test_z_sd_meets_its_cramer_rao_bound_when_bright_and_out_of_focus():
    """At 10 000 photons, 300 nm from each focus, the posterior SD is within 10% of sqrt CRLB
    (the mean of 8 posteriors: each SD is itself within a few % of the bound)."""
    scene = _at(-500.0, 10_000.0)
    counts, _ = simulate(scene, 8, 3)
    model = Model.from_scene(scene)
    bound = crlb_z(model, DEFOCUS, np.array([0.0, 0.0, -500.0, 10_000.0, 10.0]))["z"]
    sds = [
        z_posterior(c, model, DEFOCUS, seed=k).summary().loc["z", "sd"]
        for k, c in enumerate(counts)
    ]
    assert np.mean(sds) / bound == pytest.approx(1.0, abs=0.1)


def test_the_papers_symmetric_defocus_reports_both_modes():
    """z = +-250 nm give the same image: the posterior puts half its mass on each (within 4 SE
    of an ESS-400 estimate, 4 x 0.025) and its |z| centres near 250 nm."""
    typical = load_scene("emccd-typical")
    scene = typical.replace(
        axial={"z": "fixed", "z0": 250.0}, emitter={**typical.emitter, "photons": 5000.0}
    )
    counts, _ = simulate(scene, 2, 4)
    model = Model.from_scene(scene)
    defocus = Defocus.symmetric(130.0, 400.0)
    for k, c in enumerate(counts):
        post = z_posterior(c, model, defocus, z_range=(-600.0, 600.0), seed=k)
        assert post.info["plane"] == 0.0
        assert post.info["above_plane"] == pytest.approx(0.5, abs=0.1)
        z = post.draws["z"].to_numpy()
        assert 0.35 < np.mean(z > 0) < 0.65
        assert abs(np.median(np.abs(z)) - 250.0) < 60.0  # |z|'s SD here is ~20 nm


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"defocus": "huang"}, "defocus must be a Defocus or a DefocusCalibration"),
        ({"z_range": (100.0, -100.0)}, "z_range must have low < high"),
        ({"z_range": 5}, "z_range must be two numbers"),
        ({"ess": 5}, "ess must be a number in"),
        ({"counts": np.zeros((3, 3))}, "counts"),
        (
            {"defocus": Defocus(*[DEFOCUS.x.__class__(130.0, 0.0, 400.0, A=-5.0)] * 2)},
            "outside this defocus curve's domain",
        ),
    ],
)
def test_bad_inputs_are_named(kwargs, message):
    counts, _ = simulate(ASTIGMATIC, 1, 0)
    args = {"counts": counts[0], "model": MODEL, "defocus": DEFOCUS, **kwargs}
    with pytest.raises(BayespsfInputError, match=message):
        z_posterior(args.pop("counts"), args.pop("model"), args.pop("defocus"), **args)


def test_z_posteriors_names_a_bad_range_or_calibration_before_any_roi_runs():
    from bayespsf.axial import z_posteriors

    counts, _ = simulate(ASTIGMATIC, 2, 0)
    with pytest.raises(BayespsfInputError, match="z_range must have low < high"):
        z_posteriors(counts, MODEL, DEFOCUS, z_range=(100.0, -100.0), workers=1)
    with pytest.raises(
        BayespsfInputError, match="calibration must be a DefocusCalibration or a Defocus"
    ):
        z_posteriors(counts, MODEL, "z.toml", workers=1)
