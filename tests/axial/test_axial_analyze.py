"""`bayespsf analyze --z-calibration` puts each frame's z posterior into the
localisation tables (picasso's z and lpz, ThunderSTORM's z [nm]) and records the calibration."""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))
from test_analysis_pipeline import CAMERA

from bayespsf import Scene, cli, load_scene
from bayespsf.axial import calibrate
from bayespsf.io import write_z_calibration
from bayespsf.psf import Defocus
from bayespsf.simulation import match_truth, simulate_movie

AXIAL = {
    "curve": "huang",
    "focus_x": -200.0,
    "focus_y": 200.0,
    "z": "uniform",
    "z_low": -400.0,
    "z_high": 400.0,
}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Two immobile molecules at their own z in a 40-frame astigmatic paper-movie, analysed
    with a calibration of the simulator's own curves (fitted to their exact widths, 0.3 nm
    errors) and Laplace posteriors of 100 draws."""
    folder = tmp_path_factory.mktemp("analyze_z")
    table = load_scene("paper-movie").to_dict()
    table["axial"] = AXIAL
    table["movie"].update(
        frames=40,
        height=64,
        width=64,
        molecules=2,
        bleach_mean=0.0,
        two_fluorophores=0.0,
        moving=0.0,
        dark_frames=0,
        photons_low=3000.0,
        photons_high=3000.0,
    )
    scene = Scene.from_dict(table)
    made = simulate_movie(scene, seed=4, out=folder / "m")
    defocus = Defocus.from_table(scene.axial, 120.0, 120.0)
    z = np.arange(-700.0, 701.0, 50.0)
    s_x, s_y = defocus.widths(z)
    steps = pd.DataFrame({"z": z, "s_x": s_x, "s_x_sd": 0.3, "s_y": s_y, "s_y_sd": 0.3})
    path = write_z_calibration(
        calibrate(steps, "huang", source={"stack": "exact"}), folder / "z.toml"
    )
    (folder / "camera.toml").write_text(CAMERA)
    out = folder / "out"
    code = cli.main(
        [
            "analyze",
            str(made.files["movie"]),
            "--camera",
            str(folder / "camera.toml"),
            "--psf-sd",
            "150",
            "--min-valid-frames",
            "25",
            "--method",
            "laplace",
            "--ess",
            "100",
            "--z-calibration",
            str(path),
            "--z-range",
            "-600",
            "600",
            "--skip-rule",
            "single_step",
            "--skip-rule",
            "equal_widths",
            "--skip-rule",
            "width_range",
            "--workers",
            "1",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    return out, made, path


def test_z_columns_are_in_every_table(run):
    out, _, path = run
    locs = pd.read_parquet(out / "locs.parquet")
    assert list(locs.columns[:11]) == [
        "frame",
        "x",
        "y",
        "photons",
        "sx",
        "sy",
        "bg",
        "lpx",
        "lpy",
        "z",
        "lpz",
    ]
    assert locs["z_converged"].all() and (locs["z_khat"] <= 0.7).all()
    assert (locs["z_q0025"] < locs["z"]).all() and (locs["z"] < locs["z_q0975"]).all()
    csv = pd.read_csv(out / "locs.csv")
    np.testing.assert_allclose(csv["z [nm]"], locs["z"], rtol=1e-6)
    np.testing.assert_allclose(csv["uncertainty_z [nm]"], locs["lpz"], rtol=1e-6)
    info = yaml.safe_load((out / "locs.yaml").read_text())
    assert info["bayespsf"]["z calibration"]["source"]["file"] == str(path)


def test_z_matches_each_molecules_truth(run):
    """Each frame's 95% interval covers its molecule's true z in at least 85% of the frames
    (about 70 frames: P(< 85%) ~ 0.01 when calibrated), and |z - truth| < 5 lpz in all."""
    out, made, _ = run
    locs = pd.read_parquet(out / "locs.parquet")
    molecules = pd.read_csv(out / "molecules.csv")
    row = match_truth(molecules, made.molecules)
    assert np.all(row >= 0)
    truth = made.molecules.iloc[row].set_index(molecules["molecule"])["z"]
    true_z = locs["molecule"].map(truth)
    covered = (locs["z_q0025"] <= true_z) & (true_z <= locs["z_q0975"])
    assert covered.mean() >= 0.85, covered.mean()
    assert (np.abs(locs["z"] - true_z) < 5 * locs["lpz"]).all()


def test_picasso_opens_z(run):
    picasso_io = pytest.importorskip("picasso.io")
    out, _, _ = run
    locs, _ = picasso_io.load_locs(str(out / "locs.hdf5"))
    parquet = pd.read_parquet(out / "locs.parquet")
    np.testing.assert_array_equal(locs["z"].to_numpy(), parquet["z"].to_numpy())
    np.testing.assert_array_equal(locs["lpz"].to_numpy(), parquet["lpz"].to_numpy())


def test_a_z_range_is_checked_before_the_detection_and_needs_a_calibration(run, tmp_path):
    # a backwards range with a calibration is refused before anything is written (it was
    # refused after the detection, its folder then holding a run that a corrected rerun could
    # not resume); without a calibration the range has nothing to be the prior of
    _, made, path = run
    (tmp_path / "camera.toml").write_text(CAMERA)
    given = [str(made.files["movie"]), "--camera", str(tmp_path / "camera.toml")]
    given += ["--psf-sd", "150", "--workers", "1", "--out", str(tmp_path / "out")]
    with pytest.raises(
        SystemExit, match=r"--z-range must have low < high; got \(800\.0, -800\.0\)"
    ):
        cli.main(["analyze", *given, "--z-calibration", str(path), "--z-range", "800", "-800"])
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    with pytest.raises(SystemExit, match="--z-range is the prior of z: it goes with --z-cali"):
        cli.main(["analyze", *given, "--z-range", "-500", "500"])


@pytest.mark.parametrize(
    ("edit", "named"),
    [
        (lambda d: d["x"].update(chi2="abc"), r"\[x\] chi2 must be a number, got 'abc'"),
        (
            lambda d: d["x"]["covariance"][2].__setitem__(2, float("inf")),
            r"\[x\] covariance must be 5 x 5 numbers \(NaN where not defined\)",
        ),
        (lambda d: d.update(bogus=5), r"unknown key\(s\) \['bogus'\]"),
    ],
)
def test_a_z_calibration_file_with_a_bad_value_is_refused_by_name(run, tmp_path, edit, named):
    import tomllib

    import tomli_w

    from bayespsf.errors import BayespsfInputError
    from bayespsf.io import read_z_calibration

    _, _, path = run
    content = tomllib.loads(Path(path).read_text())
    edit(content)
    bad = tmp_path / "z.toml"
    bad.write_text(tomli_w.dumps(content))
    with pytest.raises(BayespsfInputError, match=rf"calibration file {bad}: {named}"):
        read_z_calibration(bad)


def test_a_z_calibration_whose_fit_had_no_covariance_reads_back(run, tmp_path):
    # calibrate writes NaN where the fit's information cannot be inverted: its own file reads
    import tomllib

    import tomli_w

    from bayespsf.io import read_z_calibration

    _, _, path = run
    content = tomllib.loads(Path(path).read_text())
    content["x"]["covariance"] = [[float("nan")] * 5] * 5
    (tmp_path / "z.toml").write_text(tomli_w.dumps(content))
    assert np.isnan(read_z_calibration(tmp_path / "z.toml").fits.loc["x", "w0_sd"])
