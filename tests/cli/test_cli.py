"""The `bayespsf` command."""

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from bayespsf import cli, load_scene, simulate_movie
from bayespsf.cameras import EMCCD
from bayespsf.cli import selfcheck
from bayespsf.io import CAMERA_KEYS
from bayespsf.movie import read_movie


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

    from bayespsf import load_scene, simulate

    assert (
        cli.main(["simulate", "paper-fig3", "-n", "7", "--seed", "3", "--out", str(tmp_path / "a")])
        == 0
    )
    counts = np.load(tmp_path / "a.npy")
    truth = pd.read_csv(tmp_path / "a.truth.csv", index_col="image")
    expected, expected_truth = simulate(load_scene("paper-fig3"), 7, seed=3)
    assert np.array_equal(counts, expected)
    assert np.allclose(truth.drop(columns="photon_unit").to_numpy(), expected_truth.to_numpy())
    assert set(truth["photon_unit"]) == {"photoelectrons"}
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

    from bayespsf import load_scene, simulate
    from bayespsf.parallel import Store

    counts, _ = simulate(load_scene("emccd-typical"), 2, seed=4)
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
    post = Store(out).posterior(1)
    assert post.draws()["s_x"].mean() == pytest.approx(summary.loc[1, "s_x_mean"], rel=1e-12)
    assert cli.main([*args, "--out", str(out), "--workers", "1"]) == 0  # resumes: nothing to do
    assert "ROI 1 (importance): converged" in capsys.readouterr().out  # auto, the default
    checked = tmp_path / "fit-checked"
    assert cli.main([*args, "--check", "--out", str(checked), "--workers", "1"]) == 0
    assert pd.read_csv(checked / "summary.csv")["gof_p"].between(0, 1).all()
    assert "gof_p" not in summary
    bare = tmp_path / "fit-bare"  # --no-draws: the same summary, the files without draws
    assert cli.main([*args, "--no-draws", "--out", str(bare), "--workers", "1"]) == 0
    assert "summaries without draws (--no-draws)" in capsys.readouterr().out
    same = pd.read_csv(bare / "summary.csv").drop(columns="seconds")
    pd.testing.assert_frame_equal(same, summary.drop(columns="seconds"))
    assert not Store(bare).keeps_draws()
    chain = tmp_path / "fit-mcmc"
    args = [*args[:-1], "400", "--method", "mcmc", "--out", str(chain), "--workers", "1"]
    assert cli.main(args) == 0
    assert set(pd.read_csv(chain / "summary.csv")["method"]) == {"mcmc"}


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


def _run(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "bayespsf.cli", *args], capture_output=True, text=True, cwd=cwd
    )


def test_help_loads_no_numerical_library():
    # `bayespsf --help` took 3.5-4 s because the package imported NumPy, SciPy, ArviZ and numba
    code = (
        "import sys, bayespsf.cli\n"
        "bayespsf.cli.build_parser().format_help()\n"
        "print(sorted(m for m in ('numpy', 'scipy', 'arviz', 'pandas', 'numba', 'emcee')"
        " if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stdout.strip() == "[]", result.stdout + result.stderr


def test_every_help_text_prints_plain_percent_signs():
    import argparse

    parser = cli.build_parser()
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for name, sub in commands.choices.items():
        assert "%%" not in sub.format_help(), name


@pytest.mark.parametrize("command", ["fit", "simulate", "demo"])
def test_out_that_is_or_lies_under_a_file_is_one_line(tmp_path, command):
    import numpy as np

    from bayespsf import load_scene, simulate

    counts, _ = simulate(load_scene("ideal"), 1, seed=0)
    np.save(tmp_path / "rois.npy", counts)
    blocker = tmp_path / "taken"
    blocker.write_text("a file")
    args = {
        "fit": ["fit", "rois.npy", "--scene", "ideal", "--workers", "1"],
        "simulate": ["simulate", "ideal", "-n", "1"],
        "demo": ["demo"],
    }[command]
    cases = [("taken/inner", "lies under")]
    if command != "simulate":  # simulate's --out is a path stem: "taken" writes taken.npy
        cases.append(("taken", "is a file"))
    for out, words in cases:
        result = _run(*args, "--out", out, cwd=tmp_path)
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
        assert result.stderr.startswith(f"bayespsf: --out {out}") and words in result.stderr


def test_camera_file_without_a_camera_is_an_error_not_a_photon_camera(tmp_path):
    # a camera file with geometry only was read as a photon-counting camera: N = 15 298 for a
    # 1 000-photon EMCCD spot. The counts' units depend on the camera, so it is never assumed
    import numpy as np

    from bayespsf import load_scene, simulate

    counts, _ = simulate(load_scene("emccd-typical"), 1, seed=0)
    np.save(tmp_path / "rois.npy", counts)
    camera = tmp_path / "camera.toml"
    for text in (
        "[geometry]\npixel_size = 100.0\n",
        "[geometry]\npixel_size = 100.0\n[camera]\ngain = 200.0\n",
    ):
        camera.write_text(text)
        with pytest.raises(SystemExit, match=r"camera\.toml: no \[camera\] table with its kind"):
            cli.main(["fit", str(tmp_path / "rois.npy"), "--camera", str(camera)])
    camera.write_text("[camera]\nkind = 'photon'\n")
    with pytest.raises(SystemExit, match=r"no \[geometry\] pixel_size"):
        cli.main(["fit", str(tmp_path / "rois.npy"), "--camera", str(camera)])
    # an EMCCD file with its kind only ran with gain 100, offset 0, e_per_adu 1: N 6x too low
    camera.write_text("[geometry]\npixel_size = 100.0\n[camera]\nkind = 'emccd'\ngain = 200.0\n")
    with pytest.raises(SystemExit, match=r"kind 'emccd' must state offset, readout_sd, e_per_ad"):
        cli.main(["fit", str(tmp_path / "rois.npy"), "--camera", str(camera)])
    camera.write_text("geometry = 3\n[camera]\nkind = 'photon'\n")
    with pytest.raises(SystemExit, match=r"\[geometry\] must be a table"):
        cli.main(["fit", str(tmp_path / "rois.npy"), "--camera", str(camera)])


def test_detect_sizes_and_spot_widths_that_cannot_work_are_one_line(tmp_path):
    import numpy as np

    np.save(tmp_path / "movie.npy", np.full((80, 64, 64), 100, np.uint16))
    camera = tmp_path / "camera.toml"
    camera.write_text("[geometry]\npixel_size = 100.0\n[camera]\nkind = 'photon'\n")
    base = ["detect", str(tmp_path / "movie.npy"), "--camera", str(camera)]
    for extra, words in (
        (["--fit", "14"], "--fit must be an odd number of pixels >= 5"),
        (["--fit", "3"], r"--fit must be an odd number of pixels >= 5 .*, got 3"),
        (["--roi", "71"], r"--roi 71 is larger than .*movie.npy's frames \(64 x 64 pixels\)"),
        (["--psf-sd", "1e6"], r"s0 \(1e\+06 nm\) is 1e\+04 pixels of 100 nm"),
        (["--psf-sd", "1.3"], r"is 1.3 nm, 0.013 of a 100 nm pixel: it is in nm \(--psf-sd"),
        (["--psf-sd", "-130"], r"must be > 0 nm and finite \(--psf-sd on the command line"),
    ):
        with pytest.raises(SystemExit, match=words):
            cli.main([*base, "--psf-sd", "120", *extra])


def test_fit_takes_the_truth_table_simulate_writes_and_keeps_logs_clean(tmp_path):
    # the coverage columns of docs/scale.md from the command line; the progress bar only on a
    # terminal (it was written into log files)
    import pandas as pd

    assert _run("simulate", "ideal", "-n", "2", "--out", "sim/a", cwd=tmp_path).returncode == 0
    result = _run(
        "fit",
        "sim/a.npy",
        "--scene",
        "ideal",
        "--truth",
        "sim/a.truth.csv",
        "--workers",
        "1",
        "--ess",
        "100",
        "--method",
        "importance",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "molecule/s" not in result.stderr and "\r" not in result.stderr
    summary = pd.read_csv(tmp_path / "bayespsf-fit" / "summary.csv")
    truth = pd.read_csv(tmp_path / "sim" / "a.truth.csv")
    assert summary["s_x_truth"].tolist() == pytest.approx(truth["s_x"].tolist())
    assert summary["s_x_rank"].between(0, 99).all()
    bad = _run(
        "fit", "sim/a.npy", "--scene", "ideal", "--truth", "sim/a.npy", "--out", "x", cwd=tmp_path
    )
    assert bad.returncode == 1 and bad.stderr.startswith("bayespsf: --truth sim/a.npy")


def test_fit_reports_a_refused_roi_and_fits_the_rest(tmp_path):
    import numpy as np

    from bayespsf import load_scene, simulate

    counts, _ = simulate(load_scene("ideal"), 3, seed=0)
    counts[1] = 4.0
    np.save(tmp_path / "rois.npy", counts)
    result = _run(
        "fit",
        "rois.npy",
        "--scene",
        "ideal",
        "--workers",
        "1",
        "--method",
        "importance",
        "--ess",
        "100",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "ROI 1: refused: every pixel has the same value" in result.stdout
    assert "ROI 2 (importance)" in result.stdout


def test_fit_settings_that_would_never_end_are_one_line(tmp_path):
    # `--ess nan` ran forever
    import numpy as np

    from bayespsf import load_scene, simulate

    counts, _ = simulate(load_scene("ideal"), 1, seed=0)
    np.save(tmp_path / "rois.npy", counts)
    for option, value in (("--ess", "nan"), ("--ess", "-5"), ("--max-seconds", "0")):
        result = _run("fit", "rois.npy", "--scene", "ideal", option, value, cwd=tmp_path)
        assert result.returncode == 1 and result.stderr.startswith("bayespsf: "), result.stderr
        assert "Traceback" not in result.stderr


def test_a_truth_table_of_the_wrong_shape_or_values_names_truth_and_the_shape(tmp_path):
    # text in a truth table ended in numpy's bare "ValueError: could not convert string to
    # float", and an empty cell ran on, its NaN truth giving meaningless ranks
    import pandas as pd

    assert _run("simulate", "ideal", "-n", "2", "--out", "sim/a", cwd=tmp_path).returncode == 0
    truth = pd.read_csv(tmp_path / "sim" / "a.truth.csv")
    shape = (
        r"expected a table of shape \(2, 6\): one row per ROI in the stack's order, columns "
        r"x0, y0, s_x, s_y, N, b, each a finite number"
    )
    for name, table, words in (
        ("text", truth.assign(s_x=["wide", 130.0]), "s_x in row 0 is 'wide', not a finite number"),
        ("empty", truth.assign(N=[1000.0, None]), "N in row 1 is empty, not a finite number"),
        ("rows", pd.concat([truth, truth]), "4 rows for 2 ROIs"),
        ("columns", truth.drop(columns=["b"]), "no column"),
    ):
        table.to_csv(tmp_path / f"{name}.csv", index=False)
        fit = ["fit", str(tmp_path / "sim" / "a.npy"), "--scene", "ideal", "--out", "out"]
        expected = rf"^bayespsf: --truth \S*{name}\.csv: {words}.*{shape}"
        with pytest.raises(SystemExit, match=expected):
            cli.main([*fit[:-1], str(tmp_path / "out"), "--truth", str(tmp_path / f"{name}.csv")])
        assert not (tmp_path / "out").exists()


def test_a_camera_file_roi_that_disagrees_is_refused_naming_both(tmp_path):
    # camera_scene replaced a stated [geometry] roi by the ROIs' (or --fit's) without a word
    import numpy as np

    from bayespsf import load_scene, simulate

    counts, _ = simulate(load_scene("emccd-typical"), 1, seed=0)  # 15 x 15 ROIs
    np.save(tmp_path / "rois.npy", counts)
    camera = tmp_path / "camera.toml"
    camera.write_text(
        "[geometry]\npixel_size = 100.0\nroi = 11\n[camera]\nkind = 'emccd'\ngain = 200.0\n"
        "readout_sd = 50.0\noffset = 100.0\ne_per_adu = 12.0\n"
    )
    rois = str(tmp_path / "rois.npy")
    with pytest.raises(SystemExit) as refused:
        cli.main(["fit", rois, "--camera", str(camera), "--out", str(tmp_path / "out")])
    assert str(refused.value) == (
        f"bayespsf: {camera}: [geometry] roi = 11, but the side of the ROIs in {rois} is 15: "
        f"set [geometry] roi = 15 in {camera} or remove that key (the side of the ROIs in "
        f"{rois} then gives it)"
    )
    np.save(tmp_path / "movie.npy", np.full((80, 64, 64), 100, np.uint16))
    detect = ["detect", str(tmp_path / "movie.npy"), "--camera", str(camera), "--psf-sd", "120"]
    with pytest.raises(SystemExit) as refused:  # a --fit that disagrees is refused
        cli.main([*detect, "--fit", "15"])
    assert str(refused.value) == (
        f"bayespsf: {camera}: [geometry] roi = 11, but --fit is 15: set [geometry] roi = 15 in "
        f"{camera} or remove that key (--fit then gives it), or give --fit 11"
    )
    # without --fit, the file's roi is the fitted window: the command goes on to the movie
    with pytest.raises(SystemExit, match="every pixel is 100 ADU"):
        cli.main(detect)
    camera.write_text(camera.read_text().replace("roi = 11", "roi = 15"))  # agreeing: fine
    fit = ["fit", rois, "--camera", str(camera), "--workers", "1", "--method", "laplace"]
    assert cli.main([*fit, "--out", str(tmp_path / "out")]) == 0


def test_pixel_size_flag_stands_in_for_metadata_and_disagreeing_values_are_refused(tmp_path):
    """``--pixel-size`` gives the pixel size where the camera file gives none (a movie without
    metadata), and one that disagrees with the camera file's is refused, naming both."""
    scene = load_scene("paper-movie").replace(
        movie={"frames": 80, "height": 48, "width": 48, "molecules": 1, "dark_frames": 0}
    )
    made = simulate_movie(scene, seed=1, out=tmp_path / "m")
    frames = read_movie(made.files["movie"])
    plain = tmp_path / "plain.npy"
    np.save(plain, np.stack([frames.frame(i) for i in range(len(frames))]))
    camera = {k: v for k, v in scene.to_dict()["camera"].items() if k in CAMERA_KEYS["emccd"]}
    lines = [f"{k} = {v!r}" for k, v in {"kind": "emccd", **camera}.items()]
    (tmp_path / "camera.toml").write_text("[camera]\n" + "\n".join(lines) + "\n")
    base = ["detect", str(plain), "--camera", str(tmp_path / "camera.toml"), "--psf-sd", "120"]
    # no metadata, no flag: both fixes named, the flag and the camera file's key
    fixes = r"state it \(nm\): --pixel-size, or \[geometry\] pixel_size in .*camera\.toml"
    with pytest.raises(SystemExit, match=r"no pixel size: .*plain\.npy's metadata give none"):
        cli.main([*base, "--out", str(tmp_path / "a")])
    for command in ("detect", "analyze"):
        with pytest.raises(SystemExit, match=fixes):
            cli.main([command, *base[1:], "--out", str(tmp_path / "a")])
    assert cli.main([*base, "--pixel-size", "79", "--out", str(tmp_path / "b")]) == 0
    stated = tmp_path / "stated.toml"
    stated.write_text((tmp_path / "camera.toml").read_text() + "[geometry]\npixel_size = 79.0\n")
    base[3] = str(stated)
    with pytest.raises(SystemExit, match=r"--pixel-size 100 nm, but .* pixel_size = 79 nm"):
        cli.main([*base, "--pixel-size", "100", "--out", str(tmp_path / "c")])


def _one_frame_movie(tmp_path, side: int, molecules: int) -> tuple[str, str]:
    """A one-frame paper-movie of ``side`` x ``side`` pixels (seed 5) and its EMCCD camera
    file: their paths."""
    scene = load_scene("paper-movie").replace(
        movie={"frames": 1, "height": side, "width": side, "molecules": molecules,
               "dark_frames": 0}
    )  # fmt: skip
    made = simulate_movie(scene, seed=5, out=tmp_path / "m")
    camera = {k: v for k, v in scene.to_dict()["camera"].items() if k in CAMERA_KEYS["emccd"]}
    lines = [f"{k} = {v!r}" for k, v in {"kind": "emccd", **camera}.items()]
    (tmp_path / "camera.toml").write_text("[camera]\n" + "\n".join(lines) + "\n")
    return str(made.files["movie"]), str(tmp_path / "camera.toml")


def test_analyze_names_a_bad_sampler_setting_before_any_work(tmp_path):
    """A sampler setting that would never end or never start a run (``--max-seconds 0``,
    ``--ess nan``) is refused by name before the detection, with and without
    ``--per-frame``; the output folder is not made."""
    movie, camera = _one_frame_movie(tmp_path, side=32, molecules=1)
    base = ["analyze", movie, "--camera", camera, "--psf-sd", "120", "--fit", "9"]
    base += ["--out", str(tmp_path / "a")]
    for option, value in (("--max-seconds", "0"), ("--ess", "nan")):
        for extra in (["--rules", "none"], ["--per-frame"]):  # named as the flag, not max_seconds
            with pytest.raises(SystemExit, match=rf"^bayespsf: {option} must be a number in"):
                cli.main([*base, *extra, option, value])
            assert not (tmp_path / "a").exists()


@pytest.mark.parametrize(
    ("message", "usage", "said"),
    [
        ("ess must be > 0, got nan", "[--ess ESS]", "--ess must be > 0, got nan"),
        ("step must not be 0", "[--z-step Z_STEP]", "--z-step must not be 0"),
        ("min_valid_frames must be", "[--min-valid-frames N]", "--min-valid-frames must be"),
        ("z must be", "[--z-range LOW HIGH]", "z must be"),  # --z alone is not its flag
        ("store x was made for another run", "[--out OUT]", "store x was made for another run"),
        ("--out x is a folder", "[--out OUT]", "--out x is a folder"),
        (
            "e_per_adu must be > 0 (--e-per-adu)",
            "[--e-per-adu E]",
            "e_per_adu must be > 0 (--e-per-adu)",
        ),
    ],
)
def test_a_functions_argument_in_a_message_is_named_as_the_commands_flag(message, usage, said):
    from bayespsf.cli._shared import as_flag

    assert as_flag(message, usage) == said


def test_selection_options_run_a_short_movie_from_the_command_line(tmp_path, capsys):
    """A 12-frame movie: refused by the paper's 75-frame rule with the flags that fix it named;
    ``--min-valid-frames`` or ``--rules none`` run it; ``--rules none`` keeps every accepted
    candidate and is refused beside the rules' own options."""
    scene = load_scene("paper-movie").replace(
        movie={
            "frames": 12,
            "height": 64,
            "width": 64,
            "molecules": 2,
            "dark_frames": 0,
            "min_spacing": 20,
            "edge": 12,
        }
    )
    made = simulate_movie(scene, seed=3, out=tmp_path / "m")
    camera = {k: v for k, v in scene.to_dict()["camera"].items() if k in CAMERA_KEYS["emccd"]}
    lines = [f"{k} = {v!r}" for k, v in {"kind": "emccd", **camera}.items()]
    (tmp_path / "camera.toml").write_text("[camera]\n" + "\n".join(lines) + "\n")
    base = ["detect", str(made.files["movie"]), "--camera", str(tmp_path / "camera.toml")]
    base += ["--psf-sd", "120"]
    with pytest.raises(SystemExit, match=r"--min-valid-frames N, --skip-rule photon_window"):
        cli.main([*base, "--out", str(tmp_path / "paper")])
    assert cli.main([*base, "--min-valid-frames", "8", "--out", str(tmp_path / "eight")]) == 0
    assert cli.main([*base, "--rules", "none", "--out", str(tmp_path / "none")]) == 0
    molecules = pd.read_csv(tmp_path / "none" / "molecules.csv")
    candidates = pd.read_csv(tmp_path / "none" / "candidates.csv")
    accepted = candidates[candidates["status"] == "accepted"]
    assert len(accepted) > 0 and int(molecules["selected"].sum()) == len(accepted)
    with pytest.raises(SystemExit, match="--rules none keeps every accepted candidate"):
        cli.main([*base, "--rules", "none", "--skip-rule", "snr", "--out", str(tmp_path / "x")])


def test_a_one_frame_movie_runs_without_runtime_warnings(tmp_path):
    """A one-frame movie with ``--rules none``: each molecule has one frame, so the check
    across frames has no statistic; ``detect`` and ``analyze`` say so and print no
    RuntimeWarning (the child processes see every warning: ``PYTHONWARNINGS``)."""
    import os

    movie, camera = _one_frame_movie(tmp_path, side=96, molecules=8)
    base = [movie, "--camera", camera, "--psf-sd", "120", "--rules", "none"]
    env = {**os.environ, "PYTHONWARNINGS": "always::RuntimeWarning"}
    for command in (
        ["detect", *base, "--out", str(tmp_path / "d")],
        ["analyze", *base, "--method", "laplace", "--workers", "1", "--out", str(tmp_path / "a")],
    ):
        result = subprocess.run(
            [sys.executable, "-m", "bayespsf.cli", *command],
            capture_output=True,
            text=True,
            env=env,
        )
        assert result.returncode == 0, result.stderr
        assert "RuntimeWarning" not in result.stderr, result.stderr
    assert "no z-score SD of s_x (it needs molecules with two or more analysed" in result.stdout


def test_calibrate_refuses_a_folder_or_an_existing_file_as_its_out(tmp_path):
    # "--out outdir/" would write a file named outdir, and an existing camera file would be
    # replaced without a word: both are refused before any work (--force replaces a file)
    import numpy as np

    np.save(tmp_path / "movie.npy", np.full((80, 64, 64), 100, np.uint16))
    base = ["calibrate", str(tmp_path / "movie.npy"), "--psf-sd", "120", "--pixel-size", "100"]
    with pytest.raises(SystemExit, match=r"--out .*outdir/ is a folder; give the camera file"):
        cli.main([*base, "--out", f"{tmp_path / 'outdir'}/"])
    assert not (tmp_path / "outdir").exists()
    (tmp_path / "cam.toml").write_text("# a camera file of another run\n")
    with pytest.raises(SystemExit, match=r"cam.toml exists: give another name, or --force"):
        cli.main([*base, "--out", str(tmp_path / "cam.toml")])
    assert (tmp_path / "cam.toml").read_text() == "# a camera file of another run\n"


def test_an_unknown_flag_gets_the_subcommands_usage_and_the_nearest_flag(capsys):
    # the subcommand's usage, not the top level's, for its misspelt flag
    with pytest.raises(SystemExit) as stop:
        cli.main(["detect", "movie.tif", "--camera", "c.toml", "--pixel_size", "100"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: bayespsf detect ")
    assert (
        "unrecognized arguments: --pixel_size 100; --pixel_size: did you mean --pixel-size?" in err
    )


def test_a_multi_channel_file_is_read_at_the_channel_given(tmp_path, capsys):
    # the library's answer to a two-channel file named channel=k, which no command took
    import numpy as np
    import tifffile

    rng = np.random.default_rng(0)
    frames = rng.poisson(5.0, (30, 2, 48, 48)).astype(np.uint16)  # TCYX
    tifffile.imwrite(tmp_path / "two.tif", frames, imagej=True, metadata={"axes": "TCYX"})
    camera = tmp_path / "camera.toml"
    camera.write_text("[geometry]\npixel_size = 100.0\n[camera]\nkind = 'photon'\n")
    base = ["detect", str(tmp_path / "two.tif"), "--camera", str(camera), "--psf-sd", "130"]
    with pytest.raises(SystemExit, match=r"2 channels \(0, 1\); pick one .*--channel k"):
        cli.main([*base, "--out", str(tmp_path / "a")])
    assert cli.main([*base, "--channel", "1", "--rules", "none", "--out", str(tmp_path / "b")]) == 0
    assert "frames=30, height=48, width=48" in capsys.readouterr().out


def test_dark_frames_are_read_at_the_channel_only_when_they_have_several(tmp_path):
    # calibrate's dark file: its own problem is reported, not the channel read's retry
    import numpy as np
    import tifffile

    from bayespsf.cli.commands import _dark_frames
    from bayespsf.errors import BayespsfInputError

    tifffile.imwrite(
        tmp_path / "complex.tif", np.zeros((3, 8, 8), np.complex64), photometric="minisblack"
    )
    with pytest.raises(BayespsfInputError, match="complex values") as error:
        _dark_frames(str(tmp_path / "complex.tif"), channel=1)
    assert "channel" not in str(error.value)
    frames = np.stack([np.full((3, 8, 8), 100, np.uint16), np.full((3, 8, 8), 7, np.uint16)], 1)
    tifffile.imwrite(tmp_path / "two.tif", frames, imagej=True, metadata={"axes": "TCYX"})
    assert _dark_frames(str(tmp_path / "two.tif"), channel=1).frames().max() == 7
    tifffile.imwrite(tmp_path / "one.tif", frames[:, 0], photometric="minisblack")
    assert _dark_frames(str(tmp_path / "one.tif"), channel=1).frames().max() == 100


def test_the_fit_report_names_a_few_rois_and_counts_the_rest(tmp_path):
    # 25 ROIs, 3 of them refused: 10 posteriors and the 3 refused named, the other 12
    # counted, with the outcomes, the methods and the files
    from bayespsf.cli._shared import SHOWN, fit_report

    rows = [
        {"molecule": i, "status": "converged", "converged": True, "method": "importance",
         "s_x_mean": 130.0 + i, "s_x_sd": 7.0, "message": ""}
        for i in range(22)
    ] + [
        {"molecule": 22 + i, "status": "refused", "converged": False, "method": "mcmc",
         "s_x_mean": np.nan, "s_x_sd": np.nan, "message": "every pixel has the same value"}
        for i in range(3)
    ]  # fmt: skip
    lines = fit_report(pd.DataFrame(rows), tmp_path).splitlines()
    assert SHOWN == 10 and lines[0] == "ROI 0 (importance): converged True, s_x = 130 +- 7 nm"
    assert lines[9].startswith("ROI 9 (importance)")
    assert lines[10:13] == [
        f"ROI {i}: refused: every pixel has the same value" for i in (22, 23, 24)
    ]
    assert lines[13] == f"... 12 more in {tmp_path / 'summary.csv'}"
    assert lines[14] == "25 ROIs: converged 22, refused 3"
    assert lines[15] == "posteriors by importance 22"
    assert lines[16].startswith(f"wrote {tmp_path / 'summary.csv'} and the posteriors of 22 ROIs")


def test_a_disk_or_path_error_ends_in_one_line_naming_the_file(monkeypatch):
    # an OSError is the disk's or the path's (read-only, full, a path through a file): one line
    # naming the file and what to check, no traceback; likewise input too large for memory
    import errno

    from bayespsf.cli import commands

    def read_only(args):
        raise OSError(errno.EROFS, "Read-only file system", "out/summary.csv")

    def too_large(args):
        raise MemoryError("Unable to allocate 74.5 GiB for an array")

    monkeypatch.setitem(commands.COMMANDS, "simulate", read_only)
    with pytest.raises(SystemExit, match=r"^bayespsf: out/summary.csv: Read-only file system \("):
        cli.main(["simulate", "ideal"])
    monkeypatch.setitem(commands.COMMANDS, "simulate", too_large)
    with pytest.raises(SystemExit, match=r"^bayespsf: out of memory \(Unable to allocate 74.5"):
        cli.main(["simulate", "ideal"])

    def bare(args):
        raise MemoryError

    monkeypatch.setitem(commands.COMMANDS, "simulate", bare)
    with pytest.raises(SystemExit, match=r"^bayespsf: out of memory \(an allocation failed\)"):
        cli.main(["simulate", "ideal"])

    def network(args):  # an OSError of a cluster or a pipe is not the disk's: raised as it is
        raise ConnectionResetError(errno.ECONNRESET, "Connection reset by peer")

    monkeypatch.setitem(commands.COMMANDS, "simulate", network)
    with pytest.raises(ConnectionResetError):
        cli.main(["simulate", "ideal"])


def test_an_output_folder_that_cannot_be_written_is_refused_before_the_work(tmp_path, monkeypatch):
    # the nearest existing folder is asked, before any work (a read-only disk was found when
    # the first file was written, after the work); root may write where permissions say no,
    # so os.access is the one answer asked
    from bayespsf.io import folders

    asked = []

    def access(path, mode):
        asked.append(path)
        return False

    monkeypatch.setattr(folders.os, "access", access)
    with pytest.raises(SystemExit, match=rf"--out {tmp_path}/a/b cannot be written: {tmp_path} is"):
        cli.main(["simulate", "ideal", "-n", "1", "--out", str(tmp_path / "a" / "b")])
    assert asked == [tmp_path] and not (tmp_path / "a").exists()


def test_workers_and_a_scheduler_together_are_refused():
    # --workers was dropped without a word where --scheduler was given
    with pytest.raises(SystemExit, match=r"give --workers .* or --scheduler .*, not both"):
        cli.main(["fit", "r.npy", "--scene", "ideal", "--workers", "2", "--scheduler", "tcp://h:1"])


def test_a_scheduler_address_without_a_port_is_named():
    from bayespsf.errors import BayespsfInputError
    from bayespsf.parallel import task_runner

    with pytest.raises(BayespsfInputError, match="'notanaddress' is not a Dask scheduler addr"):
        with task_runner("notanaddress", None):
            pass


@pytest.mark.parametrize("value", ["0", "-79", "nan", "1e6", "abc"])
def test_a_bad_pixel_size_is_named_as_the_flag(value, capsys):
    # it was named as the camera file's [geometry] pixel_size, a key the file did not hold
    for command in ("detect", "analyze", "calibrate"):
        with pytest.raises(SystemExit) as ended:
            cli.main([command, "m.tif", "--camera", "c.toml", "--pixel-size", value])
        assert ended.value.code == 2
        said = capsys.readouterr().err
        assert f"argument --pixel-size: a pixel size in nm within [1, 100000], got {value}" in said


def test_calibrate_z_keeps_an_existing_calibration_without_force(tmp_path):
    # it overwrote the file without a word, where calibrate refuses its camera file
    (tmp_path / "z.toml").write_text("kept")
    args = ["calibrate-z", "s.tif", "--camera", "c.toml", "--z-start", "0", "--z-step", "50"]
    args += ["--frames-per-step", "4", "--out", str(tmp_path / "z.toml")]
    with pytest.raises(SystemExit, match=r"--out .*z\.toml exists: give another name, or --force"):
        cli.main(args)
    assert (tmp_path / "z.toml").read_text() == "kept"
    with pytest.raises(SystemExit, match=r"--out .* is a folder; give the calibration file's na"):
        cli.main([*args[:-1], str(tmp_path)])
