"""Posterior.load: a file that is not a result file is named, never a raw h5py or xarray error,
and never a tree that loads and then fails in draws() or summary()."""

import numpy as np
import pytest
import xarray as xr

from bayespsf.errors import BayespsfInputError
from bayespsf.inference import Posterior


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


def _posterior_tree(path, values, dims=("chain", "draw")):
    """A NetCDF of another program: a posterior group whose six parameters hold ``values``."""
    names = ("x0", "y0", "s_x", "s_y", "N", "b")
    group = xr.Dataset({name: (dims, values) for name in names})
    xr.DataTree.from_dict({"posterior": group}).to_netcdf(path, engine="h5netcdf")
    return path


@pytest.mark.parametrize(
    "values,dims,words",
    [
        # each loaded, then failed in draws() or summary() (or, for other dims, was misread)
        (np.zeros(5), ("draw",), r"x0, y0, s_x, s_y, N, b do not have dims \(chain, draw\)"),
        (
            np.zeros((2, 5, 3)),
            ("chain", "draw", "extra"),
            r"x0, y0, s_x, s_y, N, b do not have dims \(chain, draw\)",
        ),
        (np.zeros((4, 0)), ("chain", "draw"), r"x0, y0, s_x, s_y, N, b have no draws"),
        (np.full((2, 5), "a"), ("chain", "draw"), "the draws of x0 must be real numbers.*text"),
    ],
    ids=["one-dim", "extra-dim", "no-draws", "text"],
)
def test_a_posterior_group_without_usable_draws_is_refused_at_load(tmp_path, values, dims, words):
    path = _posterior_tree(tmp_path / "odd.nc", values, dims)
    with pytest.raises(BayespsfInputError, match=rf"odd\.nc: not a bayespsf result file: {words}"):
        Posterior.load(path)


def test_a_real_netcdf3_file_is_named(tmp_path):
    # xarray raised its own error for a NetCDF3 file (no groups)
    path = tmp_path / "old.nc"
    xr.Dataset({"x0": (("chain", "draw"), np.zeros((2, 5)))}).to_netcdf(path, engine="scipy")
    with pytest.raises(BayespsfInputError, match=r"old\.nc: a NetCDF3 file"):
        Posterior.load(path)


def test_a_plain_hdf5_file_is_not_a_result_file(tmp_path):
    # h5netcdf warned about the dims of its datasets, an error here and "damaged" to the user
    import h5py

    with h5py.File(tmp_path / "plain.h5", "w") as file:
        file["x0"] = np.zeros(3)
    with pytest.raises(BayespsfInputError, match=r"plain\.h5: .*no 'posterior' group"):
        Posterior.load(tmp_path / "plain.h5")
