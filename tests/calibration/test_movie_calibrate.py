"""Offset and readout noise from dark frames, against the simulator's declared camera."""

import numpy as np
import pytest

from bayespsf import load_scene
from bayespsf.calibration import dark_calibration
from bayespsf.errors import BayespsfInputError
from bayespsf.simulation import simulate_movie


def test_dark_frames_give_the_declared_offset_and_readout(tmp_path):
    # paper-movie's camera: offset 100 ADU, readout 50 e- at 12 e-/ADU (4.1667 ADU), whole ADU
    # (rounding adds 1/12 ADU^2). 20 dark frames of 96 x 96 pixels: the estimates' SEs are
    # ~0.01 ADU; the tolerance is 4 SEs
    scene = load_scene("paper-movie").replace(
        movie={"frames": 2, "height": 96, "width": 96, "molecules": 1, "dark_frames": 20}
    )
    files = simulate_movie(scene, seed=4, out=tmp_path / "m").files
    dark = dark_calibration(files["dark"])
    expected_sd = np.sqrt((50.0 / 12.0) ** 2 + 1 / 12)
    assert dark.frames == 20 and dark.offset_map.shape == (96, 96)
    assert abs(dark.offset - 100.0) <= 4 * dark.offset_se
    assert abs(dark.readout_sd - expected_sd) <= 4 * dark.readout_sd_se
    table = dark.camera_table(12.0)
    assert table["readout_sd"] == pytest.approx(12.0 * dark.readout_sd)


def test_too_few_dark_frames_are_named(tmp_path):
    np.save(tmp_path / "one.npy", np.zeros((1, 8, 8), dtype=np.uint16))
    with pytest.raises(BayespsfInputError, match="at least 2"):
        dark_calibration(tmp_path / "one.npy")
    with pytest.raises(BayespsfInputError, match="e_per_adu"):
        np.save(tmp_path / "two.npy", np.arange(128, dtype=np.uint16).reshape(2, 8, 8))
        dark_calibration(tmp_path / "two.npy").camera_table(0.0)


def test_flat_fields_give_each_pixels_gain_with_calibrated_errors(tmp_path):
    # an sCMOS of per-pixel gains 1.6..2.6 ADU per photoelectron, offsets 90..110 ADU and
    # variances 4..16 ADU^2 (Huang et al. 2013's model, drawn by the camera law itself); 40 dark
    # frames and 4 flat levels of 2..300 photoelectrons, 150 frames each, on 24 x 24 pixels.
    # Against the declared maps: the z-scores' mean within 4 of its SEs (1 / sqrt(576)) of 0,
    # and their SD within 0.85..1.15 (the normal-weights SE is exact only to O(1/K))
    from bayespsf.calibration import flat_field_gain
    from bayespsf.cameras import SCMOS

    rng = np.random.default_rng(3)
    shape = (24, 24)
    gain = rng.uniform(1.6, 2.6, shape)
    camera = SCMOS(gain, rng.uniform(90, 110, shape), rng.uniform(4, 16, shape))
    np.save(tmp_path / "dark.npy", camera.sample(np.zeros((40, *shape)), rng))
    flats = []
    for k, level in enumerate((2.0, 20.0, 100.0, 300.0)):
        np.save(tmp_path / f"flat{k}.npy", camera.sample(np.full((150, *shape), level), rng))
        flats.append(tmp_path / f"flat{k}.npy")
    dark = dark_calibration(tmp_path / "dark.npy")
    found = flat_field_gain(flats, dark)
    assert found.levels == 4 and found.frames == (150,) * 4
    z = ((found.gain_map - gain) / found.gain_se_map).ravel()
    assert abs(z.mean()) < 4 / np.sqrt(z.size) and 0.85 < z.std(ddof=1) < 1.15, (z.mean(), z.std())
    per_pixel = found.camera(dark)
    per_adu, offset = per_pixel.photons_per_adu()
    np.testing.assert_array_equal(offset, dark.offset_map)
    np.testing.assert_allclose(per_adu, 1 / found.gain_map)
    with pytest.raises(BayespsfInputError, match="sequence of movies"):
        flat_field_gain(tmp_path / "flat0.npy", dark)
    with pytest.raises(BayespsfInputError, match=r"flats\[0\]: .* no light to calibrate"):
        flat_field_gain([tmp_path / "dark.npy"], dark)
    with pytest.raises(BayespsfInputError, match="dark must be a DarkCalibration"):
        flat_field_gain(flats, tmp_path / "dark.npy")
    np.save(tmp_path / "small.npy", np.zeros((5, 8, 8)))
    with pytest.raises(BayespsfInputError, match=r"flats\[0\]: frames \(8, 8\)"):
        flat_field_gain([tmp_path / "small.npy"], dark)
