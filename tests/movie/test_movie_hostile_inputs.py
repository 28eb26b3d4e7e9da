"""The movie path under hostile or unusual inputs: counts below the camera's offset,
saturated spots and movies, two spots closer than the detector resolves, frame indices outside
the movie, positions given as text, pixel sizes in the wrong unit, and the stated false-positive
rate on single EMCCD frames at low background. Each is a named error or a flag in the
candidates table, never a silently wrong result."""

import numpy as np
import pandas as pd
import pytest
import tifffile

from bayespsf import psf
from bayespsf.cameras import EMCCD
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.movie import cut_rois, detect, detect_frames, detect_movie, read_movie, traces
from bayespsf.movie.detect import COLUMNS

A, S = 79.0, 120.0  # pixel size and PSF SD (nm), the paper's
CAMERA = EMCCD(100.0, 10.0, 100.0)


def _expected(spots, b, shape, side=21):
    """Expected photons: spots ``(x, y, N)`` (picasso's convention) on a background ``b``."""
    image = np.full(shape, float(b))
    h = side // 2
    for x, y, n in spots:
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        spot = psf.expected_counts([(x - c) * A, (y - r) * A, S, S, n, 0.0], side, A)
        image[r - h : r + h + 1, c - h : c + h + 1] += spot
    return image


def _movie(tmp_path, counts, name="m.npy"):
    path = tmp_path / name
    np.save(path, counts)
    return read_movie(path)


def _spots_movie(tmp_path, rng, frames=10, camera=CAMERA, n=1500.0, dtype=np.uint16):
    expected = _expected([(30.0, 30.0, n), (70.2, 40.0, n), (45.0, 75.0, n)], 20.0, (100, 100))
    counts = camera.sample(np.broadcast_to(expected, (frames, 100, 100)), rng)
    return np.round(counts).astype(dtype)


# ---- 1. counts below the camera's offset ---------------------------------------------------


def test_a_movie_below_the_cameras_offset_is_named(tmp_path):
    """Counts of ~2 100 ADU with a declared offset of 5000 ADU (was: candidates found on a
    background of about -29 photons per pixel)."""
    counts = _spots_movie(tmp_path, np.random.default_rng(1))
    movie = _movie(tmp_path, counts)
    camera = EMCCD(100.0, 10.0, 5000.0)
    words = (
        r"median count 2\d{3}\.?\d* ADU lies 2\d{3}\.?\d* ADU below the camera's offset 5000 ADU"
    )
    with pytest.raises(BayespsfInputError, match=words + r".*\[camera\] offset"):
        detect_movie(movie, psf_sd=S, pixel_size=A, camera=camera)
    with pytest.raises(BayespsfInputError, match=r"frame 0: its median count"):
        detect_frames(movie, psf_sd=S, pixel_size=A, camera=camera)


def test_int32_counts_with_the_offset_already_subtracted_are_named(tmp_path):
    """int32 counts mostly below the offset: a dim movie whose offset was already removed."""
    expected = _expected([(30.0, 30.0, 300.0), (60.0, 50.0, 300.0)], 0.3, (100, 100))
    counts = CAMERA.sample(np.broadcast_to(expected, (10, 100, 100)), np.random.default_rng(2))
    movie = _movie(tmp_path, np.round(counts).astype(np.int32) - 100)
    with pytest.raises(BayespsfInputError, match=r"below the camera's offset 100 ADU.*subtracted"):
        detect_movie(movie, psf_sd=S, pixel_size=A, camera=CAMERA)
    # within the readout noise of the offset, a dark movie is fine
    dark = np.round(CAMERA.sample(np.zeros((5, 64, 64)), np.random.default_rng(3)))
    table = detect_movie(_movie(tmp_path, dark, "dark.npy"), psf_sd=S, pixel_size=A, camera=CAMERA)
    assert len(table) == 0


def test_a_negative_background_in_photons_is_named():
    rng = np.random.default_rng(4)
    image = rng.poisson(10.0, (64, 64)) - 300.0  # an offset removed twice
    with pytest.raises(BayespsfInputError, match=r"background: -2\d\d.*photons per pixel.*offset"):
        detect(image, psf_sd=S, pixel_size=A)
    with pytest.raises(BayespsfInputError, match=r"background: -50 photons.*\(given, median\)"):
        detect(rng.poisson(10.0, (64, 64)), psf_sd=S, pixel_size=A, background=-50.0)


# ---- 2. saturation -------------------------------------------------------------------------


def test_a_clipped_spot_is_flagged_and_the_others_are_not(tmp_path):
    rng = np.random.default_rng(5)
    counts = CAMERA.sample(
        np.broadcast_to(
            _expected(
                [(30.0, 30.0, 1500.0), (70.0, 40.0, 1500.0), (45.0, 75.0, 5e5)], 20.0, (100, 100)
            ),
            (10, 100, 100),
        ),
        rng,
    )
    counts = np.round(np.minimum(counts, 65535)).astype(np.uint16)  # a 16-bit ADC
    table = detect_movie(_movie(tmp_path, counts), psf_sd=S, pixel_size=A, camera=CAMERA)
    assert list(table.columns) == list(COLUMNS)
    assert len(table) == 3 and (table["status"] == "accepted").all()
    by_row = table.set_index("row")
    assert by_row.loc[75, "saturated"] > 0
    assert by_row.loc[30, "saturated"] == by_row.loc[40, "saturated"] == 0
    assert table.attrs["detection"]["saturated_pixels"] == by_row.loc[75, "saturated"]
    # a declared saturation (the Model's) below the type's maximum, float data
    model = Model(15, A, CAMERA, saturation=4000.0)
    table = detect_movie(
        _movie(tmp_path, counts.astype(np.float32), "f.npy"), psf_sd=S, camera=model
    )
    assert table.set_index("row").loc[75, "saturated"] > 0
    # per frame too
    per_frame = detect_frames(_movie(tmp_path, counts), psf_sd=S, pixel_size=A, camera=CAMERA)
    clipped = per_frame[per_frame["row"] == 75]
    assert len(clipped) == 10 and (clipped["saturated"] > 0).all()


@pytest.mark.parametrize(
    "value,words",
    [
        (65535, r"every pixel is 65535 ADU: every pixel is saturated"),
        (0, r"every pixel is 0 ADU: an all-zero"),
    ],
    ids=["saturated", "zero"],
)
def test_saturated_and_all_zero_movies_are_named(tmp_path, value, words):
    movie = _movie(tmp_path, np.full((4, 64, 64), value, dtype=np.uint16))
    with pytest.raises(BayespsfInputError, match=r"mean projection of frames 0-3: " + words):
        detect_movie(movie, psf_sd=S, pixel_size=A, camera=CAMERA)
    with pytest.raises(BayespsfInputError, match=words.replace("ADU", "photons")[:30]):
        detect(np.full((64, 64), value, dtype=np.uint16), psf_sd=S, pixel_size=A)
    # frame by frame without a camera (counts taken as photons), the frame is named
    with pytest.raises(BayespsfInputError, match=r"m\.npy: frame 2: every pixel is"):
        detect_frames(movie, psf_sd=S, pixel_size=A, frames=range(2, 4))


def test_a_mostly_saturated_movie_is_named(tmp_path):
    counts = _spots_movie(tmp_path, np.random.default_rng(6))
    counts[:, :, :70] = 65535
    with pytest.raises(BayespsfInputError, match=r"7000 of 10000 pixels \(70%\) are saturated"):
        detect_movie(_movie(tmp_path, counts), psf_sd=S, pixel_size=A, camera=CAMERA)


# ---- 3. two spots closer than the detector resolves ----------------------------------------


def _pairs(rng, separation, n_photons):
    """Spots (or pairs ``separation`` px apart, at random angles) on a 6 x 6 grid."""
    spots = []
    for gx in np.arange(20, 200, 30):
        for gy in np.arange(20, 200, 30):
            angle = rng.uniform(0, np.pi)
            x0, y0 = gx + rng.uniform(-0.5, 0.5), gy + rng.uniform(-0.5, 0.5)
            dx, dy = separation / 2 * np.cos(angle), separation / 2 * np.sin(angle)
            spots += [(x0 + dx, y0 + dy, n_photons), (x0 - dx, y0 - dy, n_photons)]
    return spots


def test_two_spots_one_pixel_apart_are_one_elongated_candidate(tmp_path):
    """36 pairs 1 px apart (2 000 photons per frame each, 20-frame EMCCD movie): one candidate
    each, flagged ``elongated`` (>= 90%); 36 single spots of the same 4 000 photons: at most one
    flagged (the test's level is 0.001 per round spot), nor of 36 bright round spots wider
    than the template."""
    rng = np.random.default_rng(7)
    found = {}
    for separation, n_photons in ((1.0, 2000.0), (0.0, 2000.0)):
        expected = _expected(_pairs(rng, separation, n_photons), 20.0, (220, 220))
        counts = CAMERA.sample(np.broadcast_to(expected, (20, 220, 220)), rng)
        movie = _movie(tmp_path, np.round(counts).astype(np.uint16), f"{separation}.npy")
        found[separation] = detect_movie(movie, psf_sd=S, pixel_size=A, camera=CAMERA)
    pairs, singles = found[1.0], found[0.0]
    assert len(pairs) == len(singles) == 36
    assert pairs["elongated"].mean() >= 0.9
    assert singles["elongated"].sum() <= 1
    assert pairs["elongation"].median() > singles["elongation"].median()
    assert (pairs["elongation"] >= 1).all() and (singles["elongation"] >= 1).all()
    # bright round spots wider than the template are round, not elongated
    spots = [(x, y, 20000.0) for x, y, _ in _pairs(rng, 0.0, 0.0)[::2]]
    expected = np.full((220, 220), 20.0)
    for x, y, n_photons in spots:
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        offset = [(x - c) * A, (y - r) * A, 140.0, 140.0, n_photons, 0.0]
        expected[r - 12 : r + 13, c - 12 : c + 13] += psf.expected_counts(offset, 25, A)
    counts = CAMERA.sample(np.broadcast_to(expected, (20, 220, 220)), rng).astype(np.float32)
    wide = detect_movie(_movie(tmp_path, counts, "w.npy"), psf_sd=S, pixel_size=A, camera=CAMERA)
    assert len(wide) == 36 and wide["elongated"].sum() <= 1


# ---- 4. frame indices ----------------------------------------------------------------------


def test_frame_indices_outside_the_movie_are_named(tmp_path):
    movie = _movie(tmp_path, np.arange(5 * 4 * 4, dtype=np.uint16).reshape(5, 4, 4))
    with pytest.raises(
        BayespsfInputError, match=r"frame 5 is not a frame of .*: its 5 frames are 0 to 4"
    ):
        movie.frame(len(movie))
    with pytest.raises(BayespsfInputError, match=r"frame -1 .*0 to 4 \(a negative index"):
        movie.frame(-1)
    with pytest.raises(BayespsfInputError, match="whole number"):
        movie.frame(1.0)
    with pytest.raises(IndexError, match=r"index 5 is out of range .* \(-5 to 4\)"):
        movie[5]  # an IndexError too: iterating over the frames ends at the last one
    assert len(list(movie)) == 5
    np.testing.assert_array_equal(movie[-1], movie.frame(4))  # an array's negative index


# ---- 5. positions given as text -------------------------------------------------------------


def test_positions_given_as_text_are_refused(tmp_path):
    movie = _movie(tmp_path, np.zeros((3, 40, 40), dtype=np.uint16))
    molecules = pd.DataFrame({"molecule": [0, 1], "x": ["20.0", "21.5"], "y": [20.0, 20.0]})
    with pytest.raises(
        BayespsfInputError, match=r"molecules\.x: positions must be numbers.*'20\.0'"
    ):
        cut_rois(movie, molecules, roi=9, fit=5)
    molecules = pd.DataFrame({"molecule": [0], "x": [20.0], "y": pd.Series(["20"], dtype="string")})
    with pytest.raises(BayespsfInputError, match=r"molecules\.y: positions must be numbers"):
        cut_rois(movie, molecules, roi=9, fit=5)
    assert cut_rois(movie, molecules.assign(y=20), roi=9, fit=5).counts.shape == (3, 9, 9)


# ---- 6. pixel sizes ------------------------------------------------------------------------


def _ome(tmp_path, size, unit, name="m.ome.tif"):
    data = _spots_movie(tmp_path, np.random.default_rng(8), frames=4)
    meta = {"axes": "TYX", "PhysicalSizeX": size, "PhysicalSizeXUnit": unit}
    tifffile.imwrite(tmp_path / name, data, ome=True, photometric="minisblack", metadata=meta)
    return read_movie(tmp_path / name)


@pytest.mark.parametrize(
    "size,unit",
    [(79, "nm"), (0.079, "µm"), (7.9e-5, "mm"), (7.9e-8, "m"), (790, "Å"), (0.0031102362, "thou")],
)
def test_ome_pixel_sizes_are_read_in_their_unit(tmp_path, size, unit):
    movie = _ome(tmp_path, size, unit)
    assert movie.pixel_size == pytest.approx(79.0, rel=1e-6)
    assert movie.metadata["pixel_size_field"] == f"PhysicalSizeX = {size} {unit}"


def test_an_implausible_pixel_size_is_named_with_its_source(tmp_path):
    """0.079 mm is 79 µm at the sample: read as such, refused where it is used, naming the
    metadata field and the fixes (was: an error about the traces' aperture)."""
    movie = _ome(tmp_path, 0.079, "mm")
    assert movie.pixel_size == pytest.approx(79000.0)
    words = r"pixel_size 79000 nm \(from the OME metadata of .*PhysicalSizeX = 0\.079 mm\)"
    fixes = r".*\[geometry\] pixel_size.*--pixel-size"
    with pytest.raises(BayespsfInputError, match=words + fixes):
        detect_movie(movie, psf_sd=S, camera=CAMERA)
    molecules = pd.DataFrame({"molecule": [0], "x": [50.0], "y": [50.0]})
    with pytest.raises(BayespsfInputError, match=words):
        traces(movie, molecules, CAMERA, s0=S, roi=9, fit=7)
    with pytest.raises(BayespsfInputError, match=r"pixel_size 0\.079 nm \(pixel_size=\)"):
        detect(np.random.default_rng(9).poisson(10.0, (64, 64)), psf_sd=S, pixel_size=0.079)
    # a file whose unit is not a length gives no pixel size, and says so
    movie = _ome(tmp_path, 1.0, "pixel", "p.ome.tif")
    assert movie.pixel_size is None
    assert "'pixel' is not a known unit" in movie.metadata["pixel_size_note"]


# ---- 7. the stated false-positive rate on single EMCCD frames ------------------------------


def test_single_emccd_frames_at_low_background_keep_the_stated_rate(tmp_path):
    """Pure EMCCD noise (the emccd-typical camera: gain 200, readout 50 e-, 12 e- per ADU,
    whole ADU) at 3 photons per pixel, detected frame by frame: the threshold from the camera
    law's exact tail puts ``false_positives`` background pixels above it per frame (within
    3 SE of the measured per-frame counts, which cluster), and the false candidates stay within
    3 Poisson SE of the stated rate, plus one. The Gaussian threshold of the old detector gave
    about 10 times too many pixels above it at ``false_positives=1`` and about 50 times too
    many candidates at 0.01 on these frames."""
    camera = EMCCD(200.0, 50.0, 100.0, 12.0)
    rng = np.random.default_rng(10)
    frames = 60
    counts = np.round(camera.sample(np.full((frames, 128, 128), 3.0), rng)).astype(np.uint16)
    movie = _movie(tmp_path, counts)
    for rate in (1.0, 0.05):
        table = detect_frames(
            movie, psf_sd=130.0, pixel_size=100.0, camera=camera, false_positives=rate
        )
        assert table.attrs["detection"]["null"] == "camera law (saddlepoint)"
        expected = frames * rate
        assert len(table) <= expected + 3 * np.sqrt(expected) + 1, (rate, len(table))
        if rate == 1.0:
            from bayespsf.movie import iter_detect_frames

            above = np.array(
                [
                    t.attrs["detection"]["pixels_above"]
                    for t in iter_detect_frames(
                        movie, psf_sd=130.0, pixel_size=100.0, camera=camera, false_positives=1.0
                    )
                ]
            )
            se = above.std(ddof=1) / np.sqrt(frames)
            assert abs(above.mean() - 1.0) < 3 * se + 0.05, (above.mean(), se)


def test_a_movie_without_a_pixel_size_names_every_way_to_state_it(tmp_path):
    movie = _movie(tmp_path, np.full((3, 64, 64), 120, np.uint16))
    fixes = r"state it \(nm\): pixel_size= .*--pixel-size .*\[geometry\] pixel_size"
    with pytest.raises(BayespsfInputError, match=r"metadata has none; " + fixes):
        detect_movie(movie, psf_sd=S, camera=CAMERA)


def test_a_nan_or_infinite_pixel_in_a_movie_is_named_by_frame_and_pixel(tmp_path):
    # a float movie's Inf went through the mean projection as inf - inf (a RuntimeWarning,
    # an error in this suite) and then "image must be finite", with no frame or pixel named
    counts = np.random.default_rng(0).poisson(5.0, (6, 32, 32)).astype(np.float32) + 100
    counts[4, 7, 9] = np.inf
    np.save(tmp_path / "m.npy", counts)
    where = r"m.npy: frame 4 has 1 NaN, infinite or vast pixel\(s\), the first NaN or infinite "
    where += r"at row 7, column 9"
    with pytest.raises(BayespsfInputError, match=where):
        detect_movie(tmp_path / "m.npy", psf_sd=S, pixel_size=A, camera=CAMERA)
    with pytest.raises(BayespsfInputError, match=where):
        detect_frames(tmp_path / "m.npy", psf_sd=S, pixel_size=A, camera=CAMERA)
    assert np.isfinite(read_movie(tmp_path / "m.npy").frames(0, 4)).all()  # the others read


def test_a_vast_pixel_in_a_float_movie_is_named_as_a_nan_is(tmp_path):
    # 1e300 ADU overflowed the projections' squares (RuntimeWarnings, then a solver's NaN
    # in a traceback); 2**53 itself still reads, one ADU above it does not
    counts = np.random.default_rng(0).poisson(5.0, (6, 32, 32)).astype(np.float64) + 100
    counts[2, 5, 6], counts[3, 1, 2] = 2.0**53, 1e300
    np.save(tmp_path / "m.npy", counts)
    with pytest.raises(BayespsfInputError, match=r"frame 3 has 1 NaN, infinite or vast pixel"):
        detect_movie(tmp_path / "m.npy", psf_sd=S, pixel_size=A, camera=CAMERA)
    assert read_movie(tmp_path / "m.npy").frames(0, 3)[2, 5, 6] == 2.0**53
    counts[3, 1, 2] = -(2.0**53 + 2.0)
    np.save(tmp_path / "m.npy", counts)
    with pytest.raises(BayespsfInputError, match=r"first beyond \+-2\*\*53 at row 1, column 2"):
        read_movie(tmp_path / "m.npy").frames()
    np.save(tmp_path / "h.npy", counts[:2].astype(np.float16))  # 2**53 is beyond float16:
    assert read_movie(tmp_path / "h.npy").frames().shape == (2, 32, 32)  # finite is the test


def test_frames_beyond_the_movie_are_refused_not_clipped(tmp_path):
    counts = np.random.default_rng(0).poisson(5.0, (10, 32, 32)).astype(np.uint16) + 100
    np.save(tmp_path / "m.npy", counts)
    for frames in (slice(5, 30), slice(12, None), slice(-13, None)):
        with pytest.raises(BayespsfInputError, match="reach beyond the movie's 10 frames"):
            detect_movie(tmp_path / "m.npy", psf_sd=S, pixel_size=A, camera=CAMERA, frames=frames)
    # counted from the end, as Python slices are: the last 3 frames
    found = detect_movie(
        tmp_path / "m.npy", psf_sd=S, pixel_size=A, camera=CAMERA, frames=slice(-3, None)
    )
    assert found.attrs["detection"]["frames"] == [7, 10]
