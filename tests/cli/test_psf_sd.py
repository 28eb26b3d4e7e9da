"""The spot's SD on the command line: estimated from the movie where neither ``--psf-sd`` nor
the camera file states it, reported in the output, ``selection.md`` and ``run.json``."""

import json

import pytest

from bayespsf import cli, load_scene, simulate_movie
from bayespsf.io import CAMERA_KEYS


@pytest.fixture
def movie_and_camera(tmp_path):
    """A 12-frame paper-movie of 96 x 96 pixels (s0 120 nm) and a camera file without
    ``[emitter]``."""
    scene = load_scene("paper-movie").replace(
        movie={"frames": 12, "height": 96, "width": 96, "molecules": 8, "dark_frames": 0}
    )
    made = simulate_movie(scene, seed=5, out=tmp_path / "m")
    camera = {k: v for k, v in scene.to_dict()["camera"].items() if k in CAMERA_KEYS["emccd"]}
    lines = [f"{k} = {v!r}" for k, v in {"kind": "emccd", **camera}.items()]
    (tmp_path / "camera.toml").write_text("[camera]\n" + "\n".join(lines) + "\n")
    return str(made.files["movie"]), str(tmp_path / "camera.toml")


def test_detect_estimates_the_sd_and_reports_it(movie_and_camera, tmp_path, capsys):
    movie, camera = movie_and_camera
    command = ["detect", movie, "--camera", camera, "--rules", "none"]
    assert cli.main([*command, "--out", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    assert "spot SD s0 = " in out and " spots (--psf-sd states it)" in out
    record = json.loads((tmp_path / "d" / "run.json").read_text())
    assert record["run"]["psf sd"] == "estimated"
    width = record["about"]["psf sd"]
    assert width["source"] == "estimated" and width["spots"] >= 5 and width["se"] > 0
    assert abs(width["psf sd"] / 120.0 - 1.0) < 0.05  # as tests/movie/test_psf_width.py
    assert (
        f"The spot SD s0 = {width['psf sd']:.1f}" in (tmp_path / "d" / "selection.md").read_text()
    )
    # the same run again: the estimate is a result, recorded but not compared
    assert cli.main([*command, "--out", str(tmp_path / "d")]) == 0
    # a stated SD is used as it is, and said to be given
    assert cli.main([*command, "--psf-sd", "118", "--out", str(tmp_path / "g")]) == 0
    assert "spot SD s0 = 118 nm, given" in capsys.readouterr().out
    assert json.loads((tmp_path / "g" / "run.json").read_text())["run"]["psf sd"] == 118.0


def test_calibrate_no_longer_requires_the_flag_and_calibrate_z_still_does(
    movie_and_camera, tmp_path
):
    movie, camera = movie_and_camera
    args = cli.build_parser().parse_args(["calibrate", movie, "--out", str(tmp_path / "c.toml")])
    assert args.psf_sd is None
    z = ["calibrate-z", movie, "--camera", camera, "--z-start", "0", "--z-step", "50"]
    with pytest.raises(SystemExit, match=r"give --psf-sd NM \(the bead's in-focus SD\)"):
        cli.main([*z, "--frames-per-step", "1", "--out", str(tmp_path / "z.toml")])
