"""Hostile and unusual inputs to the camera calibration (``calibrate_camera``, ``bayespsf
calibrate``, ``dark_calibration``, photon transfer and Eq. photonConv): each ends in one named
error that says what is wrong and which flag or key fixes it, never a traceback or a silently
wrong camera file."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import cli, load_scene
from bayespsf.calibration import calibrate_camera, dark_calibration, gain_from_molecules
from bayespsf.calibration.gain import _combine
from bayespsf.calibration.photon_transfer import (
    first_adu_per_photon,
    offset_from_cumulants,
    pixel_cumulants,
)
from bayespsf.errors import BayespsfInputError
from bayespsf.simulation import simulate_movie

NO_MOLECULE = "no immobile molecule was found to calibrate the ADU per photon against"


def _movie(folder, molecules: int, bleach_mean: float = 1e6, dark_frames: int = 20):
    """An 80-frame 64 x 64 paper-movie (79 nm pixels in its OME metadata) and its dark
    frames."""
    scene = load_scene("paper-movie").replace(
        movie={
            "frames": 80,
            "height": 64,
            "width": 64,
            "molecules": molecules,
            "dark_frames": dark_frames,
            "bleach_mean": bleach_mean,
            "two_fluorophores": 0.0,
            "moving": 0.0,
        }
    )
    return simulate_movie(scene, seed=1, out=folder / "m").files


@pytest.fixture(scope="module")
def empty(tmp_path_factory):
    """A movie of background alone (no molecule), with 20 dark frames."""
    return _movie(tmp_path_factory.mktemp("empty"), molecules=0)


@pytest.mark.parametrize("with_dark", [True, False])
def test_a_movie_without_molecules_is_named_not_a_key_error(empty, with_dark):
    # was KeyError: 'before_bleach', with or without dark frames
    dark = empty["dark"] if with_dark else None
    with pytest.raises(BayespsfInputError, match=NO_MOLECULE) as info:
        calibrate_camera(empty["movie"], dark, kind="emccd", s0=120.0)
    message = str(info.value)
    assert "detection found no spot on the movie's mean projection" in message
    assert "give a movie of them" in message
    assert "--psf-sd (the spot's SD, 120 nm given)" in message
    assert "--pixel-size (79 nm, from the movie's metadata)" in message
    assert "`bayespsf detect`" in message


def test_the_calibrate_command_names_a_movie_without_molecules(empty, tmp_path):
    out = tmp_path / "camera.toml"
    for dark in (["--dark", str(empty["dark"])], []):
        with pytest.raises(SystemExit, match=NO_MOLECULE):
            cli.main(
                ["calibrate", str(empty["movie"]), *dark, "--psf-sd", "120", "--out", str(out)]
            )
        assert not out.exists()


def test_molecules_that_fail_the_selection_are_named_with_the_rules(tmp_path):
    # one molecule that never bleaches: detected, then left out by the single_step rule
    files = _movie(tmp_path, molecules=1)
    with pytest.raises(BayespsfInputError, match=NO_MOLECULE) as info:
        calibrate_camera(files["movie"], files["dark"], kind="emccd", s0=120.0)
    assert "1 spot(s) were detected but none passed the selection rules" in str(info.value)
    assert "single_step 1" in str(info.value)


def test_constant_dark_frames_are_not_a_readout_of_zero(tmp_path, empty):
    # was readout_sd = 0.0 without a word: a camera whose dark frames never change is not a
    # working EMCCD or sCMOS (their readout noise is never 0); named with the count of
    # constant pixels, the frames, and what to check
    np.save(tmp_path / "constant.npy", np.full((20, 64, 64), 100, np.uint16))
    message = (
        r"dark frames: 4096 of 4096 pixels hold the same count in all 20 frames, so the "
        r"readout noise reads 0 ADU"
    )
    with pytest.raises(BayespsfInputError, match=message) as info:
        dark_calibration(tmp_path / "constant.npy")
    assert "--dark" in str(info.value) and "raw frames" in str(info.value)
    # half the pixels stuck and half noisy: the median pixel still varies, a readout > 0
    half = np.random.default_rng(0).normal(100.0, 4.0, (20, 64, 64)).round()
    half[:, :, :31] = 100.0
    np.save(tmp_path / "half.npy", half)
    assert dark_calibration(tmp_path / "half.npy").readout_sd > 0
    with pytest.raises(SystemExit, match="readout noise reads 0 ADU"):
        cli.main(
            [
                "calibrate",
                str(empty["movie"]),
                "--dark",
                str(tmp_path / "constant.npy"),
                "--psf-sd",
                "120",
                "--out",
                str(tmp_path / "camera.toml"),
            ]
        )
    assert not (tmp_path / "camera.toml").exists()


def test_calibrate_camera_messages_name_the_flag_that_fixes_them(tmp_path, empty):
    missing = tmp_path / "missing.tif"  # the checks before any frame is read
    with pytest.raises(BayespsfInputError, match=r"--fit, --roi"):
        calibrate_camera(missing, kind="emccd", s0=120.0, roi=15, fit=15)
    with pytest.raises(BayespsfInputError, match=r"kind must be one of emccd, scmos \(--kind\)"):
        calibrate_camera(missing, kind="photon", s0=120.0)
    with pytest.raises(BayespsfInputError, match=r"e_per_adu must be a number > 0 \(--e-per-adu"):
        calibrate_camera(missing, kind="emccd", s0=120.0, e_per_adu=0.0)
    with pytest.raises(
        BayespsfInputError, match=r"readout_sd must be a number >= 0 \(electrons; --r"
    ):
        calibrate_camera(missing, kind="emccd", s0=120.0, readout_sd=-1.0)
    with pytest.raises(BayespsfInputError, match=r"--dark or --readout-sd"):
        calibrate_camera(missing, missing, kind="emccd", s0=120.0, readout_sd=50.0)
    # a movie without metadata: no pixel size
    np.save(tmp_path / "plain.npy", np.full((30, 64, 64), 100, np.uint16))
    with pytest.raises(
        BayespsfInputError,
        match=r"metadata give none; state it \(nm\): --pixel-size .*\[geometry\] pixel_size",
    ):
        calibrate_camera(tmp_path / "plain.npy", empty["dark"], kind="emccd", s0=120.0)
    # dark frames of another shape
    np.save(tmp_path / "small.npy", np.full((20, 32, 32), 100, np.uint16))
    with pytest.raises(BayespsfInputError, match=r"the dark frames \(--dark\) must come from"):
        calibrate_camera(empty["movie"], tmp_path / "small.npy", kind="emccd", s0=120.0)
    # the movie as its own dark frames
    with pytest.raises(BayespsfInputError, match=r"no background light.*--dark"):
        calibrate_camera(empty["dark"], empty["dark"], kind="emccd", s0=120.0)


def test_dark_frame_and_photon_transfer_messages_name_the_flag(tmp_path):
    np.save(tmp_path / "one.npy", np.zeros((1, 8, 8), np.uint16))
    with pytest.raises(BayespsfInputError, match=r"at least 2 \(use 20 or more; --dark\)"):
        dark_calibration(tmp_path / "one.npy")
    with pytest.raises(BayespsfInputError, match=r"e_per_adu must be .*--e-per-adu"):
        np.save(tmp_path / "two.npy", np.arange(128, dtype=np.uint16).reshape(2, 8, 8))
        dark_calibration(tmp_path / "two.npy").camera_table(0.0)
    np.save(tmp_path / "short.npy", np.zeros((10, 20, 20)))
    with pytest.raises(
        BayespsfInputError, match=r"needs at least 20 \(or give dark frames: --dark"
    ):
        pixel_cumulants(tmp_path / "short.npy")
    np.save(tmp_path / "flat.npy", np.full((30, 20, 20), 100.0))
    flat = pixel_cumulants(tmp_path / "flat.npy")
    with pytest.raises(BayespsfInputError, match=r"no photon noise.*give dark frames \(--dark\)"):
        first_adu_per_photon(flat, 2.0)
    with pytest.raises(BayespsfInputError, match=r"--readout-sd.*give dark frames \(--dark\)"):
        offset_from_cumulants(flat, 10.0, 2.0)
    with pytest.raises(BayespsfInputError, match=r"at least 100 \(.*--dark"):
        offset_from_cumulants(flat, 10.0, 2.0, mask=np.zeros((20, 20), bool))
    with pytest.raises(BayespsfInputError, match=r"excess must be 2 .*--kind"):
        offset_from_cumulants(flat, 10.0, 3.0)


def test_gain_messages_say_what_would_help(tmp_path, empty):
    # fewer than 2 molecules with 10 frames; the periphery; molecules that disagree
    molecules = pd.DataFrame({"molecule": [0, 1], "x": [20.0, 40.0], "y": [20.0, 40.0]})
    frames = pd.DataFrame({"molecule": [0, 1] * 5, "frame": list(range(10))})
    with pytest.raises(BayespsfInputError, match=r"at least 2 molecules.*bleaching step"):
        gain_from_molecules(empty["movie"], molecules, frames)
    with pytest.raises(BayespsfInputError, match=r"periphery gives the background \(--fit"):
        gain_from_molecules(empty["movie"], molecules, frames, roi=15, fit=15)
    per_molecule = pd.DataFrame(
        {"molecule": [0, 1, 2], "adu_per_photon": [5.0, 20.0, 80.0], "se": [0.1, 0.1, 0.1]}
    )
    with pytest.raises(BayespsfInputError, match=r"fewer than 2 molecules agree within 5 of"):
        _combine(per_molecule, 2.0)


def test_a_spot_sd_estimated_before_the_call_is_reported_as_estimated(tmp_path):
    # the command line estimates the SD, prints it, and hands it on: the advice when no
    # molecule is found must not call it given
    from bayespsf.calibration.camera import calibrate_camera
    from bayespsf.movie.psf_width import PsfWidth

    rng = np.random.default_rng(0)
    background = 100 + 2.0 * rng.poisson(5.0, (80, 48, 48)) + rng.normal(0, 3.0, (80, 48, 48))
    np.save(tmp_path / "flat.npy", np.round(background).astype(np.uint16))
    for s0, words in (
        (PsfWidth(130.0, 3.0, 12, "estimated", 130.0), "estimated"),
        (130.0, "given"),
    ):
        with pytest.raises(BayespsfInputError, match=rf"the spot's SD, 130 nm {words}"):
            calibrate_camera(tmp_path / "flat.npy", kind="scmos", s0=s0, pixel_size=100.0)


def test_frames_that_hold_light_are_refused_as_dark_frames(tmp_path):
    # a movie of molecules over an uneven background, given as --dark, would be taken for dark
    # frames (offset 143 ADU and readout 9.9 where the truth is 100 and 3): its brighter
    # pixels spread more. Dark frames pass: EMCCD ones with clock-induced charge (rare
    # amplified electrons raise some pixels' mean and variance: a check on the plain mean
    # and variance refused them), sCMOS ones with per-pixel offsets and readout variances
    from bayespsf.calibration.dark import LIGHT_RATIO
    from bayespsf.cameras import EMCCD

    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[:64, :64]
    lit = 2.0 + 20.0 * np.exp(-((rows - 20.0) ** 2 + (cols - 40.0) ** 2) / (2 * 16.0**2))
    counts = EMCCD(200.0, 50.0, 100.0, 12.0).sample(np.broadcast_to(lit, (30, 64, 64)), rng)
    np.save(tmp_path / "lit.npy", np.round(counts))
    with pytest.raises(BayespsfInputError, match="dark frames: they hold light"):
        dark_calibration(tmp_path / "lit.npy")
    scene = load_scene("paper-movie").replace(
        camera={"clock_induced_charge": 0.05},
        movie={"frames": 2, "height": 64, "width": 64, "molecules": 1, "dark_frames": 20},
    )
    made = simulate_movie(scene, seed=2, out=tmp_path / "m")
    assert dark_calibration(made.files["dark"]).frames == 20
    offsets = rng.normal(100.0, 5.0, (64, 64))
    sd = np.sqrt(rng.lognormal(np.log(1.5), 0.5, (64, 64)))
    np.save(tmp_path / "scmos_dark.npy", np.round(offsets + sd * rng.standard_normal((5, 64, 64))))
    assert dark_calibration(tmp_path / "scmos_dark.npy").frames == 5
    assert LIGHT_RATIO == 1.5  # the darks above read 0.99-1.21, such movies 2.4-2.5
