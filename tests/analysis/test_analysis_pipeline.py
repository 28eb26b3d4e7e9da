"""`bayespsf analyze` end to end on a small simulated movie: every file, one row per analysed
(molecule, frame), picasso opens the result, and the calibration check without ground truth
passes when the camera file is the simulator's."""

import numpy as np
import pandas as pd
import pytest

from bayespsf import Scene, cli, load_scene
from bayespsf.model import Model
from bayespsf.parallel import Store
from bayespsf.simulation import match_truth, simulate_movie

CAMERA = """[geometry]
pixel_size = 79.0

[camera]
kind = "emccd"
gain = 200.0
readout_sd = 50.0
offset = 100.0
e_per_adu = 12.0
quantize = true
saturation = 65535.0
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 96 x 96 paper-movie of 60 frames (4 immobile single molecules bleaching after 60
    frames on average), analysed with the simulator's own camera, Laplace posteriors, two
    worker processes and 25 valid frames per molecule (a posterior file: ~0.13 s to write)."""
    folder = tmp_path_factory.mktemp("analyze")
    table = load_scene("paper-movie").to_dict()
    table["movie"].update(
        frames=60,
        height=96,
        width=96,
        molecules=4,
        bleach_mean=60.0,
        two_fluorophores=0.0,
        moving=0.0,
        dark_frames=0,
    )
    made = simulate_movie(Scene.from_dict(table), seed=3, out=folder / "m")
    (folder / "camera.toml").write_text(CAMERA)
    out = folder / "out"
    code = cli.main(
        [
            "analyze",
            str(made.files["movie"]),
            "--camera",
            str(folder / "camera.toml"),
            "--psf-sd",
            "120",
            "--min-valid-frames",
            "25",
            "--method",
            "laplace",
            "--workers",
            "2",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    return out, made


def test_every_file_is_written_with_one_row_per_analysed_frame(run):
    out, _ = run
    for name in (
        "locs.hdf5",
        "locs.yaml",
        "locs.csv",
        "locs.parquet",
        "molecules.csv",
        "consistency.csv",
        "width_spread.csv",
        "report.md",
        "selection.md",
        "frames.csv",
        "camera.toml",
        "detections.png",
        "traces.png",
        "zscores.png",
        "width_precision.png",
        "gof_p.png",
        "residuals.png",
        "width_by_window.csv",
    ):
        assert (out / name).exists(), name
    locs = pd.read_parquet(out / "locs.parquet")
    frames = pd.read_csv(out / "frames.csv")
    valid = frames[frames["valid"]]
    assert len(locs) == len(valid) > 0
    assert set(zip(locs["molecule"], locs["frame"], strict=True)) == set(
        zip(valid["molecule"], valid["frame"], strict=True)
    )
    molecules = pd.read_csv(out / "molecules.csv")
    chosen = molecules[molecules["selected"]]
    assert chosen["s_x_combined"].notna().all()
    # the joint posterior over each molecule's frames: sharper than one frame, by ~sqrt(K)
    assert (chosen["joint_method"] == "importance").all()
    root_k = np.sqrt(chosen["joint_frames"])
    ratio = chosen["s_x_joint_sd"] * root_k / chosen["s_x_frame_sd"]
    assert ratio.between(0.7, 1.4).all(), ratio
    assert "joint posterior of each molecule" in (out / "report.md").read_text()
    assert (out / "posteriors" / "summary.csv").exists()
    report = (out / "report.md").read_text()
    assert "calibration check" in report and "(zscores.png)" in report
    assert "- `camera.toml`" in report  # the camera file the run used, in the Files list
    assert locs["gof_p"].between(0, 1).all() and "goodness-of-fit" in report
    assert "flagged frames" in report and "flagged fraction" in report


def test_positions_match_the_truth_and_picasso_opens_them(run):
    picasso_io = pytest.importorskip("picasso.io")
    out, made = run
    locs, info = picasso_io.load_locs(str(out / "locs.hdf5"))
    assert info[0]["Pixelsize"] == 79.0 and info[0]["Frames"] == 60
    molecules = pd.read_csv(out / "molecules.csv")
    row = match_truth(molecules, made.molecules)  # detection's ids are not the simulator's
    assert np.all(row >= 0)
    truth = made.molecules.iloc[row].set_index(molecules["molecule"])
    parquet = pd.read_parquet(out / "locs.parquet")
    # locations within 5 of their posterior SDs of the truth (immobile: frame 0's position)
    for axis, sd in (("x", "lpx"), ("y", "lpy")):
        z = (parquet[axis] - parquet["molecule"].map(truth[axis])) / parquet[sd]
        assert np.all(np.abs(z) < 5), z.abs().max()
    assert len(locs) == len(parquet)


def test_the_check_without_ground_truth_passes_on_a_right_model(run):
    # the simulator's camera and a Gaussian spot: z-score SDs within 4 of their SEs of 1
    out, _ = run
    check = pd.read_csv(out / "consistency.csv").set_index("parameter")
    for p in ("x0", "y0", "s_x", "s_y"):
        assert abs(check.loc[p, "z_sd"] - 1) < 4 * check.loc[p, "z_sd_se"], check.loc[p]


def test_a_rerun_continues_from_the_store(run, capsys):
    out, made = run
    files = sorted((out / "posteriors").glob("*.nc"))
    analysed = len(pd.read_parquet(out / "locs.parquet"))  # a posterior per analysed frame
    assert files and len(Store(out / "posteriors").finished(10**6)) == analysed
    stamps = [f.stat().st_mtime_ns for f in files]
    code = cli.main(
        [
            "analyze",
            str(made.files["movie"]),
            "--camera",
            str(out / "camera.toml"),
            "--psf-sd",
            "120",
            "--min-valid-frames",
            "25",
            "--method",
            "laplace",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    assert [f.stat().st_mtime_ns for f in files] == stamps  # no posterior made again


def test_the_goodness_of_fit_discrepancy_is_checked_and_kept_with_the_store(run, tmp_path):
    # a bad name is refused before any work; a rerun into the same folder with the other
    # discrepancy is refused by the posterior store (its gof_p were made with the default)
    from bayespsf.analysis import analyze
    from bayespsf.cameras import EMCCD
    from bayespsf.errors import BayespsfInputError

    out, made = run
    model = Model(15, 79.0, EMCCD(200.0, 50.0, 100.0, 12.0))
    with pytest.raises(BayespsfInputError, match="gof_discrepancy must be one of"):
        analyze(made.files["movie"], model, s0=120.0, out=tmp_path / "x", gof_discrepancy="x2")
    assert not (tmp_path / "x").exists()
    command = [
        "analyze",
        str(made.files["movie"]),
        "--camera",
        str(out.parent / "camera.toml"),
        "--psf-sd",
        "120",
        "--min-valid-frames",
        "25",
        "--method",
        "laplace",
        "--gof-discrepancy",
        "pearson",
        "--out",
        str(out),
    ]
    with pytest.raises(SystemExit, match="model check"):
        cli.main(command)


def test_nothing_selected_is_named_after_the_selection_files(run, tmp_path):
    from bayespsf.analysis import analyze
    from bayespsf.cameras import EMCCD
    from bayespsf.errors import BayespsfInputError
    from bayespsf.movie import Rules

    _, made = run
    model = Model(15, 79.0, EMCCD(200.0, 50.0, 100.0, 12.0))
    with pytest.raises(BayespsfInputError, match="no molecule passed the selection rules"):
        analyze(
            made.files["movie"],
            model,
            s0=120.0,
            out=tmp_path / "none",
            rules=Rules(min_snr=1e6, min_valid_frames=25),
        )
    assert (tmp_path / "none" / "selection.md").exists()


def test_the_tables_do_not_depend_on_the_workers(run, tmp_path):
    # the fixture's run sent the fits, the steps, the estimates beside the posteriors and the
    # figures to two workers; in one process every table is the same, to the last bit
    out, made = run
    command = ["analyze", str(made.files["movie"]), "--camera", str(out / "camera.toml")]
    command += ["--psf-sd", "120", "--min-valid-frames", "25", "--method", "laplace"]
    assert cli.main([*command, "--workers", "1", "--out", str(tmp_path / "one")]) == 0
    for name in ("frames.csv", "molecules.csv", "width_by_window.csv", "locs.parquet"):
        read = pd.read_parquet if name.endswith(".parquet") else pd.read_csv
        two, one = read(out / name), read(tmp_path / "one" / name)
        timing = [c for c in two.columns if c.endswith("seconds")]
        pd.testing.assert_frame_equal(one.drop(columns=timing), two.drop(columns=timing))
    assert {p.name for p in out.glob("*.png")} == {p.name for p in (tmp_path / "one").glob("*.png")}


def test_chunks_hold_whole_molecules_in_order():
    from bayespsf.analysis.molecule_tasks import molecule_chunks

    molecules = np.array([1, 1, 2, 2, 1, 3, 3, 3, 2, 7])  # a block of frames at a time
    chunks = molecule_chunks(molecules, size=3)  # a chunk closes at a molecule past 3 ROIs
    assert [c.tolist() for c in chunks] == [[0, 1, 4], [2, 3, 8], [5, 6, 7], [9]]
    assert [c.tolist() for c in molecule_chunks(molecules, size=100)] == [
        [0, 1, 4, 2, 3, 8, 5, 6, 7, 9]
    ]
    assert molecule_chunks(np.array([], dtype=int)) == []
    # no ROI: the empty tables, with their columns, as the fits of an empty stack give them
    from bayespsf.analysis.molecule_tasks import send_estimates

    model = Model.from_scene(load_scene("paper-movie"))
    fits, windows = send_estimates(np.zeros((0, 15, 15)), model, np.zeros(0, int), None)()
    assert len(fits) == len(windows) == 0 and "s_x_mle" in fits and "s_x_se" in windows


def test_a_dask_scheduler_gives_the_same_tables(run, tmp_path):
    # --scheduler: one client for the run, its executor passed to every stage (the selection's
    # fits and steps, the posteriors, the estimates, the joint posteriors, the figures, whose
    # PNG bytes come back to this process): the tables of the fixture's two local workers
    distributed = pytest.importorskip("distributed")  # a dependency: installed by pyproject
    out, made = run
    command = ["analyze", str(made.files["movie"]), "--camera", str(out / "camera.toml")]
    command += ["--psf-sd", "120", "--min-valid-frames", "25", "--method", "laplace"]
    # ":0": the scheduler's HTTP server on a free port (another test's cluster may hold 8787)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, dashboard_address=":0", processes=True
    ) as cluster:
        address = cluster.scheduler_address
        assert cli.main([*command, "--scheduler", address, "--out", str(tmp_path / "d")]) == 0
    for name in ("frames.csv", "molecules.csv", "width_by_window.csv"):
        two, dask = pd.read_csv(out / name), pd.read_csv(tmp_path / "d" / name)
        timing = [c for c in two.columns if c.endswith("seconds")]
        pd.testing.assert_frame_equal(dask.drop(columns=timing), two.drop(columns=timing))
    assert (tmp_path / "d" / "residuals.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
