"""Reading movies: every format read exactly, frame by frame, with its
metadata; every bad file named; projections equal NumPy's on the whole array, with memory
bounded independently of the number of frames."""

import pickle
import tracemalloc

import numpy as np
import pytest
import tifffile

from bayespsf.errors import BayespsfInputError
from bayespsf.movie import Movie, project, read_movie

RNG = np.random.default_rng(13)
DATA = RNG.integers(0, 60_000, (24, 9, 11)).astype(np.uint16)


def _write(path, data, **options):
    tifffile.imwrite(path, data, photometric="minisblack", **options)
    return path


def _check(movie, data):
    assert isinstance(movie, Movie)
    assert movie.shape == data.shape and len(movie) == movie.n_frames == len(data)
    assert movie.dtype == data.dtype
    np.testing.assert_array_equal(movie.frames(), data)
    np.testing.assert_array_equal(movie[-1], data[-1])
    np.testing.assert_array_equal(movie.frames(3, 7, rows=slice(2, 5)), data[3:7, 2:5])
    np.testing.assert_array_equal(movie.to_dask(frames_per_chunk=5).compute(), data)


@pytest.mark.parametrize(
    "options",
    [{}, {"compression": "zlib"}, {"byteorder": ">"}],
    ids=["contiguous", "compressed", "big-endian"],
)
def test_a_plain_multipage_tiff_is_read_exactly(tmp_path, options):
    movie = read_movie(_write(tmp_path / "m.tif", DATA, **options))
    _check(movie, DATA)
    assert movie.pixel_size is None and movie.exposure is None
    assert movie.metadata["pixel_size"] is None and movie.metadata["exposure"] is None
    assert "frames=24" in repr(movie) and "pixel_size=None" in repr(movie)
    assert "pixel_size=100 nm," in movie.describe(100.0)  # the size a run uses, where none is read
    with pytest.raises(BayespsfInputError, match="pixel_size must be a number in nm"):
        movie.describe("100 nm")
    movie.close()


def test_pages_written_one_by_one_are_frames(tmp_path):
    # each page its own series in tifffile's eyes, its data between image directories
    with tifffile.TiffWriter(tmp_path / "pages.tif") as tif:
        for frame in DATA.astype(np.float32):
            tif.write(frame)
    _check(read_movie(tmp_path / "pages.tif"), DATA.astype(np.float32))


def test_ome_tiff_pixel_size_exposure_and_z_t_frames(tmp_path):
    data = DATA.reshape(6, 4, 9, 11)  # T, Z
    meta = {
        "axes": "TZYX",
        "PhysicalSizeX": 0.107,
        "PhysicalSizeXUnit": "µm",
        "TimeIncrement": 50,
        "TimeIncrementUnit": "ms",
    }
    movie = read_movie(_write(tmp_path / "m.ome.tif", data, ome=True, metadata=meta))
    _check(movie, DATA)  # Z x T flattened in acquisition order
    assert movie.pixel_size == pytest.approx(107.0) and movie.exposure == pytest.approx(0.05)
    assert movie.metadata["pixel_size"] == movie.metadata["exposure"] == "OME"
    assert "pixel_size=107 nm (OME)," in movie.describe(107.0)  # the size used, and whence
    # a size given in its place (--pixel-size, a camera file) is the one shown, with the file's
    assert "pixel_size=100 nm, not the metadata's 107 nm (OME)," in movie.describe(100.0)
    assert movie.metadata["exposure_field"] == "TimeIncrement"
    # a plane's ExposureTime is the exposure, preferred to the frame interval
    meta = {
        "axes": "TYX",
        "PhysicalSizeX": 80,
        "PhysicalSizeXUnit": "nm",
        "TimeIncrement": 1,
        "Plane": {"ExposureTime": [30] * 24, "ExposureTimeUnit": ["ms"] * 24},
    }
    movie = read_movie(_write(tmp_path / "e.ome.tif", DATA, ome=True, metadata=meta))
    assert movie.pixel_size == pytest.approx(80.0) and movie.exposure == pytest.approx(0.03)
    assert movie.metadata["exposure_field"] == "ExposureTime"


def test_imagej_hyperstack_frames_and_calibration(tmp_path):
    data = DATA.reshape(3, 8, 9, 11)  # T, Z
    meta = {"axes": "TZYX", "unit": "um", "finterval": 0.1}
    path = _write(
        tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.16, 1 / 0.16), metadata=meta
    )
    movie = read_movie(path)
    _check(movie, DATA)
    assert movie.pixel_size == pytest.approx(160.0) and movie.exposure == pytest.approx(0.1)
    assert movie.metadata["pixel_size"] == movie.metadata["exposure"] == "ImageJ"
    assert movie.metadata["axes"] == "TZYX"


@pytest.mark.parametrize("kind", ["ome", "imagej"])
def test_several_channels_need_one_picked(tmp_path, kind):
    data = DATA.reshape(6, 2, 2, 9, 11)  # T, C, Z
    meta = {"axes": "TCZYX", "Channel": {"Name": ["Cy3", "Cy5"]}} if kind == "ome" else {}
    options = {"ome": True} if kind == "ome" else {"imagej": True}
    if kind == "imagej":
        meta, data = {"axes": "TZCYX"}, data.transpose(0, 2, 1, 3, 4)  # ImageJ's order
    path = _write(tmp_path / f"two.{kind}.tif", data, metadata=meta, **options)
    names = r"2 channels \(0 \('Cy3'\), 1 \('Cy5'\)\)" if kind == "ome" else r"2 channels \(0, 1\)"
    with pytest.raises(BayespsfInputError, match=rf"two\.{kind}\.tif: it has {names}.*channel="):
        read_movie(path)
    second = DATA.reshape(6, 2, 2, 9, 11)[:, 1].reshape(-1, 9, 11)
    _check(read_movie(path, channel=1), second)
    with pytest.raises(BayespsfInputError, match=r"channel=2, but it has 2 channel"):
        read_movie(path, channel=2)


def test_a_series_of_files_is_one_movie_in_name_order(tmp_path):
    for k, part in zip((1, 2, 10), np.split(DATA, [5, 16]), strict=True):
        _write(tmp_path / f"run_{k}.tif", part)
    movie = read_movie(str(tmp_path / "run_*.tif"))  # run_2 before run_10
    _check(movie, DATA)
    assert [p.name for p in movie.path] == ["run_1.tif", "run_2.tif", "run_10.tif"]
    assert [start for start, _ in movie.blocks(7)] == [0, 7, 14, 21]
    np.testing.assert_array_equal(np.concatenate([b for _, b in movie.blocks(7)]), DATA)
    listed = read_movie([tmp_path / "run_10.tif", tmp_path / "run_1.tif"])  # the order given
    np.testing.assert_array_equal(listed.frames(), np.concatenate([DATA[16:], DATA[:5]]))
    _write(tmp_path / "odd_1.tif", DATA[:3])
    _write(tmp_path / "odd_2.tif", DATA[:3, :8])
    with pytest.raises(BayespsfInputError, match=r"odd_2\.tif: frames \(8, 11\).*odd_1\.tif"):
        read_movie(str(tmp_path / "odd_*.tif"))
    _write(tmp_path / "type_2.tif", DATA[:3].astype(np.float32))
    with pytest.raises(BayespsfInputError, match=r"type_2\.tif: .*float32.*odd_1\.tif"):
        read_movie([tmp_path / "odd_1.tif", tmp_path / "type_2.tif"])
    with pytest.raises(BayespsfInputError, match="no files match"):
        read_movie(str(tmp_path / "none_*.tif"))


def test_npy_movies_and_a_single_frame(tmp_path):
    np.save(tmp_path / "m.npy", DATA)
    _check(read_movie(tmp_path / "m.npy"), DATA)
    np.save(tmp_path / "f.npy", np.asfortranarray(DATA[0]))
    _check(read_movie(tmp_path / "f.npy"), DATA[:1])


def test_indexing_pickling_and_dask(tmp_path):
    movie = read_movie(_write(tmp_path / "m.tif", DATA, compression="zlib"))
    np.testing.assert_array_equal(movie[3:20:4, 2], DATA[3:20:4, 2])
    np.testing.assert_array_equal(movie[::-5, :, 1:3], DATA[::-5, :, 1:3])
    np.testing.assert_array_equal(movie[7], DATA[7])
    assert movie[30:].shape == (0, 9, 11)
    with pytest.raises(IndexError):
        movie.frame(24)
    again = pickle.loads(pickle.dumps(movie))  # reopened from the file, not copied
    np.testing.assert_array_equal(again.frames(), DATA)
    lazy = movie.to_dask(frames_per_chunk=10)
    assert lazy.chunks[0] == (10, 10, 4)
    assert float(lazy.mean().compute()) == pytest.approx(DATA.mean(), rel=1e-12)
    with pytest.raises(BayespsfInputError, match="size must be"):
        next(movie.blocks(0))
    again.close()
    movie.close()


def _cut_data(tmp_path):
    # pages written one by one: the last image data follow the last image directory, so
    # cutting them leaves the chain of pages whole
    with tifffile.TiffWriter(tmp_path / "ok.tif") as tif:
        for frame in DATA[:4]:
            tif.write(frame, photometric="minisblack")
    raw = (tmp_path / "ok.tif").read_bytes()
    (tmp_path / "ok.tif").unlink()
    (tmp_path / "x.tif").write_bytes(raw[:-60])


def _cut_chain(tmp_path):
    raw = _write(tmp_path / "ok.tif", DATA).read_bytes()
    (tmp_path / "ok.tif").unlink()
    (tmp_path / "x.tif").write_bytes(raw[: len(raw) // 2])


def _cut_npy(tmp_path):
    np.save(tmp_path / "x.npy", DATA)
    raw = (tmp_path / "x.npy").read_bytes()
    (tmp_path / "x.npy").write_bytes(raw[:-100])


def _hand_tiff(path, bits: int, stored: int, side: int = 100_000):
    """One uncompressed page of ``side`` x ``side`` pixels of ``bits`` bits over ``stored``
    bytes, written by hand: the header, an IFD of 8 tags, then the data."""
    import struct

    tags = [(256, 4, side), (257, 4, side), (258, 3, bits), (259, 3, 1), (262, 3, 1)]
    tags += [(273, 4, 8 + 2 + 8 * 12 + 4), (277, 3, 1), (279, 4, stored)]  # offset, bytes
    ifd = struct.pack("<H", len(tags))
    for tag, kind, value in tags:  # one value each: a LONG (4) or a SHORT (3) padded to 4 bytes
        ifd += struct.pack("<HHI", tag, kind, 1)
        ifd += struct.pack("<I", value) if kind == 4 else struct.pack("<HH", value, 0)
    path.write_bytes(b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + bytes(stored))
    return path


def _short_strip(tmp_path):
    _hand_tiff(tmp_path / "x.tif", 16, 8)  # 100 000 x 100 000 pixels of 16 bits over 8 bytes


def test_a_packed_12_bit_page_is_not_taken_for_a_short_one(tmp_path):
    # 16 x 16 pixels of 12 bits fill 16 rows of 24 bytes, not 512 bytes of uint16
    movie = read_movie(_hand_tiff(tmp_path / "p.tif", 12, 16 * 24, side=16))
    assert movie.shape == (1, 16, 16)
    with pytest.raises(BayespsfInputError, match=r"holds 383 bytes .* 12 bits need 384\)"):
        read_movie(_hand_tiff(tmp_path / "q.tif", 12, 16 * 24 - 1, side=16))


def _empty_pages(tmp_path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tifffile warns that it writes a zero-size image
        _write(tmp_path / "x.tif", np.ones((0, 9, 11), np.uint16))


def _mixed(tmp_path):
    with tifffile.TiffWriter(tmp_path / "x.tif") as tif:
        for rows in (9, 9, 8, 9):
            tif.write(DATA[0, :rows], photometric="minisblack")


def _mixed_types(p):
    with tifffile.TiffWriter(p / "x.tif") as tif:
        tif.write(DATA[0].astype(np.uint16), photometric="minisblack")
        tif.write(np.full((9, 11), 3.5, np.float32), photometric="minisblack")


@pytest.mark.parametrize(
    "make,words",
    [
        (lambda p: p / "x.tif", r"x\.tif: no such file"),
        (lambda p: (p / "x.tif").mkdir(), r"x\.tif is a directory"),
        (lambda p: (p / "x.png").write_bytes(b"png"), r"x\.png: unknown file type '\.png'"),
        (lambda p: (p / "x.tif").write_bytes(b"\x00" * 64), r"x\.tif: cannot read it"),
        (lambda p: (p / "x.tif").write_bytes(b"II*\x00\x08\x00\x00\x00"), r"x\.tif: .*no images"),
        (_cut_chain, r"x\.tif: damaged or truncated TIFF"),
        (_cut_data, r"x\.tif: damaged or truncated TIFF \(frame 3's image data end"),
        (_short_strip, r"x\.tif: damaged or truncated TIFF \(frame 0's page holds 8 bytes"),
        (_mixed, r"x\.tif: its pages differ in shape .*page 2 \(8, 11\)"),
        (_mixed_types, r"x\.tif: page 1 holds float32, the first page uint16"),
        (lambda p: _write(p / "x.tif", DATA.astype(np.complex64)), r"x\.tif: complex values"),
        (lambda p: _write(p / "x.tif", DATA > 9), r"x\.tif: boolean values"),
        (
            lambda p: tifffile.imwrite(p / "x.tif", np.zeros((4, 9, 11, 3), np.uint8)),
            r"x\.tif: its pages are \(9, 11, 3\), not 2-D",
        ),
        (_empty_pages, r"x\.tif: no frames, its pages hold no image data"),
        (lambda p: np.save(p / "x.npy", np.ones(5)), r"x\.npy: an array of 1 dimensions"),
        (lambda p: np.save(p / "x.npy", np.ones((2, 2, 3, 3))), r"x\.npy: an array of 4"),
        (lambda p: np.save(p / "x.npy", DATA + 1j), r"x\.npy: complex values"),
        (lambda p: np.save(p / "x.npy", DATA > 9), r"x\.npy: boolean values"),
        (lambda p: np.save(p / "x.npy", np.empty((0, 9, 11))), r"x\.npy: an empty movie"),
        (
            lambda p: (p / "x.npy").write_bytes(np.lib.format.magic(1, 0) + b"\x10\x00{'descr'"),
            r"x\.npy: cannot read it",
        ),
        (_cut_npy, r"x\.npy: cannot read it, damaged or truncated"),
    ],
    ids=[
        "missing",
        "dir",
        "extension",
        "not-a-tiff",
        "header-only",
        "cut-chain",
        "cut-data",
        "short-strip",
        "mixed-pages",
        "mixed-types",
        "complex",
        "boolean",
        "rgb",
        "empty-pages",
        "1d-npy",
        "4d-npy",
        "complex-npy",
        "boolean-npy",
        "empty-npy",
        "truncated-npy",
        "cut-npy",
    ],
)
def test_bad_movies_are_named(tmp_path, make, words):
    make(tmp_path)
    path = next(iter(tmp_path.iterdir()), tmp_path / "x.tif")
    with pytest.raises(BayespsfInputError, match=words):
        read_movie(path)


def test_bad_series_and_channels_are_named(tmp_path):
    with pytest.raises(BayespsfInputError, match="an empty list"):
        read_movie([])
    np.save(tmp_path / "a.npy", DATA)
    _write(tmp_path / "b.tif", DATA)
    with pytest.raises(BayespsfInputError, match=r"a\.npy: unknown file type .*list of \.tif"):
        read_movie([tmp_path / "a.npy", tmp_path / "b.tif"])
    with pytest.raises(BayespsfInputError, match=r"b\.tif: channel=1, but it has 1 channel"):
        read_movie(tmp_path / "b.tif", channel=1)
    with pytest.raises(BayespsfInputError, match=r"channel must be an integer"):
        read_movie(tmp_path / "b.tif", channel="Cy3")


@pytest.mark.parametrize("kind", ["mean", "std", "median", "max"])
@pytest.mark.parametrize(
    "frames", [None, slice(2, 19), range(1, 24, 3)], ids=["all", "slice", "step"]
)
def test_projections_equal_numpy_on_the_whole_array(tmp_path, kind, frames):
    movie = read_movie(_write(tmp_path / "m.tif", DATA, compression="zlib"))
    chosen = DATA[frames if isinstance(frames, slice) else slice(None)]
    if isinstance(frames, range):
        chosen = DATA[frames.start : frames.stop : frames.step]
    expected = getattr(np, kind)(chosen.astype(np.float64), axis=0)
    got = project(movie, kind, frames=frames, block=5, budget=2_000)  # many blocks and bands
    assert got.shape == (9, 11) and got.dtype == np.float64
    if kind in ("mean", "std"):
        np.testing.assert_allclose(got, expected, rtol=1e-12)
    else:
        np.testing.assert_array_equal(got, expected)
    movie.close()


@pytest.mark.parametrize("kind", ["mean", "std"])
def test_mean_and_std_do_not_depend_on_the_frames_read_at_a_time(tmp_path, kind):
    # Frames are merged 16 at a time whatever the block read (at least 16): the same image to
    # the last bit, so detection on a projection does not move with the memory budget.
    data = np.random.default_rng(3).integers(0, 60_000, (70, 9, 11)).astype(np.uint16)
    movie = read_movie(_write(tmp_path / "long.tif", data))
    images = [project(movie, kind, block=block) for block in (16, 17, 40, 70, None)]
    for image in images[1:]:
        np.testing.assert_array_equal(image, images[0])
    expected = getattr(np, kind)(data.astype(np.float64), axis=0)
    np.testing.assert_allclose(images[0], expected, rtol=1e-12)  # ~70 roundings of ~1e-16
    movie.close()


def test_projection_arguments_are_checked(tmp_path):
    movie = read_movie(_write(tmp_path / "m.tif", DATA))
    cases = [
        ({"kind": "mode"}, "kind must be one of"),
        ({"frames": slice(30, 40)}, "selects none"),
        ({"frames": [1, 2]}, "frames must be a slice"),
        ({"block": 0}, "block must be"),
        ({"budget": 0}, "budget must be"),
    ]
    for kwargs, words in cases:
        with pytest.raises(BayespsfInputError, match=words):
            project(movie, **kwargs)


def test_projecting_a_mapped_movie_does_not_hold_it_in_memory(tmp_path):
    data = np.random.default_rng(1).integers(0, 4000, (200, 256, 256)).astype(np.uint16)
    movie = read_movie(_write(tmp_path / "big.tif", data))
    size = data.nbytes  # 26 MB
    for kind in ("mean", "std", "max", "median"):
        tracemalloc.start()
        got = project(movie, kind, budget=2 * 2**20)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < size / 5, (kind, peak, size)
        if kind in ("median", "max"):
            np.testing.assert_array_equal(got, getattr(np, kind)(data, axis=0))
