"""Molecules over time: ROIs cut at the recorded pixels, the ROI
centre convention, aperture photons and periphery background against the truth within their
SEs, bleach steps, two-step flags, false steps and drift on simulated EMCCD movies at the
paper's photon levels.

Monte Carlo setup (module fixture ``paper_movie``): 144 molecules on a 12 × 12 grid (25 pixels
apart) in 150 frames of 300 × 300 pixels, 79 nm pixels, s0 = 120 nm, N per frame log-uniform
in 500–5000 photons, background 3 photons per pixel, EMCCD gain 100, readout 10 e-, offset
100 ADU (rounded to uint16). 100 molecules bleach in one step at a frame uniform in 15–134;
24 in two steps (two equal fluorophores, the first bleaching 5–30 frames before the second);
20 never bleach, 10 of them static and 10 drifting by 0.002–0.006 pixels per frame.
"""

import numpy as np
import pandas as pd
import pytest
import tifffile

from bayespsf import Model, fit_mle, psf
from bayespsf.cameras import EMCCD, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.movie import (
    bleach_steps,
    cut_rois,
    iter_rois,
    molecules_over_time,
    read_movie,
    traces,
)
from bayespsf.movie.traces import drift

A, S0, B = 79.0, 120.0, 3.0
FRAMES, GRID = 150, 12


def _movie(shape, molecules, photons, camera, rng, b=B, drift_xy=None):
    """Frames ``shape`` of background ``b`` plus each molecule's spot (``photons`` (M, F)
    per frame, ``drift_xy`` (M, 2) pixels per frame), sampled by ``camera``."""
    frames = shape[0]
    expected = np.full(shape, b)
    t = np.arange(frames)
    for k, (x, y) in enumerate(zip(molecules["x"], molecules["y"], strict=True)):
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        vx, vy = (0.0, 0.0) if drift_xy is None else drift_xy[k]
        params = np.column_stack(
            [
                (x + vx * t - c) * A,
                (y + vy * t - r) * A,
                np.full((frames, 2), S0),
                photons[k],
                np.zeros(frames),
            ]
        )
        expected[:, r - 7 : r + 8, c - 7 : c + 8] += psf.expected_counts(params, 15, A)
    return camera.sample(expected, rng)


@pytest.fixture(scope="module")
def paper_movie(tmp_path_factory):
    rng = np.random.default_rng(2010)
    m = GRID * GRID
    gy, gx = np.divmod(np.arange(m), GRID)
    molecules = pd.DataFrame(
        {
            "molecule": np.arange(100, 100 + m),
            "x": gx * 25 + 12 + rng.uniform(-0.5, 0.5, m),
            "y": gy * 25 + 12 + rng.uniform(-0.5, 0.5, m),
        }
    )
    kind = np.array(["one"] * 100 + ["two"] * 24 + ["static"] * 10 + ["drift"] * 10)
    n = np.exp(rng.uniform(np.log(500), np.log(5000), m))
    bleach = rng.integers(15, 135, m)
    first = bleach - rng.integers(5, 31, m)
    bleach[kind == "two"] = np.maximum(bleach[kind == "two"], 40)
    first = np.maximum(first, 5)
    t = np.arange(FRAMES)[None, :]
    level = (t < bleach[:, None]).astype(float)
    level[kind == "two"] *= np.where(t < first[kind == "two", None], 1.0, 0.5)
    level[np.isin(kind, ["static", "drift"])] = 1.0
    drift_xy = np.zeros((m, 2))
    drift_xy[kind == "drift"] = rng.uniform(0.002, 0.006, (10, 2)) * rng.choice([-1, 1], (10, 2))
    camera = EMCCD(100.0, 10.0, 100.0)
    counts = _movie(
        (FRAMES, 300, 300), molecules, n[:, None] * level, camera, rng, drift_xy=drift_xy
    )
    path = tmp_path_factory.mktemp("movie") / "paper.npy"
    np.save(path, np.clip(np.rint(counts), 0, 65535).astype(np.uint16))
    per_molecule, per_frame = molecules_over_time(path, molecules, camera, s0=S0, pixel_size=A)
    truth = dict(kind=kind, n=n, bleach=bleach, level=level, drift=drift_xy)
    return molecules, truth, per_molecule, per_frame


def test_rois_are_the_movies_pixels_at_their_recorded_corner(tmp_path):
    data = np.random.default_rng(1).integers(0, 60_000, (7, 40, 50)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "m.tif", data, photometric="minisblack")
    molecules = pd.DataFrame({"molecule": ["a", "b"], "x": [10.5, 38.49], "y": [9.0, 30.2]})
    stack = cut_rois(tmp_path / "m.tif", molecules, roi=9, fit=5, block=3)
    assert stack.counts.shape == (14, 9, 9) and stack.counts.dtype == np.uint16
    assert list(stack.table.columns) == ["molecule", "frame", "row0", "col0"]
    assert list(stack.table["molecule"]) == ["a"] * 7 + ["b"] * 7  # by molecule, then frame
    assert stack.table.iloc[0][["row0", "col0"]].tolist() == [5, 7]  # x = 10.5 rounds up to 11
    for k, row in stack.table.iterrows():
        patch = data[row.frame, row.row0 : row.row0 + 9, row.col0 : row.col0 + 9]
        np.testing.assert_array_equal(stack.counts[k], patch)
    assert stack.central().shape == (14, 5, 5) and stack.central(7).shape == (14, 7, 7)
    np.testing.assert_array_equal(stack.central()[:, 2, 2], stack.counts[:, 4, 4])
    background = stack.periphery_background(Photon())
    assert list(background.columns) == ["b", "b_se"] and len(background) == 14
    ring = np.ones((9, 9), bool)
    ring[2:7, 2:7] = False
    np.testing.assert_allclose(background["b"], stack.counts[:, ring].mean(axis=1))
    blocks = list(iter_rois(read_movie(tmp_path / "m.tif"), molecules, roi=9, fit=5, block=3))
    assert [len(b) for b in blocks] == [6, 6, 2]
    joined = pd.concat([b.table for b in blocks]).assign(k=np.arange(14))
    order = joined.sort_values(["molecule", "frame"])["k"].to_numpy()
    np.testing.assert_array_equal(np.concatenate([b.counts for b in blocks])[order], stack.counts)
    part = cut_rois(tmp_path / "m.tif", molecules, roi=9, fit=5, frames=slice(2, 5))
    assert list(part.table["frame"]) == [2, 3, 4] * 2


def test_the_roi_centre_is_the_molecules_pixel_centre(tmp_path):
    """A spot at x = j + 0.3, y = i - 0.2 pixels fits at x0 = +0.3 a, y0 = -0.2 a nm in the
    central ROI (mean of 40 frames within 4 of its SEs, the CRLB over sqrt(40))."""
    rng = np.random.default_rng(3)
    molecules = pd.DataFrame({"molecule": [0], "x": [20.3], "y": [17.8]})
    counts = _movie((40, 40, 40), molecules, np.full((1, 40), 3000.0), Photon(), rng)
    np.save(tmp_path / "m.npy", counts.astype(np.uint16))
    stack = cut_rois(tmp_path / "m.npy", molecules, roi=25, fit=15)
    fits = fit_mle(stack.central(), Model(15, A, Photon()), laplace=False)
    assert fits["converged"].all()
    for name, truth in (("x0", 0.3 * A), ("y0", -0.2 * A)):
        se = fits[f"crlb_{name}"].mean() / np.sqrt(len(fits))
        assert abs(fits[name].mean() - truth) < 4 * se, (name, fits[name].mean(), se)


def test_aperture_photons_and_background_agree_with_the_truth(paper_movie):
    """Frames before any step: (photons - N) / photons_se has mean within 0.1 and SD within
    0.9–1.1 (~9 000 frames); the periphery b likewise against 3 photons per pixel."""
    molecules, truth, _, per_frame = paper_movie
    lit = truth["level"].ravel() == 1.0
    z = (per_frame["photons"] - np.repeat(truth["n"], FRAMES)) / per_frame["photons_se"]
    assert abs(z[lit].mean()) < 0.1 and 0.9 < z[lit].std() < 1.1
    zb = (per_frame["b"] - B) / per_frame["b_se"]
    assert abs(zb.mean()) < 0.1 and 0.9 < zb.std() < 1.1
    static = np.repeat(np.isin(truth["kind"], ["one", "two", "static"]), FRAMES) & lit
    dx = per_frame["x"] - np.repeat(molecules["x"].to_numpy(), FRAMES)
    assert abs(dx[static].median()) < 0.01  # centroid in picasso's pixel convention


def test_bleach_steps_on_the_paper_movie(paper_movie):
    """>= 90% of single-step molecules: one step, bleach frame within +-1 frame; >= 90% of
    two-step molecules flagged; no step on the static constant molecules."""
    _, truth, per_molecule, _ = paper_movie
    kind = truth["kind"]
    one = per_molecule[kind == "one"]
    hit = (one["steps"] == 1) & ((one["bleach_frame"] - truth["bleach"][kind == "one"]).abs() <= 1)
    assert hit.mean() >= 0.9, hit.mean()
    assert (one["frames_before"] == one["bleach_frame"]).all()
    two = per_molecule[kind == "two"]
    assert two["multiple_steps"].mean() >= 0.9
    assert ((two["bleach_frame"] - truth["bleach"][kind == "two"]).abs() <= 1).mean() >= 0.9
    static = per_molecule[kind == "static"]
    assert (static["steps"] == 0).all() and static["bleach_frame"].isna().all()
    assert (static["frames_before"] == FRAMES).all()
    assert ((one["photons_mean"] / truth["n"][kind == "one"] - 1).abs() < 0.1).all()


def test_drift_slopes_are_recovered_within_their_se(paper_movie):
    """Drifting and static molecules: |slope - truth| < 4 SE in x and y for all 20."""
    _, truth, per_molecule, _ = paper_movie
    rows = np.isin(truth["kind"], ["static", "drift"])
    for axis, column in ((0, "drift_x"), (1, "drift_y")):
        slope = per_molecule.loc[rows, column].to_numpy()
        se = per_molecule.loc[rows, f"{column}_se"].to_numpy()
        z = (slope - truth["drift"][rows, axis] * A) / se
        assert np.all(np.abs(z) < 4), z


def test_no_false_steps_on_constant_emccd_traces():
    """300 constant traces of 100 frames: aperture sums of 45 EMCCD pixels (N 500–5000,
    b = 3, gain 100), background removed: at most 3 traces (1%) with a step (measured: 3 of
    1 000 such traces, and 1 of 1 000 Gaussian traces of 150 frames)."""
    rng = np.random.default_rng(7)
    n = np.exp(rng.uniform(np.log(500), np.log(5000), 300))
    lam = n[:, None, None] * np.full(45, 0.95 / 45) + B
    camera = EMCCD(100.0, 10.0, 100.0)
    photons = ((camera.sample(np.broadcast_to(lam, (300, 100, 45)), rng) - 100.0) / 100.0).sum(-1)
    false = sum(bleach_steps(trace - 45 * B).steps > 0 for trace in photons)
    assert false <= 3


def test_bleach_steps_places_and_labels_a_step():
    rng = np.random.default_rng(4)
    y = np.r_[1000 + 40 * rng.standard_normal(57), 20 * rng.standard_normal(43)]
    found = bleach_steps(y, frames=np.arange(200, 300))
    assert found.steps == 1 and found.bleach_frame == 257 and found.frames_before == 57
    assert found.change_points == (257,) and not found.multiple_steps
    assert found.levels[0] > 900 and abs(found.levels[1]) < 20
    up = bleach_steps(y[::-1])  # a molecule switching on: a step, no bleaching
    assert up.steps == 1 and up.bleach_frame is None and up.frames_before == 100
    assert bleach_steps(np.full(20, 5.0)).steps == 0
    slope, se = drift(np.arange(50), 0.5 * np.arange(50) + rng.standard_normal(50))
    assert abs(slope - 0.5) < 4 * se


def test_bad_inputs_are_named(tmp_path):
    np.save(tmp_path / "m.npy", np.zeros((3, 30, 30), np.uint16))
    path = tmp_path / "m.npy"
    ok = pd.DataFrame({"molecule": [1, 2], "x": [15.0, 15.0], "y": [15.0, 12.0]})
    near = pd.DataFrame({"molecule": [1, 9], "x": [15.0, 3.2], "y": [15.0, 15.0]})
    with pytest.raises(BayespsfInputError, match=r"leave the 30x30 frame: molecule\(s\) 9 \(x=3.2"):
        cut_rois(path, near, roi=9, fit=5)
    with pytest.raises(BayespsfInputError, match="roi must be an odd number of pixels >= 1"):
        cut_rois(path, ok, roi=8, fit=5)
    with pytest.raises(BayespsfInputError, match="fit must be an odd number of pixels >= 1"):
        cut_rois(path, ok, roi=9, fit=4)
    with pytest.raises(BayespsfInputError, match=r"fit \(11\) must be at most roi \(9\)"):
        cut_rois(path, ok, roi=9, fit=11)
    with pytest.raises(BayespsfInputError, match="missing column"):
        cut_rois(path, ok.drop(columns="y"), roi=9, fit=5)
    with pytest.raises(BayespsfInputError, match="unique"):
        cut_rois(path, ok.assign(molecule=1), roi=9, fit=5)
    with pytest.raises(BayespsfInputError, match="consecutive frames"):
        cut_rois(path, ok, roi=9, fit=5, frames=slice(0, 3, 2))
    with pytest.raises(BayespsfInputError, match="smaller than roi"):
        cut_rois(path, ok, roi=9, fit=9).periphery_background(Photon())
    with pytest.raises(BayespsfInputError, match="pixel_size"):
        traces(path, ok, Photon(), s0=S0, roi=9, fit=5)
    with pytest.raises(BayespsfInputError, match="aperture"):
        traces(path, ok, Photon(), s0=S0, pixel_size=A, roi=9, fit=5, aperture=3)
    with pytest.raises(BayespsfInputError, match="one-dimensional"):
        bleach_steps(np.zeros((4, 4)))


def test_a_step_within_a_frame_is_one_step():
    """Bleaching at a time T inside a frame leaves that frame at a fraction of the level (as
    bayespsf's movies and real exposures do): 300 traces of 120 frames, N 500–5000 with
    EMCCD-like noise (variance 2 N + 100), T uniform in [6, 114): one step, bleach frame
    ceil(T) within +-1, for >= 97% (measured 300 of 300 with the partial frame fitted between
    the levels; 87 of 300 where it is split off as a level of its own, a second step)."""
    rng = np.random.default_rng(11)
    t = np.arange(120)
    hits = 0
    for _ in range(300):
        n, bleach = np.exp(rng.uniform(np.log(500), np.log(5000))), rng.uniform(6, 114)
        level = n * np.clip(bleach - t, 0.0, 1.0)
        found = bleach_steps(level + np.sqrt(2 * level + 100) * rng.standard_normal(120))
        hits += found.steps == 1 and abs(found.bleach_frame - np.ceil(bleach)) <= 1
    assert hits >= 0.97 * 300, hits
