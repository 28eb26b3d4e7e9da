"""Per-frame localisation (``localize_frames``, ``bayespsf detect|analyze --per-frame``): every
spot of every frame found and localised in its own frame, with error bars that hold against the
simulation's truth."""

import json
import os

import numpy as np
import pandas as pd
import pytest

from bayespsf import Model, cli, load_scene, simulate_movie
from bayespsf.analysis import localizations, localize_frames
from bayespsf.errors import BayespsfInputError
from bayespsf.io import CAMERA_KEYS
from bayespsf.parallel import Store
from bayespsf.psf import PARAMETER_NAMES as NAMES


def _scene(frames, molecules, side=96):
    """paper-movie's molecules and camera on a Poisson background of 3 photons per pixel (the
    model's: paper-movie's own truncated-Gaussian background is quieter than Poisson, and its
    MLE errors read 0.91 +- 0.02 of the Cramér-Rao bound over 888 localisations)."""
    return load_scene("paper-movie").replace(
        background={"kind": "poisson", "mean": 3.0},
        movie={
            "frames": frames,
            "height": side,
            "width": side,
            "molecules": molecules,
            "dark_frames": 0,
            "two_fluorophores": 0.0,
            "moving": 0.0,
        },
    )


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """8 frames of 96 x 96 pixels with 6 immobile molecules (paper-movie's EMCCD, s0 120 nm)."""
    scene = _scene(8, 6)
    folder = tmp_path_factory.mktemp("per_frame")
    made = simulate_movie(scene, seed=3, out=folder / "m")
    truth = pd.read_csv(made.files["truth"])
    return made.files["movie"], _camera_file(scene, folder), Model.from_scene(scene), truth


def _camera_file(scene, folder):
    """The scene's EMCCD and pixel size as a camera file (``folder/camera.toml``)."""
    camera = {k: v for k, v in scene.to_dict()["camera"].items() if k in CAMERA_KEYS["emccd"]}
    lines = [f"{k} = {v!r}" for k, v in {"kind": "emccd", **camera}.items()]
    lines += ["[geometry]", "pixel_size = 79.0"]
    (folder / "camera.toml").write_text("[camera]\n" + "\n".join(lines) + "\n")
    return folder / "camera.toml"


def _matched(locs, truth, radius=1.0):
    """Each localisation's nearest molecule that is on in its frame (NaN-free rows only), and
    the localisations farther than ``radius`` pixels from every such molecule."""
    on = truth[truth["on"]]
    rows, false = [], 0
    for _, loc in locs.iterrows():
        here = on[on["frame"] == loc["frame"]]
        distance = np.hypot(here["x"] - loc["x"], here["y"] - loc["y"])
        if len(here) and distance.min() <= radius:
            near = here.iloc[int(np.argmin(distance.to_numpy()))]
            rows.append({**loc.to_dict(), "x_true": near["x"], "y_true": near["y"]})
        else:
            false += 1
    return pd.DataFrame(rows), false


def _z_scores(matched):
    """The errors of x and y against the truth over their SDs (``lpx``, ``lpy``)."""
    x = (matched["x"] - matched["x_true"]) / matched["lpx"]
    return np.concatenate([x, (matched["y"] - matched["y_true"]) / matched["lpy"]])


def test_every_spot_of_every_frame_is_localised_within_its_error_bar(movie, tmp_path):
    path, _, model, truth = movie
    found = localize_frames(path, model, s0=120.0, out=tmp_path / "d", posterior=False)
    locs = found.locs
    matched, false = _matched(locs, truth)
    on = truth[truth["on"]]
    # recall: every molecule that is on (its faintest frame here holds ~400 photons, far above
    # the threshold's ~100) is found in every frame where it shines
    assert len(matched) == len(on) == 8 * 6
    # 0.01 false candidates per frame are stated: 0.08 expected over 8 frames, so at most one
    assert false <= 1
    # the MLE's errors against the truth, in units of its Cramér-Rao bound: SD 1 when the
    # bound holds (1.01 +- 0.03 over 664 coordinates of this scene); 96 coordinates give the
    # SD a standard error of ~0.07 (tolerance ~3 SE)
    z = _z_scores(matched)
    assert 0.78 < np.std(z) < 1.22 and abs(np.mean(z)) < 0.31
    # the candidates table says which were localised, and the locs name the candidate
    accepted = found.candidates[found.candidates["status"] == "accepted"]
    assert sorted(locs["molecule"]) == sorted(accepted["molecule"])
    assert {"locs.hdf5", "locs.yaml", "locs.csv", "locs.parquet", "candidates.csv"} <= set(
        found.paths
    )
    assert "Per-frame localisation" in (tmp_path / "d" / "report.md").read_text()


def test_posteriors_per_frame_cover_the_truth(tmp_path):
    """The posterior path on a 2-frame movie of 4 molecules (8 windows), one process."""
    scene = _scene(2, 4, side=80)
    made = simulate_movie(scene, seed=11, out=tmp_path / "m")
    truth = pd.read_csv(made.files["truth"])
    found = localize_frames(
        made.files["movie"], Model.from_scene(scene), s0=120.0, out=tmp_path / "a", workers=1
    )
    locs = found.locs
    assert (locs["status"] == "converged").all() and locs["x0_mean"].notna().all()
    matched, false = _matched(locs, truth)
    assert len(matched) == 8 and false == 0
    # posterior SDs against the truth: 16 coordinates, |z| < 3.5 for each (a 3.5-SD miss has
    # probability 0.7% over 16 normal draws)
    z = _z_scores(matched)
    assert np.all(np.abs(z) < 3.5)
    # the MLE and least squares are kept beside the posterior; the store holds the chunk
    assert {"x0_mle", "crlb_x0", "x0_lsq", "gof_p"} <= set(locs.columns)
    assert (tmp_path / "a" / "posteriors" / "chunk-00000" / "summary.csv").exists()
    # --no-draws: the same table from chunk stores that keep no draws, recorded in run.json
    base = ["analyze", str(made.files["movie"]), "--camera", str(_camera_file(scene, tmp_path))]
    base += ["--psf-sd", "120", "--workers", "1", "--no-draws"]
    assert cli.main([*base, "--per-frame", "--out", str(tmp_path / "b")]) == 0
    bare = pd.read_csv(tmp_path / "b" / "locs.csv")
    assert np.allclose(bare["x [nm]"], pd.read_csv(tmp_path / "a" / "locs.csv")["x [nm]"])
    assert not Store(tmp_path / "b" / "posteriors" / "chunk-00000").keeps_draws()
    record = json.loads((tmp_path / "b" / "run.json").read_text())
    assert record["run"]["draws"] == "not kept"
    with pytest.raises(SystemExit, match="--no-draws goes with --per-frame"):
        cli.main([*base, "--out", str(tmp_path / "c")])
    with pytest.raises(BayespsfInputError, match="keep_draws"):  # not a bool
        localize_frames(
            made.files["movie"], Model.from_scene(scene), out=tmp_path / "e", keep_draws="no"
        )
    with pytest.raises(BayespsfInputError, match="keep_draws"):
        localize_frames(
            made.files["movie"],
            Model.from_scene(scene),
            out=tmp_path / "d",
            posterior=False,
            keep_draws=False,
        )


def test_the_command_line_runs_per_frame_and_refuses_trace_options(movie, tmp_path, capsys):
    path, camera, _, _ = movie
    base = ["detect", str(path), "--camera", str(camera), "--psf-sd", "120", "--per-frame"]
    assert cli.main([*base, "--out", str(tmp_path / "d")]) == 0
    printed = capsys.readouterr().out
    assert "48 localisations in 8 of 8 frames" in printed
    record = json.loads((tmp_path / "d" / "run.json").read_text())
    assert record["run"]["per frame"] is True and record["run"]["command"] == "detect"
    locs = pd.read_csv(tmp_path / "d" / "locs.csv")
    assert len(locs) == 48  # ThunderSTORM's table, one row per localisation
    # options that need a trace or a projection are refused by name
    for extra in (["--rules", "none"], ["--skip-rule", "snr"], ["--roi", "25"]):
        with pytest.raises(SystemExit, match=f"{extra[0]}.*not with --per-frame"):
            cli.main([*base, *extra, "--out", str(tmp_path / "x")])
    # another run's folder is refused before any work
    with pytest.raises(SystemExit, match="--force"):
        cli.main([*base, "--fit", "13", "--out", str(tmp_path / "d")])


def test_localizations_from_the_mle_and_bad_estimate():
    table = pd.DataFrame(
        {"molecule": [0], "frame": [2], "row": [10], "col": [20]}
        | {f"{p}_mle": [v] for p, v in zip(NAMES, [79, -79, 120, 158, 900, 5], strict=True)}
        | {f"crlb_{p}": [v] for p, v in zip(NAMES, [7.9, 15.8, 3, 3, 30, 0.2], strict=True)}
    )
    locs = localizations(table, 79.0, estimate="mle")
    assert locs.loc[0, ["x", "y", "sx", "sy", "lpx", "lpy"]].tolist() == pytest.approx(
        [21.0, 9.0, 120 / 79, 2.0, 0.1, 0.2], rel=1e-6
    )
    # a fit that did not converge gives no position: picasso leaves the row out, the last
    # iterate stays in <p>_mle and the missing column says why
    # a window refused before fitting likewise, with the refusal as the reason
    three = pd.concat([table] * 3, ignore_index=True).assign(
        mle_converged=[True, False, False],
        mle_status=["converged", "not converged", "refused"],
        mle_message=["", "iteration limit (200)", "every pixel has the same value (5)"],
    )
    three.loc[2, [f"{p}_mle" for p in NAMES] + [f"crlb_{p}" for p in NAMES]] = np.nan
    locs = localizations(three, 79.0, estimate="mle")
    assert np.isfinite(locs.loc[0, ["x", "y", "photons", "lpx"]].to_numpy(float)).all()
    picasso = ["x", "y", "photons", "sx", "sy", "bg", "lpx", "lpy"]
    assert locs.loc[[1, 2], picasso].isna().all().all()
    assert (locs["frame"] == 2).all() and locs.loc[1, "x0_mle"] == 79
    assert locs.loc[1, "missing"] == (
        "x, y, photons, sx, sy, bg, lpx, lpy: the maximum-likelihood fit did not converge"
    )
    assert locs.loc[2, "missing"].startswith(
        "x, y, photons, sx, sy, bg, lpx, lpy: the ROI was refused (every pixel has the same"
    )
    assert locs.loc[0, "missing"] == ""
    from bayespsf.analysis.per_frame import FrameLocalizations, _report
    from bayespsf.movie import PsfWidth

    candidates = pd.DataFrame({"status": ["accepted"] * 3})
    result = FrameLocalizations(candidates, locs, PsfWidth(sd=120.0, source="given"))
    report = _report(result, 3, posterior=False, provenance={})
    assert "- Maximum-likelihood fits converged: 1 of 3." in report
    assert "1 fit(s) that did not converge" in report
    assert "and 1 window(s) refused before fitting." in report
    with pytest.raises(BayespsfInputError, match="estimate must be"):
        localizations(table, 79.0, estimate="map")
    with pytest.raises(BayespsfInputError, match="x0_mean"):
        localizations(table, 79.0)


def test_a_bad_window_is_named_as_the_fit(movie):
    # frame_spots checks fit as both sides of one window: the error names fit, not roi
    from bayespsf.analysis.per_frame import frame_spots

    path, _, model, _ = movie
    for fit in (4, None, 7.0):
        with pytest.raises(BayespsfInputError, match=r"^fit must be an odd number of pixels"):
            next(iter(frame_spots(path, model.for_roi(15), psf_sd=120.0, fit=fit)))


def test_workers_and_the_order_tasks_finish_in_change_no_result(movie, tmp_path, monkeypatch):
    """Chunks of 7 windows (48 windows: 7 chunks, split inside frames) and blocks of 3 frames:
    one process, 3 threads on which the first block finishes last, 2 worker processes and a
    Dask cluster of 2 give the same tables and stores to the last bit (only the timings
    differ)."""
    import concurrent.futures as cf
    import time

    from bayespsf.analysis import frame_tasks, per_frame
    from bayespsf.parallel import local_executor

    path, _, model, _ = movie
    monkeypatch.setattr(frame_tasks, "CHUNK", 7)
    monkeypatch.setattr(per_frame, "block_frames", lambda shape, frames, workers: 3)
    options = dict(s0=120.0, method="laplace", gof_discrepancy="pearson")

    def run(name, **where):
        found = localize_frames(path, model, out=tmp_path / name, **options, **where)
        stores = sorted(p.name for p in (tmp_path / name / "posteriors").iterdir())
        return found, stores

    alone, stores = run("alone", workers=1)
    assert len(alone.locs) == 48 and stores == [f"chunk-{k:05d}" for k in range(7)]
    finished = []
    detect = frame_tasks.block_spots

    def first_block_last(first, frames, settings):
        time.sleep(0.5 if first == 0 else 0.0)
        finished.append(first)
        return detect(first, frames, settings)

    with monkeypatch.context() as patch:
        patch.setattr(frame_tasks, "block_spots", first_block_last)
        with cf.ThreadPoolExecutor(3) as threads:
            late = run("threads", executor=threads)
    assert finished[-1] == 0 and sorted(finished) == [0, 3, 6]
    with local_executor(2) as pool:
        processes = run("processes", executor=pool)
    distributed = pytest.importorskip("distributed")  # a dependency: installed by pyproject
    # ":0": the scheduler's HTTP server on a free port (None still binds 8787, which another
    # test's cluster may hold when the tests run in parallel: a warning, an error here)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, dashboard_address=":0", processes=True
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        dask = run("dask", executor=client)
    for found, folders in (late, processes, dask):
        assert folders == stores
        pd.testing.assert_frame_equal(found.candidates, alone.candidates)
        pd.testing.assert_frame_equal(
            found.locs.drop(columns="seconds"), alone.locs.drop(columns="seconds")
        )


def test_the_device_localises_the_chunks_while_workers_detect(movie, tmp_path, monkeypatch):
    """``backend="jax"``: the chunks run in this process (where the device is), the blocks of
    frames on the workers; the tables do not depend on the workers."""
    pytest.importorskip("jax")
    from bayespsf.analysis import frame_tasks, per_frame
    from bayespsf.parallel import local_executor

    path, _, model, _ = movie
    monkeypatch.setattr(frame_tasks, "CHUNK", 20)
    monkeypatch.setattr(per_frame, "block_frames", lambda shape, frames, workers: 2)
    options = dict(s0=120.0, method="laplace", backend="jax", gof_discrepancy="pearson")
    alone = localize_frames(path, model, out=tmp_path / "a", workers=1, **options)
    localized, localize = [], frame_tasks.localize_chunk

    def here(*args):  # a local function: a worker could not even unpickle it
        localized.append(os.getpid())
        return localize(*args)

    monkeypatch.setattr(frame_tasks, "localize_chunk", here)
    with local_executor(2) as pool:
        pooled = localize_frames(path, model, out=tmp_path / "p", executor=pool, **options)
    assert localized == [os.getpid()] * 3  # 48 windows: chunks of 20, 20 and 8
    assert len(alone.locs) == 48 and (alone.locs["method"] == "laplace").all()
    pd.testing.assert_frame_equal(
        pooled.locs.drop(columns="seconds"), alone.locs.drop(columns="seconds")
    )


def test_a_frames_accepted_places_are_its_accepted_rows():
    from bayespsf.analysis.frame_tasks import _accepted_places
    from bayespsf.analysis.localizations import PLACE_COLUMNS

    rng = np.random.default_rng(0)
    others = np.array(["edge", "neighbour", "saturated"], dtype=object)
    for n, accept in ((9, 0.5), (4, 0.0), (0, 0.0), (5, 1.0)):  # some, none, empty, all
        status = np.where(rng.random(n) < accept, "accepted", others[np.arange(n) % 3])
        table = pd.DataFrame(
            {
                "frame": np.full(n, 7),
                "row": rng.integers(0, 99, n),
                "col": rng.integers(0, 99, n),
                "status": status.astype(object),
                "amplitude": rng.random(n),
            },
            index=np.arange(10, 10 + n),  # not from 0: the places are
        )
        numbered = table.assign(molecule=np.arange(40, 40 + n))  # the frame's from 40
        expected = numbered.loc[numbered["status"] == "accepted", list(PLACE_COLUMNS)]
        pd.testing.assert_frame_equal(
            _accepted_places(table, 40), expected.reset_index(drop=True), check_exact=True
        )


def test_a_short_movie_is_cut_into_blocks_that_every_worker_gets():
    from bayespsf.analysis.frame_tasks import BLOCKS_PER_WORKER, block_frames

    assert block_frames((256, 256)) == 64  # BLOCK_PIXELS of them
    assert block_frames((2048, 2048)) == 1 and block_frames((64, 64)) == 64  # 1 to 64
    assert block_frames((256, 256), 100_000, 16) == 64  # a long movie: the largest
    for frames, workers in ((200, 16), (200, 2), (7, 4), (1, 16), (1000, 3)):
        block = block_frames((256, 256), frames, workers)
        blocks = -(-frames // block)
        wanted = BLOCKS_PER_WORKER * workers
        assert blocks >= min(frames, wanted), (frames, workers, block)  # every worker its own
        assert block >= min(64, max(1, frames // wanted))  # no smaller than that needs
