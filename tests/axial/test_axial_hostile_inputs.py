"""Hostile and unusual inputs to the z calibration (``bead_rois``, ``step_widths``,
``calibrate``, ``bayespsf calibrate-z``, the calibration file) and where a calibration meets a
model (``z_posterior``, ``z_posteriors``): each ends in a named error that says what is wrong
and what fixes it, or in a result that says what it did."""

import numpy as np
import pandas as pd
import pytest
import tifffile

from bayespsf import Scene, cli, load_scene, simulate
from bayespsf.axial import bead_rois, calibrate, fit_curve, step_widths, z_posterior, z_posteriors
from bayespsf.axial.match import calibration_setup, check_calibration
from bayespsf.errors import BayespsfInputError
from bayespsf.io import read_z_calibration, write_z_calibration
from bayespsf.model import Model
from bayespsf.psf import Defocus
from bayespsf.simulation import simulate_zstack, zstack_positions

ASTIGMATIC = load_scene("astigmatic")  # 100 nm pixels, an EMCCD
BEAD = ASTIGMATIC.replace(emitter={"photons": 20_000.0, "position": "fixed"})
MODEL = Model.from_scene(BEAD)
Z = zstack_positions(-700.0, 200.0, 8, 2)  # 8 steps of 2 frames: enough for a 3-term curve
CAMERA = """[geometry]
pixel_size = 100.0

[camera]
kind = "emccd"
gain = 200.0
readout_sd = 50.0
offset = 100.0
e_per_adu = 12.0
quantize = true
saturation = 65535.0
"""


def _stack(path, second=None):
    """A 45 x 90 stack: the bead's simulated ROIs at (x, y) = (22, 22) and, with ``second``,
    that stack's at (67, 22); every other pixel images no spot."""
    first, _ = simulate_zstack(BEAD, Z, 1)
    dark = BEAD.replace(emitter={"photons": 1e-9})
    frames, _ = simulate(dark, 18 * len(Z), 9)
    movie = frames.reshape(len(Z), 3, 6, 15, 15).transpose(0, 1, 3, 2, 4)
    movie = movie.reshape(len(Z), 45, 90).copy()
    movie[:, 15:30, 15:30] = first
    if second is not None:
        movie[:, 15:30, 60:75] = second
    tifffile.imwrite(path, movie.astype(np.float32))
    return path, first


@pytest.fixture(scope="module")
def two_beads(tmp_path_factory):
    """Two beads of 20 000 and 16 000 photons (comparable) and, in a second stack, of 20 000
    and 2 000 (one clearly the brightest)."""
    folder = tmp_path_factory.mktemp("beads")
    bright, _ = simulate_zstack(BEAD.replace(emitter={"photons": 16_000.0}), Z, 2)
    dim, _ = simulate_zstack(BEAD.replace(emitter={"photons": 2_000.0}), Z, 3)
    comparable, first = _stack(folder / "two.tif", bright)
    clear, _ = _stack(folder / "dim.tif", dim)
    return comparable, clear, first, bright


@pytest.fixture(scope="module")
def calibration():
    """Curves from one bead's stack measured with the 100 nm EMCCD model."""
    counts, _ = simulate_zstack(BEAD, Z, 1)
    steps = step_widths(counts, Z, MODEL, seed=1, workers=1)
    return calibrate(steps, "huang", higher_order=False, source={"stack": "simulated"})


def test_two_comparable_beads_are_named_with_their_positions(two_beads):
    # was: the brightest used without a word that there were two, or which
    comparable, _, first, bright = two_beads
    with pytest.raises(BayespsfInputError, match="2 beads on the stack's mean projection") as info:
        bead_rois(comparable, MODEL, s0=130.0)
    message = str(info.value)
    assert "x 22.0, y 22.0" in message and "x 67.0, y 22.0" in message
    assert "crop the stack to one bead" in message and "bead=(x, y)" in message
    # the caller picks: by position, or the brightest
    rois, bead = bead_rois(comparable, MODEL, s0=130.0, bead=(67.0, 22.0))
    np.testing.assert_array_equal(rois, bright.astype(np.float32))
    assert (int(bead["beads"].iloc[0]), int(bead["rank"].iloc[0])) == (2, 2)
    rois, bead = bead_rois(comparable, MODEL, s0=130.0, bead="brightest")
    np.testing.assert_array_equal(rois, first.astype(np.float32))
    assert (int(bead["beads"].iloc[0]), int(bead["rank"].iloc[0])) == (2, 1)
    with pytest.raises(BayespsfInputError, match=r"no accepted bead within 3 pixels.*x 67.0"):
        bead_rois(comparable, MODEL, s0=130.0, bead=(40.0, 40.0))
    with pytest.raises(BayespsfInputError, match="bead must be"):
        bead_rois(comparable, MODEL, s0=130.0, bead="dimmest")


def test_a_clearly_brightest_bead_is_used_and_says_there_were_others(two_beads):
    _, clear, first, _ = two_beads
    rois, bead = bead_rois(clear, MODEL, s0=130.0)
    np.testing.assert_array_equal(rois, first.astype(np.float32))
    assert int(bead["beads"].iloc[0]) == 2 and int(bead["rank"].iloc[0]) == 1
    assert (bead["x"].iloc[0], bead["y"].iloc[0]) == pytest.approx((22.0, 22.0), abs=0.6)


def test_the_calibrate_z_command_names_two_comparable_beads(two_beads, tmp_path):
    comparable, _, _, _ = two_beads
    (tmp_path / "camera.toml").write_text(CAMERA)
    out = tmp_path / "z.toml"
    args = ["calibrate-z", str(comparable), "--camera", str(tmp_path / "camera.toml")]
    args += ["--psf-sd", "130", "--z-start", "-700", "--z-step", "200", "--frames-per-step"]
    with pytest.raises(SystemExit, match=r"2 beads on the stack's mean projection.*x 67.0"):
        cli.main([*args, "2", "--no-higher-order", "--workers", "1", "--out", str(out)])
    assert not out.exists()


def test_calibrate_z_picks_the_bead_that_bead_names(two_beads, tmp_path, capsys):
    comparable, _, _, _ = two_beads
    (tmp_path / "camera.toml").write_text(CAMERA)
    out = tmp_path / "z.toml"
    args = ["calibrate-z", str(comparable), "--camera", str(tmp_path / "camera.toml")]
    args += ["--psf-sd", "130", "--z-start", "-700", "--z-step", "200", "--frames-per-step"]
    args += ["2", "--no-higher-order", "--workers", "1", "--bead", "67", "22", "--out", str(out)]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert "bead at x 67" in printed and "of 2 beads found" in printed
    source = read_z_calibration(out).source
    assert source["beads found"] == 2
    assert (source["bead x"], source["bead y"]) == pytest.approx((67.0, 22.0), abs=0.6)


def test_the_calibration_records_the_models_pixel_size_and_camera(calibration, tmp_path):
    assert calibration.source["pixel_size"] == 100.0
    assert calibration.source["camera_kind"] == "emccd"
    loaded = read_z_calibration(write_z_calibration(calibration, tmp_path / "z.toml"))
    assert loaded.source["pixel_size"] == 100.0 and loaded.source["camera_kind"] == "emccd"
    assert calibration_setup(loaded)["pixel_size"] == (100.0, "[source] pixel_size")


def test_a_calibration_used_at_another_pixel_size_is_named(calibration, tmp_path):
    # was: z = 608 +- 26 nm for a true 50 nm with a 160 nm model, without a word
    scene = ASTIGMATIC.replace(geometry={"pixel_size": 160.0}, axial={"z": "fixed", "z0": 50.0})
    counts, _ = simulate(scene, 2, 5)
    model = Model.from_scene(scene)
    path = write_z_calibration(calibration, tmp_path / "z.toml")
    loaded = read_z_calibration(path)
    message = (
        rf"the z calibration {path} was made at 100 nm pixels \(\[source\] pixel_size\), but "
        r"the model's pixels are 160 nm"
    )
    with pytest.raises(BayespsfInputError, match=message) as info:
        z_posterior(counts[0], model, loaded)
    assert "set pixel_size = 160 in the calibration file's [source]" in str(info.value)
    with pytest.raises(BayespsfInputError, match="made at 100 nm pixels"):
        z_posteriors(counts, model, calibration, workers=1)
    # stated in the file (the same optics, binned): the check passes
    text = path.read_text().replace("pixel_size = 100.0", "pixel_size = 160.0")
    (tmp_path / "binned.toml").write_text(text)
    check_calibration(read_z_calibration(tmp_path / "binned.toml"), model)
    # a bare Defocus records nothing: not checked
    defocus = Defocus.from_table(ASTIGMATIC.axial, 130.0, 130.0)
    check_calibration(calibrate(_exact_steps(defocus), "huang"), model)


def _exact_steps(defocus):
    z = np.arange(-700.0, 701.0, 100.0)
    s_x, s_y = defocus.widths(z)
    return pd.DataFrame({"z": z, "s_x": s_x, "s_x_sd": 0.5, "s_y": s_y, "s_y_sd": 0.5})


def test_a_calibrate_z_file_of_before_records_its_pixel_size_in_its_camera_file():
    # files written before the [source] keys: the camera file that calibrate-z keeps in
    # [source] "camera file" gives the pixel size and the camera's kind
    defocus = Defocus.from_table(ASTIGMATIC.axial, 130.0, 130.0)
    old = calibrate(_exact_steps(defocus), "huang", source={"camera file": CAMERA})
    model = Model.from_scene(ASTIGMATIC.replace(geometry={"pixel_size": 160.0}))
    with pytest.raises(BayespsfInputError, match=r"made at 100 nm pixels \(the \[geometry\]"):
        check_calibration(old, model)
    table = ASTIGMATIC.to_dict()
    table["camera"] = {"kind": "scmos", "gain": 2.0, "offset": 100.0, "variance": 4.0}
    scmos = Scene.from_dict(table)
    with pytest.raises(BayespsfInputError, match=r"camera of kind emccd .* the model's is scmos"):
        check_calibration(old, Model.from_scene(scmos))
    check_calibration(old, Model.from_scene(ASTIGMATIC))  # the same pixels and camera


def test_a_bad_recorded_pixel_size_is_named(calibration, tmp_path):
    path = write_z_calibration(calibration, tmp_path / "z.toml")
    path.write_text(path.read_text().replace("pixel_size = 100.0", 'pixel_size = "big"'))
    with pytest.raises(BayespsfInputError, match=r"\[source\] pixel_size must be the stack's"):
        read_z_calibration(path)


def test_steps_without_widths_say_why():
    # one frame per step: no joint posterior, so no widths; was "needs at least 6 steps with
    # widths; got 0"
    steps = pd.DataFrame(
        {
            "z": np.arange(8.0),
            "frames": 1,
            "s_x": np.nan,
            "s_x_sd": np.nan,
            "s_y": np.nan,
            "s_y_sd": np.nan,
            "method": "none",
        }
    )
    message = r"8 of 8 steps have no widths \(their joint posterior's method: none 8\)"
    with pytest.raises(BayespsfInputError, match=message) as info:
        calibrate(steps, "huang")
    assert "at least 2 usable frames per step" in str(info.value)
    assert "--frames-per-step" in str(info.value)


def test_curve_and_bead_messages_name_the_flag(tmp_path):
    z = np.linspace(-600.0, 600.0, 5)
    with pytest.raises(BayespsfInputError, match=r"curve must be one of .* \(--curve\)"):
        fit_curve(z, np.full(5, 130.0), np.ones(5), "spline")
    with pytest.raises(BayespsfInputError, match=r"got 5 \(.*--frames-per-step; or three"):
        fit_curve(z, np.full(5, 130.0), np.ones(5), "huang")
    dark = BEAD.replace(emitter={"photons": 1e-9})
    frames, _ = simulate(dark, 9, 9)
    np.save(
        tmp_path / "empty.npy", frames.reshape(1, 3, 3, 15, 15).swapaxes(2, 3).reshape(1, 45, 45)
    )
    with pytest.raises(BayespsfInputError, match=r"no bead was detected.*--psf-sd.*--camera"):
        bead_rois(tmp_path / "empty.npy", MODEL, s0=130.0)
