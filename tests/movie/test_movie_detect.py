"""Detection: the matched-filter likelihood-ratio test keeps its stated
false-positive rate on background-only images, detects spots at the rate its closed form
predicts, places them in picasso's convention, and rejects and counts edge and neighbour
candidates."""

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy import stats

from bayespsf import psf, theory
from bayespsf.cameras import EMCCD, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.movie import (
    detect,
    detect_frame,
    detect_frames,
    detect_movie,
    frame_settings,
    read_movie,
)
from bayespsf.movie.detect import COLUMNS, camera_noise_variance, estimate_noise_variance

A, S = 79.0, 120.0  # pixel size and PSF SD (nm), the paper's
SIZE = 128
GRID = np.arange(20, SIZE, 30)  # 4 x 4 spots 30 px apart, 20 px from the edges


def _image(xs, ys, n_photons, b, shape=(SIZE, SIZE), side=15):
    """Expected photons: spots of ``n_photons`` at (xs, ys) in picasso's convention (column
    j's centre at x = j) plus a background ``b``, each spot a ``side`` ROI of expected_counts
    centred on its nearest pixel."""
    image = np.full(shape, float(b))
    h = side // 2
    for x, y in zip(np.atleast_1d(xs), np.atleast_1d(ys), strict=True):
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        spot = psf.expected_counts([(x - c) * A, (y - r) * A, S, S, n_photons, 0.0], side, A)
        image[r - h : r + h + 1, c - h : c + h + 1] += spot
    return image


def _photons(camera, expected, rng, frames=1):
    """A mean of ``frames`` frames drawn by the camera's law, converted to photons."""
    per_adu, offset = camera.photons_per_adu()
    counts = camera.sample(np.broadcast_to(expected, (frames, *expected.shape)), rng)
    return ((counts - offset) * per_adu).mean(axis=0)


def _template_norm():
    """||g||: the root sum of squares of the spot's photon fractions (a 41-pixel square)."""
    g = psf.expected_counts([0.0, 0.0, S, S, 1.0, 0.0], 41, A)
    return float(np.sqrt((g**2).sum()))


def test_background_pixels_above_the_threshold_match_the_nominal_rate():
    """E[pixels with T > t] = false_positives under the null (noise and background given):
    400 ideal-camera images at 1000 photons per pixel (nearly Gaussian counts), 3 SE of the
    per-image counts (the exceedances cluster, so their SE is measured, not Poisson)."""
    rng = np.random.default_rng(1)
    above, found = [], []
    for _ in range(400):
        image = _photons(Photon(), np.full((64, 64), 1000.0), rng)
        table = detect(
            image, psf_sd=S, pixel_size=A, noise_var=1000.0, background=1000.0, false_positives=1.0
        )
        above.append(table.attrs["detection"]["pixels_above"])
        found.append(len(table))
    above = np.array(above)
    assert abs(above.mean() - 1.0) < 3 * above.std() / np.sqrt(above.size)
    assert np.mean(found) <= 1.0  # every false candidate is a pixel above the threshold


@pytest.mark.parametrize(
    "camera,b,frames,size,n",
    [(Photon(), 100.0, 1, SIZE, 200), (EMCCD(100.0, 10.0, 100.0), 20.0, 20, 64, 100)],
    ids=["photon-frames", "emccd-20-frame-means"],
)
def test_false_candidates_per_image_stay_under_the_default_rate(camera, b, frames, size, n):
    """The default 0.01 false candidates per image bounds the observed number with noise and
    background estimated from each image: the total over ``n`` images is within 3 Poisson SE
    of the bound's expectation (n x 0.01), plus one."""
    rng = np.random.default_rng(2)
    expected = n * 0.01
    total = 0
    for _ in range(n):
        image = _photons(camera, np.full((size, size), b), rng, frames)
        total += len(detect(image, psf_sd=S, pixel_size=A))
    assert total <= expected + 3 * np.sqrt(expected) + 1


def test_detection_rate_follows_the_matched_filter_closed_form():
    """P(detect) = Φ(E[T] - t) with E[T] = N ||g|| / σ (Kay vol. II, sec. 4.3) for spots at
    pixel centres: within 0.06 (3 SE of 640 spots) at E[T] = t - 1, t, t + 1, and all found at
    t + 4. A candidate counts whatever its status (a false candidate beside a spot rejects
    both as neighbours: rejection is tested below)."""
    rng = np.random.default_rng(3)
    b = 50.0
    t = stats.norm.isf(0.01 / SIZE**2)
    xs, ys = (v.ravel().astype(float) for v in np.meshgrid(GRID, GRID))
    for shift in (-1.0, 0.0, 1.0, 4.0):
        n_photons = (t + shift) * np.sqrt(b) / _template_norm()
        found = 0
        for _ in range(40):
            image = _photons(Photon(), _image(xs, ys, n_photons, b), rng)
            table = detect(image, psf_sd=S, pixel_size=A)
            near = (
                np.hypot(table["x"].to_numpy()[:, None] - xs, table["y"].to_numpy()[:, None] - ys)
                < 2
            )
            found += int(near.any(axis=0).sum())
        rate = found / (40 * xs.size)
        if shift < 4:
            assert abs(rate - stats.norm.cdf(shift)) < 0.06, (shift, rate)
        else:
            assert rate == 1.0


def test_positions_are_picasso_pixel_coordinates_at_the_centroid_precision():
    """x = column + offset (picasso's ``locs_from_fits``): unbiased (< 0.02 px) and as precise
    as the centroid's closed form (Eq. centroiderror, within 25%) for 2000-photon spots at
    random sub-pixel positions; amplitudes within 10% of N. Every spot must be accepted in all
    30 images, so a false candidate beside one (a neighbour rejection) would fail the test:
    at the default 0.01 per image up to 0.3 are expected over 30 images, at 0.001 up to 0.03."""
    rng = np.random.default_rng(4)
    n_photons, b = 2000.0, 50.0
    errors, amplitudes = [], []
    for _ in range(30):
        xs = np.repeat(GRID, GRID.size) + rng.uniform(-0.5, 0.5, GRID.size**2)
        ys = np.tile(GRID, GRID.size) + rng.uniform(-0.5, 0.5, GRID.size**2)
        image = _photons(Photon(), _image(xs, ys, n_photons, b), rng)
        table = detect(image, psf_sd=S, pixel_size=A, false_positives=1e-3)
        table = table[table["status"] == "accepted"]
        assert len(table) == xs.size
        nearest = np.argmin(
            np.hypot(table["x"].to_numpy()[:, None] - xs, table["y"].to_numpy()[:, None] - ys),
            axis=1,
        )
        errors.append(np.column_stack([table["x"] - xs[nearest], table["y"] - ys[nearest]]))
        amplitudes.append(table["amplitude"].to_numpy())
    errors = np.concatenate(errors)
    assert np.all(np.abs(errors.mean(axis=0)) < 0.02)
    closed_form = theory.delta_x_analytic(n_photons, S, S, A, 0.0, b) / A
    assert np.all(np.sqrt((errors**2).mean(axis=0)) < 1.25 * closed_form)
    assert abs(np.mean(np.concatenate(amplitudes)) / n_photons - 1) < 0.1
    table = detect(
        _image([40.3], [70.0], 1e6, 10.0), psf_sd=S, pixel_size=A, noise_var=10.0, background=10.0
    )
    assert table.loc[0, ["col", "row"]].tolist() == [40, 70]
    assert table.loc[0, "x"] == pytest.approx(40.3, abs=1e-3)
    assert table.loc[0, "y"] == pytest.approx(70.0, abs=1e-3)


def test_edge_and_neighbour_candidates_are_rejected_and_counted():
    """A spot 8 px from the edge (its 25 x 25 ROI would cross it) is rejected; a pair 10 px
    apart is rejected (each puts 5% of its 3000 photons, about 150, into the other's 15 x 15
    window, 1.7 times the window's noise SD of about 87, background and shot noise); a diagonal
    pair 20 px apart in rows and columns (each 12.5 px past the other's window, 8 spot SDs on
    either axis: no light there) and two isolated spots are accepted. The paper's fixed rule
    (``min_distance=roi``) rejects the diagonal pair too: their 25 x 25 ROIs overlap."""
    xs = [64.0, 30.0, 40.0, 75.0, 95.0, 20.0, 100.0]
    ys = [8.0, 60.0, 60.0, 20.0, 40.0, 105.0, 100.0]
    image = _photons(Photon(), _image(xs, ys, 3000.0, 20.0), np.random.default_rng(5))
    table = detect(image, psf_sd=S, pixel_size=A)
    assert list(table.columns) == list(COLUMNS)
    status = dict(zip(zip(table["row"], table["col"], strict=True), table["status"], strict=True))
    assert len(status) == 7
    assert status[(8, 64)] == "rejected: edge"
    for key in ((60, 30), (60, 40)):
        assert status[key] == "rejected: neighbour"
    for key in ((20, 75), (40, 95), (105, 20), (100, 100)):
        assert status[key] == "accepted"
    assert table.attrs["detection"]["counts"] == {
        "accepted": 4,
        "rejected: edge": 1,
        "rejected: neighbour": 2,
    }
    paper = detect(image, psf_sd=S, pixel_size=A, min_distance=25)
    assert paper.attrs["detection"]["counts"] == {
        "accepted": 2,
        "rejected: edge": 1,
        "rejected: neighbour": 4,
    }
    loose = detect(
        _image(xs, ys, 3000.0, 20.0),
        psf_sd=S,
        pixel_size=A,
        noise_var=20.0,
        background=20.0,
        min_distance=0,
    )
    assert loose.attrs["detection"]["counts"]["accepted"] == 6


def test_noise_variance_from_the_camera_law_matches_the_estimate_from_data():
    """On flat images the estimate agrees with the camera law's variance within 3 of its SEs
    (measured over 10 images): an EMCCD 20-frame mean and an ideal camera's integer counts
    (whose MAD alone would be quantised)."""
    rng = np.random.default_rng(6)
    for camera, b, frames in ((EMCCD(100.0, 10.0, 100.0), 20.0, 20), (Photon(), 10.0, 1)):
        law = float(camera_noise_variance(camera, b, frames))
        estimates = np.array(
            [
                estimate_noise_variance(_photons(camera, np.full((SIZE, SIZE), b), rng, frames))
                for _ in range(10)
            ]
        )
        se = estimates.std(ddof=1) / np.sqrt(estimates.size)
        assert abs(estimates.mean() - law) < 3 * se + 1e-12, (camera, estimates.mean(), law)
        assert np.all(np.abs(estimates / law - 1) < 0.05)
    assert camera_noise_variance(EMCCD(100.0, 10.0), 20.0) == pytest.approx(40.01)


def test_a_movie_is_detected_on_its_projection_and_frame_by_frame(tmp_path):
    """ADU movie, EMCCD law: the mean projection's noise comes from the camera law (named),
    the three molecules are found within 0.2 px; per frame each is found in most frames; the
    tables survive a CSV round trip."""
    rng = np.random.default_rng(7)
    camera = EMCCD(100.0, 10.0, 100.0)
    xs, ys = [30.2, 70.0, 50.6], [30.0, 45.4, 70.1]
    expected = _image(xs, ys, 1500.0, 20.0, shape=(100, 100))
    frames = camera.sample(np.broadcast_to(expected, (30, 100, 100)), rng)
    tifffile.imwrite(tmp_path / "m.tif", frames.astype(np.float32), photometric="minisblack")
    movie = read_movie(tmp_path / "m.tif")
    table = detect_movie(movie, psf_sd=S, pixel_size=A, camera=camera)
    assert (table["noise_source"] == "camera").all() and len(table) == 3
    assert table["noise_var"].to_numpy() == pytest.approx(2 * 20.0 / 30, rel=0.05)
    assert np.sort(table["x"]) == pytest.approx(np.sort(xs), abs=0.2)
    assert table.attrs["detection"]["frames"] == [0, 30]
    per_frame = detect_frames(movie, psf_sd=S, pixel_size=A, camera=camera, frames=slice(0, 10))
    assert list(per_frame.columns) == ["frame", *COLUMNS]
    assert per_frame["molecule"].tolist() == list(range(len(per_frame)))
    assert 27 <= (per_frame["status"] == "accepted").sum() <= 31
    per_frame.to_csv(tmp_path / "d.csv", index=False)
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "d.csv"), per_frame, check_dtype=False)
    # one frame already read, with the settings of the movie (given as its path): that frame's
    # rows of the per-frame table, its candidates numbered within the frame
    settings = frame_settings(tmp_path / "m.tif", psf_sd=S, pixel_size=A, camera=camera)
    assert settings["source"] == str(tmp_path / "m.tif") and settings["pixel_size"] == A
    one = detect_frame(movie.frames(4, 5)[0], 4, **settings)
    expected = per_frame[per_frame["frame"] == 4].drop(columns="molecule")
    pd.testing.assert_frame_equal(
        one.drop(columns="molecule"), expected.reset_index(drop=True), check_like=False
    )


@pytest.mark.parametrize(
    "change,field",
    [
        ({"image": np.full((32, 32), np.nan)}, "image"),
        ({"image": np.zeros((4, 32, 32))}, "image"),
        ({"psf_sd": 0.0}, "psf_sd"),
        ({"psf_sd": -1.0}, "psf_sd"),
        ({"false_positives": 0.0}, "false_positives"),
        ({"false_positives": 32 * 32}, "false_positives"),
        ({"roi": 24}, "roi"),
        ({"pixel_size": 0.0}, "pixel_size"),
        ({"noise_var": -1.0}, "noise_var"),
        ({"noise_var": np.ones((3, 3))}, "noise_var"),
        ({"background": np.ones((3, 3))}, "background"),
        ({"min_distance": -1.0}, "min_distance"),
    ],
)
def test_bad_inputs_are_named(change, field):
    arguments = {
        "image": np.random.default_rng(8).normal(10, 1, (32, 32)),
        "psf_sd": S,
        "pixel_size": A,
    } | change
    with pytest.raises(BayespsfInputError, match=field):
        detect(arguments.pop("image"), **arguments)
