"""ADU per photon from a movie's molecules (bayespsf.calibration.gain), against the simulator's
declared camera: paper-movie's EMCCD has gain 200 and 12 e- per ADU, so M = 16.667 ADU per
photon, and its molecules' photons fluctuate uniformly within +-20% between frames (a relative
variance of 0.2^2 / 3 = 0.01333)."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import cli, load_scene
from bayespsf.calibration import gain_from_molecules
from bayespsf.errors import BayespsfInputError
from bayespsf.io import camera_scene, read_camera_file
from bayespsf.model import Model
from bayespsf.simulation import simulate_movie

M_TRUE = 200.0 / 12.0


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """150 frames of 128 x 128 pixels, 12 single immobile molecules (N 500-5000 per frame)
    bleaching after 100 frames on average; the truth gives each molecule's frames before its
    bleaching frame (the frame that holds part of its exposure excluded)."""
    scene = load_scene("paper-movie").replace(
        movie={
            "frames": 150,
            "height": 128,
            "width": 128,
            "molecules": 12,
            "bleach_mean": 100.0,
            "two_fluorophores": 0.0,
            "moving": 0.0,
            "dark_frames": 20,
        }
    )
    truth = simulate_movie(scene, seed=5, out=tmp_path_factory.mktemp("gain") / "m")
    frames = pd.read_csv(truth.files["truth"])
    bleach = truth.molecules.set_index("molecule")["bleach_frame"]
    last = frames["molecule"].map(bleach.astype(float)).fillna(np.inf) - 1
    before = frames[frames["frame"] < last]
    return truth.files["movie"], truth.molecules, before, truth.files["dark"]


def test_the_declared_adu_per_photon_lies_in_the_interval(movie):
    # one movie: the truth inside the 95% interval (a biased estimator, e.g. Eq. photonConv
    # without the fluctuation term, reads ~30% high here), and the interval narrow (< 10%)
    path, molecules, before, _ = movie
    gain = gain_from_molecules(path, molecules, before)
    low, high = gain.interval
    assert low <= M_TRUE <= high, str(gain)
    assert high - low < 0.1 * M_TRUE
    assert not gain.per_molecule["outlier"].any() and len(gain.per_molecule) >= 10
    # the fitted photon fluctuation: its inverse-variance mean within 4 SEs of 0.2^2 / 3
    phi = gain.per_molecule["fluctuation"]
    assert abs(phi.mean() - 0.04 / 3) < 4 * phi.std(ddof=1) / np.sqrt(len(phi))
    assert "ADU per photon" in str(gain) and "DeSantis" in str(gain)


def test_frames_across_a_bleaching_step_are_a_fluctuation_not_an_outlier(movie):
    # all frames of one bleaching molecule: the step adds p (1 - p) S_i^2 to its pixels'
    # variance, which the fluctuation term takes; its estimate stays within 4 SEs of the truth
    path, molecules, before, _ = movie
    bleached = molecules.loc[molecules["bleach_frame"].notna(), "molecule"].iloc[0]
    every = pd.DataFrame({"molecule": bleached, "frame": np.arange(150)})
    frames = pd.concat([before[before["molecule"] != bleached], every])
    row = gain_from_molecules(path, molecules, frames).per_molecule.set_index("molecule")
    assert not row.loc[bleached, "outlier"]
    assert abs(row.loc[bleached, "adu_per_photon"] - M_TRUE) < 4 * row.loc[bleached, "se"]
    assert row.loc[bleached, "fluctuation"] > 0.1  # p (1 - p) >~ 0.1 for p in 0.1..0.9


def test_moving_molecules_are_flagged_and_left_out(tmp_path):
    # 5 of 9 molecules walk 20 nm per frame: their pixels' variance is not photon noise
    # (measured 47-241 ADU per photon); exactly they are flagged, and the 4 others cover M
    scene = load_scene("paper-movie").replace(
        movie={
            "frames": 150,
            "height": 128,
            "width": 128,
            "molecules": 9,
            "bleach_mean": 100.0,
            "two_fluorophores": 0.0,
            "moving": 0.25,
            "moving_step": 20.0,
            "dark_frames": 0,
        }
    )
    truth = simulate_movie(scene, seed=5, out=tmp_path / "m")
    frames = pd.read_csv(truth.files["truth"])
    bleach = truth.molecules.set_index("molecule")["bleach_frame"].astype(float)
    before = frames[frames["frame"] < frames["molecule"].map(bleach).fillna(np.inf) - 1]
    gain = gain_from_molecules(truth.files["movie"], truth.molecules, before)
    flagged = gain.per_molecule.set_index("molecule")["outlier"]
    moving = truth.molecules.set_index("molecule")["moving"].astype(bool)
    assert moving.sum() == 5 and flagged.equals(moving.reindex(flagged.index).rename("outlier"))
    assert gain.interval[0] <= M_TRUE <= gain.interval[1]


def test_bad_inputs_are_named(movie):
    path, molecules, before, _ = movie
    with pytest.raises(BayespsfInputError, match="at least 2 molecules"):
        gain_from_molecules(path, molecules, before[before["frame"] < 5])
    with pytest.raises(BayespsfInputError, match=r"frames must be a table with columns"):
        gain_from_molecules(path, molecules, before.drop(columns="frame"))
    with pytest.raises(BayespsfInputError, match="excess must be"):
        gain_from_molecules(path, molecules, before, excess=0.0)
    with pytest.raises(BayespsfInputError, match="periphery"):
        gain_from_molecules(path, molecules, before, roi=15, fit=15)


def test_calibrate_writes_a_camera_file_that_detect_reads(movie, tmp_path, capsys):
    # dark frames give offset 100 ADU and readout 50 e- / 12 (+ 1/12 ADU^2 of rounding); the
    # molecules give M; the file states gain = M e_per_adu, and `bayespsf detect` reads it
    path, _, _, dark = movie
    out = tmp_path / "cal" / "camera.toml"
    assert (
        cli.main(
            [
                "calibrate",
                str(path),
                "--dark",
                str(dark),
                "--psf-sd",
                "120",
                "--e-per-adu",
                "12",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "ADU per photon" in capsys.readouterr().out
    text = out.read_text()
    assert text.startswith("# made by: bayespsf calibrate ") and "--dark" in text
    table = read_camera_file(str(out))
    camera = table["camera"]
    assert camera["kind"] == "emccd" and camera["e_per_adu"] == 12.0
    assert table["geometry"]["pixel_size"] == 79.0  # from the movie's OME metadata
    low, high = (float(v) for v in text.split("95% interval ")[1].split(")")[0].split(" to "))
    # the interval is printed to 6 significant figures: its midpoint is known to ~5e-6
    assert low <= M_TRUE <= high
    assert camera["gain"] == pytest.approx(12.0 * (low + high) / 2, rel=1e-5)
    assert camera["offset"] == pytest.approx(100.0, abs=0.05)
    assert camera["readout_sd"] == pytest.approx(12.0 * np.sqrt((50 / 12) ** 2 + 1 / 12), rel=0.01)
    model = camera_scene(table, str(out), 15)  # what `bayespsf detect --camera` builds
    assert model.camera["gain"] == camera["gain"]


def test_calibrate_inputs_that_cannot_work_are_one_line(movie, tmp_path):
    path, _, _, dark = movie
    np.save(tmp_path / "small.npy", np.full((20, 64, 64), 100, np.uint16))
    for args, words in (
        (["--dark", str(tmp_path / "small.npy")], r"dark frames \(64, 64\) and movie frames"),
        (["--dark", str(dark), "--kind", "photon"], None),
        (["--dark", str(dark), "--e-per-adu", "0"], "e_per_adu must be"),
        (["--dark", str(dark), "--quantum-efficiency", "1.5"], "--quantum-efficiency must be"),
        (["--readout-sd", "-1"], "readout_sd must be a number >= 0"),
        (["--dark", str(dark), "--readout-sd", "50"], "the dark frames measure the readout"),
        (["--dark", str(path), "--out", str(tmp_path)], "is a folder"),
    ):
        with pytest.raises(SystemExit, match=words):
            cli.main(["calibrate", str(path), "--psf-sd", "120", *args])
    with pytest.raises(SystemExit, match="no background light"):  # the movie as its own dark
        cli.main(
            [
                "calibrate",
                str(dark),
                "--dark",
                str(dark),
                "--psf-sd",
                "120",
                "--out",
                str(tmp_path / "c.toml"),
            ]
        )


def test_calibrate_an_scmos_camera_without_dark_frames(tmp_path):
    # a CCD/sCMOS of one gain 2.17 ADU per photoelectron, offset 100 ADU, variance 12 ADU^2
    # (+1/12 ADU^2 of rounding), a Poisson background of 3 photons and no dark frames
    # (`bayespsf calibrate` without --dark): excess noise 1; the file states gain, offset and
    # variance, the offset and the readout each within 4 of the SEs its comments state, the
    # gain's 95% interval covering 2.17, and the declared quantum efficiency
    from bayespsf import Scene

    table = load_scene("paper-movie").to_dict()
    table["camera"] = {
        "kind": "scmos",
        "gain": 2.17,
        "offset": 100.0,
        "variance": 12.0,
        "quantize": True,
        "saturation": 65535.0,
    }
    table["background"] = {"kind": "poisson", "mean": 3.0}
    table["movie"].update(
        frames=150,
        height=128,
        width=128,
        molecules=12,
        bleach_mean=100.0,
        two_fluorophores=0.0,
        moving=0.0,
        dark_frames=0,
    )
    files = simulate_movie(Scene.from_dict(table), seed=5, out=tmp_path / "s").files
    out = tmp_path / "camera.toml"
    assert (
        cli.main(
            [
                "calibrate",
                str(files["movie"]),
                "--kind",
                "scmos",
                "--psf-sd",
                "120",
                "--quantum-efficiency",
                "0.8",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    text = out.read_text()
    assert "no dark frames" in text
    low, high = (float(v) for v in text.split("95% interval ")[1].split(")")[0].split(" to "))
    assert low <= 2.17 <= high
    camera = read_camera_file(str(out))["camera"]
    assert set(camera) == {"kind", "gain", "offset", "variance", "quantum_efficiency"}
    assert camera["kind"] == "scmos" and camera["quantum_efficiency"] == 0.8
    offset_se = float(text.split("offset ")[1].split(" +- ")[1].split(" ADU")[0])
    readout, readout_se = (
        float(v) for v in text.split("readout ")[1].split(" ADU")[0].split(" +- ")
    )
    assert abs(camera["offset"] - 100.0) < 4 * offset_se
    assert readout == pytest.approx(np.sqrt(camera["variance"]))
    assert abs(readout - np.sqrt(12.0 + 1 / 12)) < 4 * readout_se
    assert "# N and b: incident photons (quantum efficiency 0.8 as declared" in text
    scene = Scene.loads(text.replace("[geometry]", "[geometry]\nroi = 15"))
    assert Model.from_scene(scene).photon_unit_label == "incident photons (quantum efficiency 0.8)"
