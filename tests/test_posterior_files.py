"""Posterior.load: a file that is not a result file is named, never a raw h5py or xarray error,
and never a tree that loads and then fails in draws() or summary() (issue 17)."""

import numpy as np
import pytest
import xarray as xr

from bayespsf.errors import BayespsfInputError
from bayespsf.posterior import Posterior


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    draws = np.random.default_rng(0).normal(size=(4, 50, 6)) + np.array([0, 0, 100, 100, 1e3, 5])
    path = tmp_path_factory.mktemp("post") / "good.nc"
    Posterior.from_draws(draws, tau=np.ones(6)).save(path)
    return path


def test_a_result_file_round_trips(saved):
    post = Posterior.load(saved)
    assert post.draws().shape == (200, 6) and np.isfinite(post.summary()["sd"]).all()


def _flip(raw: bytes) -> bytes:
    data = bytearray(raw)
    for k in range(0, len(data), 97):  # damage the whole file, the signature kept
        if k >= 8:
            data[k] ^= 0xFF
    return bytes(data)


@pytest.mark.parametrize(
    "damage,words",
    [
        (lambda raw: raw[: len(raw) // 3], "damaged or truncated"),
        (lambda raw: b"", "an empty file"),
        (lambda raw: np.random.default_rng(1).bytes(4000), "not a bayespsf result file"),
        (_flip, "damaged or truncated"),
        (lambda raw: b"CDF\x01" + b"\x00" * 100, "a NetCDF3 file"),
    ],
    ids=["truncated", "empty", "random", "bit-flipped", "netcdf3"],
)
def test_damaged_files_are_named(saved, tmp_path, damage, words):
    bad = tmp_path / "bad.nc"
    bad.write_bytes(damage(saved.read_bytes()))
    with pytest.raises(BayespsfInputError, match=rf"bad\.nc: .*{words}"):
        Posterior.load(bad)


def test_a_directory_and_a_missing_file_are_named(tmp_path):
    with pytest.raises(BayespsfInputError, match="is a directory"):
        Posterior.load(tmp_path)
    with pytest.raises(BayespsfInputError, match="no such result file"):
        Posterior.load(tmp_path / "missing.nc")


def test_a_netcdf_of_another_program_is_refused_at_load(tmp_path):
    # it loaded, then failed in draws() and summary()
    other = tmp_path / "other.nc"
    xr.Dataset({"temperature": ("time", np.arange(5.0))}).to_netcdf(other, engine="h5netcdf")
    with pytest.raises(BayespsfInputError, match="no 'posterior' group"):
        Posterior.load(other)
    partial = tmp_path / "partial.nc"
    tree = xr.DataTree.from_dict(
        {"posterior": xr.Dataset({"x0": (("chain", "draw"), np.zeros((2, 5)))})}
    )
    tree.to_netcdf(partial, engine="h5netcdf")
    with pytest.raises(BayespsfInputError, match="posterior group has no y0, s_x, s_y, N, b"):
        Posterior.load(partial)
