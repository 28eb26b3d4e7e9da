"""Reading ROI stacks: every bad file is named with what is wrong with it."""

import numpy as np
import pytest
import tifffile

from bayespsf.errors import BayespsfInputError
from bayespsf.io import read_rois


def test_a_tiff_whose_pages_differ_in_shape_is_named_page_by_page(tmp_path):
    # only the first page was analysed, exit 0
    path = tmp_path / "mixed.tif"
    with tifffile.TiffWriter(path) as tif:
        for size in (15, 15, 17, 15):
            tif.write(np.ones((size, size), np.float32))
    with pytest.raises(BayespsfInputError, match=r"pages differ in shape .*page 2 \(17, 17\)"):
        read_rois(path)


def test_a_multipage_tiff_is_every_page(tmp_path):
    stack = np.random.default_rng(0).random((5, 15, 15)).astype(np.float32)
    with tifffile.TiffWriter(tmp_path / "pages.tif") as tif:
        for page in stack:
            tif.write(page)
    np.testing.assert_array_equal(read_rois(tmp_path / "pages.tif"), stack)
    tifffile.imwrite(tmp_path / "one.tif", stack[0])
    assert read_rois(tmp_path / "one.tif").shape == (1, 15, 15)


@pytest.mark.parametrize(
    "make,words",
    [
        (lambda p: np.save(p / "x.npy", np.empty((0, 15, 15))), r"x\.npy: no ROIs"),
        (lambda p: np.save(p / "x.npy", np.ones((2, 15, 15)) + 1j), r"x\.npy: counts .*complex"),
        (lambda p: np.save(p / "x.npy", np.ones((2, 15, 15), bool)), r"x\.npy: .*boolean"),
        (lambda p: (p / "x.npy").write_bytes(b"\x93NUMPY\x01\x00v\x00{'descr'"), "damaged"),
        # a TIFF header alone (its first page's offset: past the end, 0, a BigTIFF's 0) was
        # read as an array of shape (0,): "got (0,)"
        (lambda p: (p / "x.tif").write_bytes(b"II*\x00\x08\x00\x00\x00"), "no images"),
        (lambda p: (p / "x.tif").write_bytes(b"II*\x00" + bytes(4)), "no images"),
        (lambda p: (p / "x.tif").write_bytes(b"II+\x00\x08\x00\x00\x00" + bytes(8)), "no images"),
        # an image directory with no tags: read as a boolean array of shape (0,)
        (lambda p: (p / "x.tif").write_bytes(b"II*\x00\x08\x00\x00\x00" + bytes(6)), "no ROIs"),
        (lambda p: (p / "x.tif").write_bytes(b"\x00" * 64), r"x\.tif: cannot read it"),
        (lambda p: (p / "x.npy").mkdir(), r"x\.npy is a directory"),
    ],
    ids=[
        "empty",
        "complex",
        "boolean",
        "truncated-npy",
        "header-only-tiff",
        "header-only-tiff-offset-0",
        "header-only-bigtiff",
        "tiff-page-without-tags",
        "random-tiff",
        "dir",
    ],
)
def test_bad_stacks_are_named(tmp_path, make, words):
    make(tmp_path)
    (path,) = list(tmp_path.iterdir())
    with pytest.raises(BayespsfInputError, match=words):
        read_rois(path)


def test_a_tiff_of_empty_pages_has_no_rois(tmp_path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tifffile warns that it writes a zero-size image
        tifffile.imwrite(tmp_path / "empty.tif", np.ones((0, 15, 15), np.float32))
    with pytest.raises(BayespsfInputError, match=r"empty\.tif: no ROIs"):
        read_rois(tmp_path / "empty.tif")


def test_a_truncated_tiff_is_named(tmp_path):
    # tifffile stops at the break in the chain of pages and returns the pages before it: a
    # stack silently shorter than the file that was written
    tifffile.imwrite(
        tmp_path / "ok.tif", np.ones((4, 15, 15), np.float32), photometric="minisblack"
    )
    raw = (tmp_path / "ok.tif").read_bytes()
    (tmp_path / "cut.tif").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(BayespsfInputError, match=r"cut\.tif: damaged or truncated TIFF"):
        read_rois(tmp_path / "cut.tif")


def test_a_tiff_with_an_unreadable_tag_but_a_readable_image_is_read(tmp_path):
    # tifffile logs the bad tag on opening and reads the image; it was refused as truncated
    import struct

    image = np.random.default_rng(0).random((15, 15)).astype(np.float32)
    tifffile.imwrite(tmp_path / "ok.tif", image, software="camera")
    raw = bytearray((tmp_path / "ok.tif").read_bytes())
    (ifd,) = struct.unpack("<I", raw[4:8])
    (entries,) = struct.unpack("<H", raw[ifd : ifd + 2])
    codes = [
        struct.unpack("<H", raw[ifd + 2 + 12 * k : ifd + 4 + 12 * k])[0] for k in range(entries)
    ]
    software = ifd + 2 + 12 * codes.index(305)
    raw[software + 2 : software + 4] = struct.pack("<H", 99)  # no such TIFF data type
    (tmp_path / "odd.tif").write_bytes(bytes(raw))
    np.testing.assert_array_equal(read_rois(tmp_path / "odd.tif"), image[None])


def test_a_one_pixel_roi_is_read_and_judged_by_the_model(tmp_path):
    # the schema allows a 1 x 1 ROI for simulation; inference refuses it by its size
    from bayespsf import Model, cameras

    np.save(tmp_path / "tiny.npy", np.ones((3, 1, 1)))
    assert read_rois(tmp_path / "tiny.npy").shape == (3, 1, 1)
    with pytest.raises(BayespsfInputError, match="roi must be >= 5"):
        Model(1, 100.0, cameras.Photon())
