"""Defocus curves from a bead z-stack, the calibration file, and the round
trip from a simulated stack to the z of simulated molecules."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from test_analysis_pipeline import CAMERA as PAPER_CAMERA

from bayespsf import cli, load_scene, simulate
from bayespsf.axial import bead_rois, calibrate, fit_curve, step_widths, z_posterior
from bayespsf.errors import BayespsfInputError
from bayespsf.io import read_z_calibration, write_z_calibration
from bayespsf.model import Model
from bayespsf.psf import TERMS, Defocus, HuangCurve, PolynomialCurve
from bayespsf.simulation import simulate_zstack, zstack_positions

ASTIGMATIC = load_scene("astigmatic")
BEAD = ASTIGMATIC.replace(emitter={"photons": 20_000.0, "position": "fixed"})
MODEL = Model.from_scene(BEAD)
TRUE = Defocus.from_table(ASTIGMATIC.axial, 130.0, 130.0)


@pytest.fixture(scope="module")
def stack():
    z = zstack_positions(-700.0, 50.0, 29, 5)
    counts, truth = simulate_zstack(BEAD, z, 1)
    return z, counts, truth


@pytest.fixture(scope="module")
def calibrated(stack):
    z, counts, _ = stack
    steps = step_widths(counts, z, MODEL, seed=1, workers=1)
    return calibrate(steps, "huang", higher_order=False, source={"stack": "simulated"})


def test_zstack_positions_repeat_each_step():
    np.testing.assert_array_equal(zstack_positions(-100, 50, 3, 2), [-100, -100, -50, -50, 0, 0])
    with pytest.raises(BayespsfInputError, match="frames_per_step must be a positive integer"):
        zstack_positions(0, 10, 3, 0)
    with pytest.raises(BayespsfInputError, match="step must not be 0"):
        zstack_positions(0, 0, 3, 1)


def test_simulated_stack_keeps_each_frames_z_in_any_order():
    z = np.array([100.0, -100.0, 100.0, 0.0, -100.0])
    counts, truth = simulate_zstack(BEAD, z, 2)
    assert counts.shape == (5, 15, 15)
    np.testing.assert_array_equal(truth["z"], z)
    np.testing.assert_allclose(truth["s_x"], TRUE.x.width(z), rtol=1e-13)
    with pytest.raises(BayespsfInputError, match="no \\[axial\\] table"):
        simulate_zstack(load_scene("emccd-typical"), z, 2)


def test_fit_curve_recovers_exact_widths():
    z = np.linspace(-600, 600, 25)
    curve = HuangCurve(125.0, -180.0, 380.0, 0.2, 0.05)
    fit = fit_curve(z, curve.width(z), np.ones_like(z), "huang")
    np.testing.assert_allclose(
        fit["terms"], [125.0, -180.0, 380.0, 0.2, 0.05], rtol=1e-6, atol=1e-7
    )
    assert fit["chi2"] < 1e-10


def test_fit_curve_covariance_matches_the_scatter_of_its_terms():
    """200 stacks of widths with known Gaussian errors (SD 1 nm): each term's z-score
    (estimate - truth) / SD has SD 1 within 0.8-1.2 (the SD of 200 z-scores has SE 0.05), and
    chi2/dof averages 1 within 0.1."""
    rng = np.random.default_rng(3)
    z = np.linspace(-700, 700, 29)
    curve = PolynomialCurve(130.0, 200.0, 420.0, 0.1)
    scores, ratios = [], []
    for _ in range(200):
        fit = fit_curve(
            z, curve.width(z) + rng.standard_normal(z.size), np.ones_like(z), "polynomial"
        )
        sd = np.sqrt(np.diagonal(fit["covariance"]))
        scores.append((fit["terms"] - [130.0, 200.0, 420.0, 0.1, 0.0]) / sd)
        ratios.append(fit["chi2"] / fit["dof"])
    assert np.all(np.abs(np.std(scores, axis=0) - 1.0) < 0.2)
    assert abs(np.mean(ratios) - 1.0) < 0.1


def test_a_curve_that_does_not_fit_the_stack_is_named():
    z = np.linspace(-700, 700, 29)
    widths = HuangCurve(130.0, -200.0, 400.0).width(z)
    sd = np.full_like(z, 0.5)
    steps = pd.DataFrame({"z": z, "s_x": widths, "s_x_sd": sd, "s_y": widths[::-1], "s_y_sd": sd})
    assert calibrate(steps, "huang").problems == []
    problems = calibrate(steps, "polynomial").problems
    assert len(problems) == 2 and "does not fit the stack's x widths" in problems[0]


def test_calibration_from_a_simulated_stack_recovers_the_curves(calibrated):
    """Each fitted term within 4 of its SDs of the scene's (a 5 x 2 set of z-scores)."""
    fits = calibrated.fits
    for axis, curve in (("x", TRUE.x), ("y", TRUE.y)):
        for term in ("w0", "c", "d"):
            error = (fits.loc[axis, term] - getattr(curve, term)) / fits.loc[axis, f"{term}_sd"]
            assert abs(error) < 4, (axis, term, error)
    assert calibrated.problems == []


def test_calibration_file_round_trips(calibrated, tmp_path):
    path = write_z_calibration(calibrated, tmp_path / "z.toml")
    loaded = read_z_calibration(path)
    assert loaded.defocus == calibrated.defocus and loaded.curve == "huang"
    pd.testing.assert_frame_equal(loaded.fits[list(TERMS)], calibrated.fits[list(TERMS)])
    for axis in ("x", "y"):
        np.testing.assert_array_equal(loaded.covariance[axis], calibrated.covariance[axis])
    np.testing.assert_array_equal(loaded.steps["s_x"], calibrated.steps["s_x"])
    assert loaded.source["stack"] == "simulated" and loaded.source["file"] == str(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('format = "other"', "format must be 'bayespsf z calibration 1'"),
        ('format = "bayespsf z calibration 1"\ncurve = "spline"', "curve must be one of"),
        ('format = "bayespsf z calibration 1"\ncurve = "huang"', r"no table \[x\]"),
        ("= broken", "not a calibration file"),
    ],
)
def test_bad_calibration_files_are_named(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(BayespsfInputError, match=message):
        read_z_calibration(path)
    with pytest.raises(BayespsfInputError, match="no calibration file"):
        read_z_calibration(tmp_path / "missing.toml")


def test_round_trip_z_of_molecules_from_the_calibrated_curves(calibrated, tmp_path):
    """Stack -> calibration file -> z of 25 molecules at random z (2 000 photons): their 95%
    intervals cover at least 21 of 25 (P(<= 20) = 0.007 when calibrated) and every result
    records the calibration."""
    loaded = read_z_calibration(write_z_calibration(calibrated, tmp_path / "z.toml"))
    counts, truth = simulate(ASTIGMATIC, 25, 5)
    model = Model.from_scene(ASTIGMATIC)
    covered = 0
    for k in range(25):
        post = z_posterior(counts[k], model, loaded, seed=k, ess=200)
        s = post.summary().loc["z"]
        covered += s["q2.5"] <= truth["z"].iloc[k] <= s["q97.5"]
        assert post.info["calibration"]["source"]["file"] == str(tmp_path / "z.toml")
    assert covered >= 21


CAMERA = PAPER_CAMERA.replace("pixel_size = 79.0", "pixel_size = 100.0")  # the scene's


def _tiff_stack(counts, path):
    """The stack's ROIs at the centre of 45 x 45 frames whose other pixels image no spot."""
    dark = BEAD.replace(emitter={"photons": 1e-9})
    frames, _ = simulate(dark, 9 * len(counts), 9)
    movie = frames.reshape(len(counts), 3, 3, 15, 15).transpose(0, 1, 3, 2, 4)
    movie = movie.reshape(len(counts), 45, 45).copy()
    movie[:, 15:30, 15:30] = counts
    tifffile.imwrite(path, movie.astype(np.float32))
    return path


def test_bead_rois_find_the_bead_of_a_tiff_stack(stack, tmp_path):
    """The bead's ROIs cut from a 45 x 45 movie are the simulated ones, pixel for pixel."""
    _, counts, _ = stack
    path = _tiff_stack(counts, tmp_path / "stack.tif")
    rois, bead = bead_rois(path, MODEL, s0=130.0, roi=25)
    assert (bead["x"].iloc[0], bead["y"].iloc[0]) == pytest.approx((22.0, 22.0), abs=0.6)
    np.testing.assert_array_equal(rois, counts.astype(np.float32))


def test_calibrate_z_command_writes_the_file_analyze_reads(stack, tmp_path, capsys, monkeypatch):
    """As documented, without --out: the default file z-calibration.toml in the folder it
    runs in."""
    _, counts, _ = stack
    path = _tiff_stack(counts, tmp_path / "stack.tif")
    (tmp_path / "camera.toml").write_text(CAMERA)
    monkeypatch.chdir(tmp_path)
    args = [
        "calibrate-z",
        "stack.tif",
        "--camera",
        "camera.toml",
        "--psf-sd",
        "130",
        "--z-start",
        "-700",
        "--z-step",
        "50",
        "--frames-per-step",
        "5",
        "--no-higher-order",
        "--workers",
        "1",
    ]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("x: w0 ") and "wrote z-calibration.toml" in printed
    loaded = read_z_calibration(tmp_path / "z-calibration.toml")
    assert path.exists()
    for axis, curve in (("x", TRUE.x), ("y", TRUE.y)):
        fit = loaded.fits.loc[axis]
        assert (
            abs(fit["c"] - curve.c) < 4 * fit["c_sd"] and abs(fit["w0"] - 130.0) < 4 * fit["w0_sd"]
        )
    assert loaded.source["command"].startswith("bayespsf calibrate-z ")
    bad = [*args, "--out", str(tmp_path / "z2.toml")]
    bad[bad.index("--frames-per-step") + 1] = "4"
    with pytest.raises(SystemExit, match="145 frames, not a whole number of steps"):
        cli.main(bad)
    bad[bad.index("--frames-per-step") + 1] = "0"
    with pytest.raises(SystemExit, match="--frames-per-step must be >= 1, got 0"):
        cli.main(bad)


def test_the_calibrations_uncertainty_widens_z_by_what_the_stack_left_unknown(calibrated):
    """With each axis's focus c uncertain by 30 nm (SD), z's posterior SD grows as the delta
    method says, sqrt(sd0^2 + s_c^2), s_c^2 = sum over axes of (dz/dc)^2 30^2, with dz/dc that
    axis's weight in the fit of z: 1/2 at z = 0, where the two slopes are equal in size, so
    s_c^2 = 30^2 / 2 (within 15%). With the stack's own term SDs (~1 nm) the marginalised
    posterior equals the plain one within Monte Carlo error."""
    counts, _ = simulate(
        ASTIGMATIC.replace(axial={"z": "fixed", "z0": 0.0}, emitter={"photons": 10_000.0}), 1, 6
    )
    model = Model.from_scene(ASTIGMATIC)
    plain = z_posterior(counts[0], model, calibrated, seed=1).summary().loc["z", "sd"]
    same = z_posterior(counts[0], model, calibrated, seed=1, calibration_uncertainty=True)
    assert same.info["calibration_uncertainty"] and same.info["converged"]
    # the stack's own term SDs are ~1 nm: they widen an SD of ~10 nm by under 1%
    assert same.summary().loc["z", "sd"] == pytest.approx(plain, rel=0.1)
    wide = copy.deepcopy(calibrated)
    for axis in ("x", "y"):
        wide.covariance[axis][1, 1] = 30.0**2
        wide.fits.loc[axis, "c_sd"] = 30.0
    post = z_posterior(counts[0], model, wide, seed=1, calibration_uncertainty=True)
    assert post.info["converged"], post.info
    expected = np.sqrt(plain**2 + 30.0**2 / 2)
    assert post.summary().loc["z", "sd"] == pytest.approx(expected, rel=0.15)
    with pytest.raises(
        BayespsfInputError, match="calibration_uncertainty needs a DefocusCalibration"
    ):
        z_posterior(counts[0], model, TRUE, calibration_uncertainty=True)
