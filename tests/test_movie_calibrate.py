"""Offset and readout noise from dark frames, against the simulator's declared camera."""

import numpy as np
import pytest

from bayespsf import scenes
from bayespsf.errors import BayespsfInputError
from bayespsf.movie.calibrate import dark_calibration
from bayespsf.movie.simulate import simulate_movie


def test_dark_frames_give_the_declared_offset_and_readout(tmp_path):
    # paper-movie's camera: offset 100 ADU, readout 50 e- at 12 e-/ADU (4.1667 ADU), whole ADU
    # (rounding adds 1/12 ADU^2). 20 dark frames of 96 x 96 pixels: the estimates' SEs are
    # ~0.01 ADU; the tolerance is 4 SEs
    scene = scenes.load("paper-movie").replace(movie={
        "frames": 2, "height": 96, "width": 96, "molecules": 1, "dark_frames": 20})  # fmt: skip
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
