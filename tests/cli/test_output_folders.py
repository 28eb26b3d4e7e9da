"""An output folder is one run: `bayespsf detect` and `bayespsf analyze` (and
`bayespsf.movie.found.write`, `bayespsf.analyze`) record the run a folder holds in
`run.json` and refuse, before writing anything, a folder that holds another run's results;
`--force` replaces them (the command's files and those the record lists, nothing else); a
killed run resumes, and never leaves two runs' files in one folder."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest

import bayespsf
from bayespsf import cli
from bayespsf.analysis.pipeline import ANALYSIS_FILES
from bayespsf.cameras import EMCCD
from bayespsf.errors import BayespsfInputError
from bayespsf.io.run_record import RECORD_NAME, RunConflict, read_run_record
from bayespsf.model import Model
from bayespsf.movie import Rules, find_molecules
from bayespsf.movie.found import SELECTION_FILES, write
from bayespsf.parallel.store import Store

CAMERA = """[geometry]
pixel_size = 79.0

[camera]
kind = "emccd"
gain = 200.0
readout_sd = 50.0
offset = 100.0
e_per_adu = 12.0
"""
ANALYZE = ["--psf-sd", "120", "--min-valid-frames", "8", "--method", "laplace", "--workers", "1"]
WAY = "give a new --out folder, or --force to replace them"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two 20-frame movies of one bleaching molecule (for analyze: 15 and 8 valid frames; the
    first bleaches during frame 17, its truth's bleach frame is 18, and the photon window
    removes the part-lit frame 17 and two bright ones), two 80-frame movies (detect's rules
    need 75), the camera file and one with another gain, and a folder that `analyze` finished
    on the first movie."""
    folder = tmp_path_factory.mktemp("folders")
    scene = bayespsf.load_scene("paper-movie")
    short = {"frames": 20, "height": 48, "width": 48, "bleach_mean": 12.0}
    long = {"frames": 80, "height": 40, "width": 40, "bleach_mean": 60.0}
    files = {}
    for name, shape, seeds in (("a", short, (0, 3)), ("d", long, (0, 1))):
        for number, seed in enumerate(seeds):
            movie = {"molecules": 1, "dark_frames": 0, "two_fluorophores": 0.0, "moving": 0.0}
            made = bayespsf.simulate_movie(
                scene.replace(movie={**movie, **shape}), seed=seed, out=folder / f"{name}{number}"
            )
            files[f"{name}{number}"] = made.files["movie"]
    files["camera"] = folder / "camera.toml"
    files["camera"].write_text(CAMERA)
    files["other camera"] = folder / "other-camera.toml"
    files["other camera"].write_text(CAMERA.replace("gain = 200.0", "gain = 210.0"))
    files["analyzed"] = folder / "analyzed"
    assert analyze(files["a0"], files["camera"], files["analyzed"]) == 0
    return files


def analyze(movie, camera, out, *extra):
    command = ["analyze", str(movie), "--camera", str(camera), *ANALYZE]
    return cli.main([*command, "--out", str(out), *extra])


def detect(movie, camera, out, *extra):
    command = ["detect", str(movie), "--camera", str(camera), "--psf-sd", "120"]
    return cli.main([*command, "--out", str(out), *extra])


def snapshot(folder):
    """Every file under ``folder``: its size, modification time and bytes."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def copy(folder, to):
    shutil.copytree(folder, to)
    return to


def test_analyze_refuses_another_movie_camera_or_setting_before_writing_anything(data, tmp_path):
    # rerunning analyze into a finished folder with another movie or camera file was refused
    # ("no molecule passed", "model differ") only after camera.toml, candidates.csv,
    # molecules.csv, frames.csv and selection.md were overwritten
    out = copy(data["analyzed"], tmp_path / "out")
    before = snapshot(out)
    cases = [
        ((data["a1"], data["camera"]), "movie differs"),
        ((data["a0"], data["other camera"]), "camera, camera.toml differ"),
    ]
    for (movie, camera), what in cases:
        with pytest.raises(SystemExit) as refused:
            analyze(movie, camera, out)
        assert str(refused.value) == (
            f"bayespsf: --out {out} holds the results of another run: {what}; {WAY}"
        )
        assert snapshot(out) == before
    command = ["analyze", str(data["a0"]), "--camera", str(data["camera"]), *ANALYZE]
    with pytest.raises(SystemExit, match=r"seed \(0 there, 4 now\) differs; give a new --out"):
        cli.main([*command, "--seed", "4", "--out", str(out)])
    assert snapshot(out) == before
    # the same run again continues (the posteriors are not made again)
    posteriors = {k: v for k, v in before.items() if k.startswith("posteriors/posteriors-")}
    assert posteriors and len(stored(out / "posteriors")) == 15
    assert analyze(data["a0"], data["camera"], out) == 0
    after = snapshot(out)
    assert {k: after[k] for k in posteriors} == posteriors


def test_force_leaves_the_new_run_alone_in_the_folder(data, tmp_path):
    out = copy(data["analyzed"], tmp_path / "out")
    (out / "notes.txt").write_text("mine")
    started = time.time_ns()
    assert analyze(data["a1"], data["camera"], out, "--force") == 0
    allowed = {*ANALYSIS_FILES, RECORD_NAME, "camera.toml", "notes.txt"}
    assert {p.name for p in out.iterdir()} <= allowed
    assert (out / "notes.txt").read_text() == "mine"  # nothing but the run's files removed
    made = [p for p in out.rglob("*") if p.is_file() and p.name not in ("notes.txt", ".lock")]
    assert all(p.stat().st_mtime_ns >= started for p in made)  # every file is the new run's
    locs = pd.read_parquet(out / "locs.parquet")
    assert len(stored(out / "posteriors")) == len(locs) > 0
    assert str(data["a1"]) in (out / "locs.yaml").read_text()
    assert read_run_record(out)["about"]["movie"] == str(data["a1"])
    assert analyze(data["a1"], data["camera"], out) == 0  # and it is that run's folder now


def test_detect_refuses_another_movie_and_force_replaces_its_results(data, tmp_path):
    # detect into a folder holding another movie's results replaced them without a word
    out = tmp_path / "out"
    assert detect(data["d0"], data["camera"], out) == 0
    before = snapshot(out)
    with pytest.raises(SystemExit) as refused:
        detect(data["d1"], data["camera"], out)
    assert str(refused.value) == (
        f"bayespsf: --out {out} holds the results of another run: movie differs; {WAY}"
    )
    assert snapshot(out) == before
    with pytest.raises(SystemExit, match=r"false positives \(0.01 there, 0.1 now\) differs"):
        detect(data["d0"], data["camera"], out, "--false-positives", "0.1")
    assert detect(data["d0"], data["camera"], out) == 0  # the same run rewrites the same files
    assert {k: v[2] for k, v in snapshot(out).items()} == {k: v[2] for k, v in before.items()}
    assert detect(data["d1"], data["camera"], out, "--force") == 0
    assert detect(data["d1"], data["camera"], tmp_path / "fresh") == 0
    for name in (*SELECTION_FILES, "camera.toml"):
        assert (out / name).read_bytes() == (tmp_path / "fresh" / name).read_bytes(), name


def test_detect_and_analyze_never_share_a_folder(data, tmp_path):
    out = copy(data["analyzed"], tmp_path / "out")
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    with pytest.raises(SystemExit) as refused:
        detect(data["d0"], data["camera"], out)
    assert str(refused.value) == (
        f"bayespsf: --out {out} holds the results of another run: command (analyze there, "
        f"detect now) differs; {WAY}"
    )
    # --force with input detect refuses: the folder is left as it was
    with pytest.raises(SystemExit, match="fewer than the 75 valid frames"):
        detect(data["a1"], data["camera"], out, "--force")
    assert snapshot(out) == before
    assert detect(data["d0"], data["camera"], out, "--force") == 0
    # analyze's files go too (its record lists them), so the folder describes detect's run
    names = {p.name for p in out.iterdir()}
    assert names == {*SELECTION_FILES, "camera.toml", RECORD_NAME, "notes.txt"}
    with pytest.raises(SystemExit, match=r"command \(detect there, analyze now\) differs"):
        analyze(data["a0"], data["camera"], out)


def test_a_folder_of_results_without_a_record_is_another_run(data, tmp_path):
    # folders made before runs were recorded, or by hand
    out = tmp_path / "old"
    out.mkdir()
    (out / "candidates.csv").write_text("molecule,x,y\n")
    (out / "locs.csv").write_text("frame\n")
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    for run in (
        lambda *extra: detect(data["d0"], data["camera"], out, *extra),
        lambda *extra: analyze(data["a0"], data["camera"], out, *extra),
    ):
        with pytest.raises(SystemExit) as refused:
            run()
        assert str(refused.value).startswith(f"bayespsf: --out {out} holds results (")
        assert str(refused.value).endswith(
            "but no run record (run.json): they were made before bayespsf recorded its runs, "
            f"or by hand, and may be another run's; {WAY}"
        )
        assert snapshot(out) == before
    (out / RECORD_NAME).write_text("{not json")
    with pytest.raises(SystemExit, match=r"and a run record that cannot be read .*--force"):
        detect(data["d0"], data["camera"], out)
    assert detect(data["d0"], data["camera"], out, "--force") == 0
    assert (out / "notes.txt").read_text() == "mine" and (out / "locs.csv").exists()
    assert json.loads((out / RECORD_NAME).read_text())["run"]["command"] == "detect"


def test_the_python_functions_refuse_in_their_own_names(data, tmp_path):
    model = Model(15, 79.0, EMCCD(200.0, 50.0, 100.0, 12.0))
    rules = Rules(min_valid_frames=8)
    # bayespsf.analyze(out=<a file>) raised a bare FileExistsError
    for out, words in (
        (data["camera"], "is a file, not a folder"),
        (data["camera"] / "inner", f"lies under {data['camera']}, which is a file"),
    ):
        with pytest.raises(BayespsfInputError) as refused:
            bayespsf.analyze(data["a0"], model, s0=120.0, out=out, rules=rules, workers=1)
        assert str(refused.value).startswith(f"out={str(out)!r} {words}")
        assert str(refused.value).endswith("give out a folder to write into")
    out = copy(data["analyzed"], tmp_path / "out")
    before = snapshot(out)
    with pytest.raises(RunConflict) as refused:
        bayespsf.analyze(data["a1"], model, s0=120.0, out=out, rules=rules, method="laplace")
    assert str(refused.value) == (
        f"out={str(out)!r} holds the results of another run: movie, camera.toml differ; give "
        "a new out folder, or force=True to replace them"
    )  # the command's run copied its camera file; this one copies none
    assert isinstance(refused.value, BayespsfInputError) and snapshot(out) == before
    found = find_molecules(data["d0"], model, s0=120.0)
    with pytest.raises(RunConflict, match=r"command \(analyze there, detect now\) differs"):
        write(found, out)
    assert snapshot(out) == before
    paths = write(found, out, force=True)
    assert set(paths) == {*SELECTION_FILES, RECORD_NAME}
    assert {p.name for p in out.iterdir()} == {*SELECTION_FILES, RECORD_NAME}
    assert write(found, out)["molecules.csv"].exists()  # the same run again


def test_an_interrupted_analyze_resumes_and_never_mixes_two_runs(data, tmp_path, monkeypatch):
    # killed while writing the posteriors of a run that --force put in another run's place
    out = copy(data["analyzed"], tmp_path / "out")
    save = Store.write

    def interrupted(self, *args):
        save(self, *args)
        raise KeyboardInterrupt  # once the first file of posteriors is written

    monkeypatch.setattr(Store, "write", interrupted)
    assert analyze(data["a1"], data["camera"], out, "--force") == 130  # "interrupted"
    monkeypatch.setattr(Store, "write", save)
    # the first run's files are gone, the second's record and first posteriors are there
    assert not (out / "locs.parquet").exists() and not (out / "report.md").exists()
    assert read_run_record(out)["about"]["movie"] == str(data["a1"])
    kept = {p.name: p.stat().st_mtime_ns for p in (out / "posteriors").glob("posteriors-*.nc")}
    assert len(kept) == 1 and stored(out / "posteriors")
    with pytest.raises(SystemExit, match="movie differs"):  # the folder is the second run's
        analyze(data["a0"], data["camera"], out)
    assert analyze(data["a1"], data["camera"], out) == 0  # resumed, without --force
    done = {p.name: p.stat().st_mtime_ns for p in (out / "posteriors").glob("posteriors-*.nc")}
    assert {k: done[k] for k in kept} == kept
    assert len(stored(out / "posteriors")) == len(pd.read_parquet(out / "locs.parquet")) == 8


def test_a_killed_analyze_process_resumes(data, tmp_path):
    # a real kill (SIGKILL, no clean-up) at whatever point the run has reached once its folder
    # is claimed; the rerun of the same run finishes it, another run is still refused
    out = tmp_path / "out"
    command = [sys.executable, "-m", "bayespsf.cli", "analyze", str(data["a0"])]
    command += ["--camera", str(data["camera"]), *ANALYZE, "--out", str(out)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (out / RECORD_NAME).exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    if process.poll() is None:
        os.kill(process.pid, signal.SIGKILL)
    _, err = process.communicate()
    assert (out / RECORD_NAME).exists(), err.decode()
    with pytest.raises(SystemExit, match="movie differs"):
        analyze(data["a1"], data["camera"], out)
    assert analyze(data["a0"], data["camera"], out) == 0
    locs = pd.read_parquet(out / "locs.parquet")
    assert len(stored(out / "posteriors")) == len(locs) == 15
    assert {p.name for p in out.iterdir()} <= {*ANALYSIS_FILES, RECORD_NAME, "camera.toml"}


def stored(folder):
    """The summary rows of the molecules in a store, by index."""
    return Store(folder).finished(10**6)


def test_the_record_is_generic_and_force_removes_only_the_runs_own_entries(tmp_path):
    from bayespsf.io.run_record import check_folder, claim_folder, file_fingerprint

    outside = tmp_path / "outside.txt"
    outside.write_text("not the run's")
    out = tmp_path / "out"
    run = {"command": "x", "value": float("nan"), "table": {"b": 1, "a": (2, 3)}}
    claim_folder(out, run, ["a.csv", "sub"])
    (out / "a.csv").write_text("1")
    (out / "sub").mkdir()
    (out / "sub" / "b.nc").write_text("2")
    (out / "mine.txt").write_text("3")
    same = {"table": {"a": [2, 3], "b": 1}, "value": float("nan"), "command": "x"}
    assert check_folder(out, same, ["a.csv", "sub"]) == []  # NaN, order, tuples: the same
    # a record edited by hand cannot make --force remove anything outside the run's names
    record = json.loads((out / RECORD_NAME).read_text())
    record["files"] += ["../outside.txt", str(outside), "..", ""]
    (out / RECORD_NAME).write_text(json.dumps(record))
    with pytest.raises(RunConflict, match=r"value \(nan there, 1.0 now\) differs"):
        check_folder(out, {**run, "value": 1.0}, ["a.csv", "sub"])
    claim_folder(out, {**run, "value": 1.0}, ["a.csv"], force=True)
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt", RECORD_NAME]
    assert outside.read_text() == "not the run's"
    # the fingerprint of a large file samples 16 blocks, from its first byte to its last
    big = tmp_path / "big.bin"
    big.write_bytes(bytes(10 << 20))
    first = file_fingerprint(big)
    with big.open("r+b") as handle:
        handle.seek((10 << 20) - 1)
        handle.write(b"\x01")
    assert file_fingerprint(big)["sha256"] != first["sha256"]
    assert file_fingerprint(big)["bytes"] == 10 << 20


def test_a_store_and_a_detect_or_analyze_run_refuse_each_others_folders(tmp_path):
    # `bayespsf fit` into a detect folder wrote its store beside the selection tables, and
    # detect into a fit store its tables beside the posteriors: each kind of run now refuses
    # the other's marker, and --force does not remove a run of the other kind
    from bayespsf.io.run_record import check_folder
    from bayespsf.parallel.store import RUN_RECORD

    assert RUN_RECORD == RECORD_NAME  # the store names the record a layer below its home
    run_folder, store_folder = tmp_path / "detected", tmp_path / "fitted"
    run_folder.mkdir()
    (run_folder / RECORD_NAME).write_text("{}")
    for refused in (Store(run_folder).lock, lambda: Store(run_folder).open({"molecules": 1})):
        with pytest.raises(BayespsfInputError, match=r"holds the results of a `bayespsf detect`"):
            refused()
    assert sorted(p.name for p in run_folder.iterdir()) == [RECORD_NAME]  # not even a .lock
    store_folder.mkdir()
    Store(store_folder).open({"molecules": 1})  # writes its manifest.json
    for force in (False, True):
        with pytest.raises(BayespsfInputError, match=r"fitted holds a posterior store \(manif"):
            check_folder(store_folder, {"run": 1}, SELECTION_FILES, force=force, option="--out")
    assert sorted(p.name for p in store_folder.iterdir()) == ["manifest.json"]
