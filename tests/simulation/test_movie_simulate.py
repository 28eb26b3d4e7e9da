"""Tests of bayespsf.simulation.movie: movies with exactly the effects a scene's [movie] declares.

Expected values come from the declarations and from the laws they state (exponential bleaching
times, the EMCCD's excess noise factor 2), not from the module's own arithmetic.
"""

from __future__ import annotations

import math
import re
import tracemalloc
import xml.etree.ElementTree as ET

import numpy as np
import pandas as pd
import pytest
import tifffile

from bayespsf import Scene, load_scene, simulate
from bayespsf.cli.commands import main
from bayespsf.scene import SceneError
from bayespsf.simulation import iter_movie, simulate_movie
from bayespsf.simulation.movie import MOLECULE_COLUMNS, TRUTH_COLUMNS, molecule_table

pytestmark = pytest.mark.filterwarnings("error")

EMCCD = {
    "kind": "emccd",
    "gain": 100.0,
    "readout_sd": 50.0,
    "offset": 100.0,
    "e_per_adu": 12.0,
    "quantize": True,
    "saturation": 65535.0,
}


def movie_scene(camera=None, emitter=None, background=None, **movie) -> Scene:
    return Scene.from_dict(
        {
            "geometry": {"pixel_size": 79.0},
            "emitter": {"photons": 2000.0, **(emitter or {})},
            "background": background or {"kind": "poisson", "mean": 2.0},
            "camera": camera or EMCCD,
            "movie": {"frames": 10, "height": 64, "width": 64, "molecules": 3, **movie},
        }
    )


def photons(counts, camera=EMCCD):
    """Counts in ADU back to photons (the mean law: offset + gain photons / e_per_adu)."""
    return (counts - camera["offset"]) * camera["e_per_adu"] / camera["gain"]


# ------------------------------------------------------------------------------ the scene table


def test_movie_table_is_optional_and_declares_a_movie():
    assert "movie" not in Scene.from_dict({}).to_dict()
    declared = Scene.from_dict({"movie": {}})
    assert declared.movie["frames"] == 100 and declared.movie["bleach_mean"] == 0.0
    assert Scene.from_dict(declared.to_dict()) == declared
    assert Scene.loads(declared.dumps()) == declared
    assert declared.replace(movie={"frames": 7}).movie["frames"] == 7


def test_paper_movie_scene():
    scene = load_scene("paper-movie")
    assert scene.geometry["pixel_size"] == 79.0
    assert scene.emitter["s0x"] == scene.emitter["s0y"] == 120.0
    assert scene.emitter["photon_jitter"] == 0.2
    assert scene.camera["kind"] == "emccd"
    m = scene.movie
    assert (m["photons_low"], m["photons_high"]) == (500.0, 5000.0)
    assert m["bleach_mean"] == 150.0 and m["min_spacing"] == 25 and m["dark_frames"] > 0


def test_roi_simulation_of_a_movie_scene_ignores_the_movie_table():
    scene = load_scene("paper-movie")
    without = Scene.from_dict({k: v for k, v in scene.to_dict().items() if k != "movie"})
    counts, truth = simulate(scene, 3, seed=2)
    expected_counts, expected_truth = simulate(without, 3, seed=2)
    np.testing.assert_array_equal(counts, expected_counts)
    pd.testing.assert_frame_equal(truth, expected_truth)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"emitter": {"width_jitter": 2.0}}, "emitter.width_jitter is not used by movies"),
        ({"optics": {"psf": "airy"}}, "optics.psf must be 'gaussian' in a movie scene"),
        ({"movie": {"blink_on": 3.0}}, "movie.blink_on and movie.blink_off declare blinking"),
    ],
)
def test_effects_a_movie_cannot_honour_are_refused(changes, message):
    scene = movie_scene().replace(**changes)
    with pytest.raises(SceneError, match=re.escape(message)):
        simulate_movie(scene, 0)


def test_a_scene_without_a_movie_is_refused():
    with pytest.raises(SceneError, match=r"declares no \[movie\] table"):
        simulate_movie(load_scene("paper-fig3"), 0)


# ------------------------------------------------------------------------------------ placement


def test_reproducible_for_a_seed():
    scene = movie_scene(bleach_mean=5.0, drift_x=3.0, moving=0.5, blink_on=2.0, blink_off=1.0)
    a, b, c = (simulate_movie(scene, s) for s in (4, 4, 5))
    np.testing.assert_array_equal(a.frames, b.frames)
    pd.testing.assert_frame_equal(a.truth, b.truth)
    pd.testing.assert_frame_equal(a.molecules, b.molecules)
    assert not np.array_equal(a.frames, c.frames)


def test_molecules_inside_the_frame_and_spaced():
    scene = movie_scene(frames=1, height=100, width=150, molecules=30, min_spacing=15, edge=7)
    mol = molecule_table(scene, 3)
    assert len(mol) == 30
    col, row = np.floor(mol["x"] + 0.5), np.floor(mol["y"] + 0.5)
    assert col.min() >= 7 and col.max() <= 150 - 1 - 7
    assert row.min() >= 7 and row.max() <= 100 - 1 - 7
    chebyshev = np.maximum(
        np.abs(col.to_numpy()[:, None] - col.to_numpy()),
        np.abs(row.to_numpy()[:, None] - row.to_numpy()),
    )
    np.fill_diagonal(chebyshev, np.inf)
    assert chebyshev.min() >= 15


def test_impossible_placement_names_the_keys():
    scene = movie_scene(height=60, width=60, molecules=20, min_spacing=25, edge=12)
    with pytest.raises(SceneError, match=r"movie\.molecules = 20.*min_spacing.*edge"):
        simulate_movie(scene, 0)


# -------------------------------------------------------------------------------------- photons


def test_bright_molecule_photons_per_frame_match_the_truth():
    """Counts -> photons, background subtracted, summed over 21 x 21 pixels around the molecule
    (+-6.9 SD: the mass outside is < 1e-11). Per frame the sum's variance is the EMCCD's
    2 (N + n b) (excess noise factor 2, the paper's Eq. photonuncerts) plus the readout's
    n (readout_sd / gain)^2 and the ADC's rounding n (e_per_adu / gain)^2 / 12; the mean error
    over 60 frames must lie within 4 of its SDs and the per-frame z-scores' SD within 0.7-1.3."""
    scene = movie_scene(frames=60, molecules=1, emitter={"photons": 8000.0, "photon_jitter": 0.2})
    movie = simulate_movie(scene, 11)
    x, y = movie.truth["x"].to_numpy(), movie.truth["y"].to_numpy()
    r, c = int(np.floor(y[0] + 0.5)), int(np.floor(x[0] + 0.5))
    window = photons(movie.frames[:, r - 10 : r + 11, c - 10 : c + 11].astype(float))
    n_pix, b = 21 * 21, 2.0
    signal = window.sum(axis=(1, 2)) - n_pix * b
    truth = movie.truth["photons"].to_numpy()
    assert truth.std() > 0.05 * truth.mean()  # the declared jitter is there
    sd = np.sqrt(2 * (truth + n_pix * b) + n_pix * (0.5**2 + 0.12**2 / 12))
    z = (signal - truth) / sd
    assert abs(z.mean()) < 4 / math.sqrt(z.size)
    assert 0.7 < z.std() < 1.3


def test_photons_log_uniform_between_the_declared_ends():
    scene = movie_scene(
        frames=1,
        height=400,
        width=400,
        molecules=400,
        min_spacing=0,
        photons_low=500.0,
        photons_high=5000.0,
    )
    n = molecule_table(scene, 1)["photons"]
    assert n.min() >= 500 and n.max() <= 5000
    u = (np.log(n) - np.log(500)) / np.log(10)  # uniform on [0, 1]
    assert abs(u.mean() - 0.5) < 4 * math.sqrt(1 / 12 / n.size)
    every = molecule_table(movie_scene(frames=1), 1)["photons"]
    assert (every == 2000.0).all()  # neither end declared: emitter.photons


# ------------------------------------------------------------------------------------ bleaching


def test_bleach_frames_follow_the_declared_exponential_mean():
    """bleach_frame = ceil(T), T ~ Exponential(mu): E = 1 / (1 - exp(-1/mu)), SD ~ mu; 3000
    molecules, within 4 Monte Carlo SEs; two-fluorophore molecules bleach at the later step."""
    mu = 20.0
    scene = movie_scene(
        frames=5000, height=600, width=600, molecules=3000, min_spacing=0, edge=0, bleach_mean=mu
    )
    mol = molecule_table(scene, 2)
    frames = mol["bleach_frame"].to_numpy(float)
    assert (mol["fluorophores"] == 1).all() and not mol["bleach_frame"].isna().any()
    expected = 1 / (1 - math.exp(-1 / mu))
    assert abs(frames.mean() - expected) < 4 * mu / math.sqrt(frames.size)
    two = molecule_table(scene.replace(movie={"two_fluorophores": 0.3}), 2)
    share = (two["fluorophores"] == 2).mean()
    assert abs(share - 0.3) < 4 * math.sqrt(0.3 * 0.7 / len(two))
    later = two.loc[two["fluorophores"] == 2, "bleach_frame"].to_numpy(float)
    # the later of two exponential times: E[max] = 1.5 mu
    assert abs(later.mean() - 1.5 * mu - 0.5) < 4 * 1.2 * mu / math.sqrt(later.size) + 0.1


def test_no_signal_from_the_bleach_frame_on():
    scene = movie_scene(frames=40, molecules=1, bleach_mean=12.0, emitter={"photons": 5000.0})
    bleach = {s: molecule_table(scene, s)["bleach_frame"][0] for s in range(20)}
    seed = next(s for s, k in bleach.items() if not pd.isna(k) and 5 <= k <= 30)
    movie = simulate_movie(scene, seed)
    k = int(movie.molecules["bleach_frame"][0])
    truth = movie.truth
    assert (truth["photons"][k:] == 0).all() and (~truth["on"][k:]).all()
    assert (truth["photons"][: k - 1] > 0).all() and truth["on"][:k].all()
    x, y = movie.molecules.loc[0, ["x", "y"]]
    r, c = int(np.floor(y + 0.5)), int(np.floor(x + 0.5))
    centre = photons(movie.frames[:, r - 2 : r + 3, c - 2 : c + 3].astype(float)).sum(axis=(1, 2))
    dark = centre[k:] - 25 * 2.0
    assert abs(dark.mean()) < 4 * math.sqrt(2 * 25 * 2.0 + 25 * 0.26) / math.sqrt(dark.size)
    assert centre[: k - 1].min() > 1000


# --------------------------------------------------------------------------- undeclared effects


def test_undeclared_effects_are_absent():
    movie = simulate_movie(movie_scene(frames=30, bleach_mean=10.0), 1)
    truth, mol = movie.truth, movie.molecules
    for _, rows in truth.groupby("molecule"):
        assert rows["x"].nunique() == 1 and rows["y"].nunique() == 1  # no drift, no walk
    assert (mol["fluorophores"] == 1).all() and not mol["moving"].any()
    assert truth["fluorophores_on"].max() <= 1
    bleach = truth["molecule"].map(mol["bleach_frame"].fillna(10**9))
    np.testing.assert_array_equal(truth["on"], truth["frame"] < bleach)  # on until bleaching
    plain = simulate_movie(movie_scene(frames=5), 1)
    assert plain.truth["on"].all() and plain.molecules["bleach_frame"].isna().all()
    assert plain.dark.shape == (0, 64, 64)


def test_drift_moves_every_position_by_the_declared_nm_per_frame():
    movie = simulate_movie(movie_scene(frames=8, drift_x=7.9, drift_y=-15.8), 3)
    t = movie.truth.merge(
        movie.molecules[["molecule", "x", "y"]], on="molecule", suffixes=("", "0")
    )
    np.testing.assert_allclose(t["x"] - t["x0"], 0.1 * t["frame"], atol=1e-12)
    np.testing.assert_allclose(t["y"] - t["y0"], -0.2 * t["frame"], atol=1e-12)


def test_only_moving_molecules_walk():
    scene = movie_scene(frames=50, height=128, width=128, molecules=6, moving=0.5, moving_step=20.0)
    movie = simulate_movie(scene, 5)
    moves = movie.truth.groupby("molecule")["x"].nunique() > 1
    np.testing.assert_array_equal(moves.to_numpy(), movie.molecules["moving"].to_numpy())
    assert movie.molecules["moving"].any()


def test_blinking_keeps_the_declared_on_fraction():
    scene = movie_scene(frames=400, molecules=2, blink_on=3.0, blink_off=1.0)
    truth = pd.concat(t for _, t in iter_movie(scene, 8))
    share = truth["photons"].sum() / (2000.0 * len(truth))
    assert abs(share - 0.75) < 0.06
    assert (~truth["on"]).any()


def test_fixed_photon_statistics_give_whole_photons():
    scene = movie_scene(frames=3, emitter={"photon_statistics": "fixed", "photon_jitter": 0.1})
    truth = simulate_movie(scene, 0).truth
    np.testing.assert_array_equal(truth["photons"], np.rint(truth["photons"]))


# ---------------------------------------------------------------------------------------- files


def test_files_columns_metadata_and_frames(tmp_path):
    scene = movie_scene(frames=6, bleach_mean=3.0, exposure=0.05, dark_frames=2)
    made = simulate_movie(scene, 9, out=tmp_path / "sub" / "m")
    assert made.frames is None and made.truth is None
    assert sorted(made.files) == ["dark", "molecules", "movie", "truth"]
    assert made.files["movie"].name == "m.ome.tif" and made.files["dark"].name == "m.dark.ome.tif"
    molecules, truth = (pd.read_csv(made.files[k]) for k in ("molecules", "truth"))
    assert list(molecules.columns) == list(MOLECULE_COLUMNS)
    assert list(truth.columns) == list(TRUTH_COLUMNS)
    assert len(truth) == 6 * 3 and truth["on"].dtype == bool
    np.testing.assert_allclose(molecules["x_nm"], molecules["x"] * 79.0)
    memory = simulate_movie(scene, 9)
    for key, frames in (("movie", memory.frames), ("dark", memory.dark)):
        with tifffile.TiffFile(made.files[key]) as tif:
            assert len(tif.pages) == len(frames) and tif.pages[0].shape == (64, 64)
            np.testing.assert_array_equal(tif.asarray(), frames)
            assert tif.pages[0].dtype == np.uint16
            ome = ET.fromstring(tif.ome_metadata)
        pixels = next(e for e in ome.iter() if e.tag.endswith("Pixels"))
        assert float(pixels.get("PhysicalSizeX")) == pytest.approx(0.079)
        assert float(pixels.get("PhysicalSizeY")) == pytest.approx(0.079)
        assert pixels.get("PhysicalSizeXUnit") == "µm"
        assert float(pixels.get("TimeIncrement")) == pytest.approx(0.05)
    pd.testing.assert_frame_equal(truth, memory.truth, check_dtype=False)


def test_unquantised_counts_are_written_as_float32(tmp_path):
    scene = movie_scene(frames=2, camera={"kind": "emccd", "gain": 50.0})
    made = simulate_movie(scene, 0, out=tmp_path / "f")
    assert tifffile.imread(made.files["movie"]).dtype == np.float32
    assert "dark" not in made.files


def test_memory_does_not_grow_with_the_frame_count(tmp_path):
    def peak(frames):
        scene = movie_scene(frames=frames, height=128, width=128, molecules=4, bleach_mean=20.0)
        tracemalloc.start()
        simulate_movie(scene, 0, out=tmp_path / f"m{frames}")
        top = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return top

    short, long = peak(50), peak(400)
    assert long < 1.2 * short, (short, long)


# ------------------------------------------------------------------------------------------ CLI


def test_cli_writes_the_movie_files(tmp_path, capsys):
    path = tmp_path / "movie.toml"
    movie_scene(frames=4, dark_frames=1).save(path)
    assert (
        main(["simulate", str(path), "--movie", "--seed", "2", "--out", str(tmp_path / "o")]) == 0
    )
    for suffix in (".ome.tif", ".molecules.csv", ".truth.csv", ".dark.ome.tif"):
        assert (tmp_path / f"o{suffix}").is_file(), suffix
    assert "wrote 4 frames of 64 x 64 pixels with 3 molecules" in capsys.readouterr().out
    assert tifffile.imread(tmp_path / "o.ome.tif").shape == (4, 64, 64)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["paper-fig3", "--movie"], "bayespsf: --movie: the scene paper-fig3 declares no [movie]"),
        (["paper-movie", "--movie", "-n", "5"], "bayespsf: -n does not apply with --movie"),
    ],
)
def test_cli_errors(args, message, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", *args, "--out", str(tmp_path / "x")])
    assert str(exc.value).startswith(message)
