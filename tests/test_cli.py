"""The `bayespsf` command."""

import subprocess
import sys

import pytest

from bayespsf import cli, selfcheck
from bayespsf.cameras import EMCCD


def test_selfcheck_moments_are_exact():
    table = selfcheck.moments_table(EMCCD(**selfcheck.DEFAULT_CAMERA))
    assert (table.abs() < 1e-8).all().all()


def test_selfcheck_command_prints_every_tier(capsys):
    assert cli.main(["selfcheck"]) == 0
    out = capsys.readouterr().out
    for tier in ("exact", "high-gain", "gaussian", "poisson"):
        assert tier in out


def test_help_and_unknown_command():
    result = subprocess.run(
        [sys.executable, "-m", "bayespsf.cli", "--help"], capture_output=True, text=True
    )
    assert result.returncode == 0 and "selfcheck" in result.stdout
    with pytest.raises(SystemExit):
        cli.main(["nonsense"])


def test_simulate_command_writes_counts_and_truth(tmp_path, capsys):
    import numpy as np
    import pandas as pd

    from bayespsf import scenes, simulate

    assert (
        cli.main(["simulate", "paper-fig3", "-n", "7", "--seed", "3", "--out", str(tmp_path / "a")])
        == 0
    )
    counts = np.load(tmp_path / "a.npy")
    truth = pd.read_csv(tmp_path / "a.truth.csv", index_col="image")
    expected, expected_truth = simulate(scenes.load("paper-fig3"), 7, seed=3)
    assert np.array_equal(counts, expected)
    assert np.allclose(truth.to_numpy(), expected_truth.to_numpy())
    assert "MultinomialPhotons" in capsys.readouterr().out


def test_simulate_command_scene_file_and_errors(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("[geometry]\nroi = 5\n")
    assert cli.main(["simulate", str(path), "-n", "2", "--out", str(tmp_path / "b")]) == 0
    with pytest.raises(SystemExit, match="no scene file"):
        cli.main(["simulate", str(tmp_path / "missing.toml")])
    path.write_text("[geometry]\nroi = -5\n")
    with pytest.raises(SystemExit, match=r"geometry\.roi"):
        cli.main(["simulate", str(path)])


def test_fit_command_tif_and_camera_file(tmp_path, capsys):
    import numpy as np
    import pandas as pd
    import tifffile

    from bayespsf import scenes, simulate
    from bayespsf.posterior import Posterior

    counts, _ = simulate(scenes.load("emccd-typical"), 2, seed=4)
    tifffile.imwrite(tmp_path / "rois.tif", counts.astype(np.float32))
    camera = tmp_path / "camera.toml"
    camera.write_text(
        "[geometry]\npixel_size = 100.0\n[camera]\nkind = 'emccd'\ngain = 200.0\n"
        "readout_sd = 50.0\noffset = 100.0\ne_per_adu = 12.0\n"
    )
    out = tmp_path / "fit"
    args = ["fit", str(tmp_path / "rois.tif"), "--camera", str(camera), "--ess", "50"]
    assert cli.main([*args, "--out", str(out), "--workers", "1"]) == 0
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 2 and {"s_x_mean", "s_x_sd", "s_x_q0975", "converged"} <= set(summary)
    post = Posterior.load(out / "molecule-000001.nc")
    assert post.draws()["s_x"].mean() == pytest.approx(summary.loc[1, "s_x_mean"], rel=1e-12)
    assert cli.main([*args, "--out", str(out), "--workers", "1"]) == 0  # resumes: nothing to do
    assert "ROI 1 (mcmc): converged" in capsys.readouterr().out
    fast = tmp_path / "fit-importance"
    args = [*args[:-1], "400", "--method", "importance", "--out", str(fast), "--workers", "1"]
    assert cli.main(args) == 0
    assert set(pd.read_csv(fast / "summary.csv")["method"]) == {"importance"}


def test_fit_command_errors_name_the_file(tmp_path):
    import numpy as np

    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((3, 14, 14)))
    with pytest.raises(SystemExit, match=r"bad\.npy.*odd size"):
        cli.main(["fit", str(bad), "--scene", "ideal"])
    wrong = tmp_path / "rois.csv"
    wrong.write_text("1,2\n")
    with pytest.raises(SystemExit, match=r"rois\.csv.*unknown file type"):
        cli.main(["fit", str(wrong), "--scene", "ideal"])
    small = tmp_path / "small.npy"
    np.save(small, np.zeros((1, 9, 9)))
    with pytest.raises(SystemExit, match="declares 15"):
        cli.main(["fit", str(small), "--scene", "ideal"])
