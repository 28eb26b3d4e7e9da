"""The on-disk cache of the EMCCD tables: built once per machine, read by every later process
(the first fit of a process took 18 s), safe with damaged files and no folder."""

import numpy as np
import pytest

from bayespsf.cameras import _emccd_table, _table_cache


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("BAYESPSF_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_an_array_is_computed_once_then_read(cache):
    calls = []

    def compute():
        calls.append(1)
        return np.arange(6.0).reshape(2, 3)

    first = _table_cache.load_or_compute("thing", compute, (2, 3))
    second = _table_cache.load_or_compute("thing", compute, (2, 3))
    np.testing.assert_array_equal(first, second)
    assert len(calls) == 1 and (cache / "thing.npy").exists()
    assert not list(cache.glob("*.partial"))


@pytest.mark.parametrize("damage", [b"", b"not an array", b"\x93NUMPY\x01\x00v\x00{"])
def test_a_damaged_or_misshapen_file_is_computed_again(cache, damage):
    cache.mkdir()
    (cache / "thing.npy").write_bytes(damage)
    out = _table_cache.load_or_compute("thing", lambda: np.ones(4), (4,))
    np.testing.assert_array_equal(out, np.ones(4))
    np.testing.assert_array_equal(np.load(cache / "thing.npy"), np.ones(4))  # replaced
    out = _table_cache.load_or_compute("thing", lambda: np.zeros(5), (5,))  # other shape
    np.testing.assert_array_equal(out, np.zeros(5))


def test_no_cache_when_off_or_unwritable(tmp_path, monkeypatch):
    monkeypatch.setenv("BAYESPSF_CACHE", "off")
    assert _table_cache.folder() is None
    assert _table_cache.load_or_compute("x", lambda: np.ones(2), (2,)).sum() == 2
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("BAYESPSF_CACHE", str(blocker / "cache"))  # cannot be made
    assert _table_cache.load_or_compute("x", lambda: np.ones(2), (2,)).sum() == 2


def test_the_table_tier_reads_its_table_from_the_cache(cache, monkeypatch):
    # the build is replaced by a stand-in of the right shape (a real one takes seconds); the
    # second process-like construction must read it, not build
    builds = []

    def fake_build(self):
        builds.append(self.r)
        return np.full((self.near_offset + (self.xi.size - 1) * (self.tau.size - 1), 16), 0.5)

    monkeypatch.setattr(_emccd_table.Table, "_build", fake_build)
    first = _emccd_table.Table(0.123)
    second = _emccd_table.Table(0.123)
    assert builds == [0.123]
    np.testing.assert_array_equal(first.coef, second.coef)
    assert isinstance(second.coef, np.memmap) and not second.coef.flags.writeable
    assert len(list(cache.glob("emccd-table-*.npy"))) == 1


@pytest.mark.parametrize("damage", [b"", b"\x93NUMPY\x01\x00v\x00{"])
def test_a_mapped_array_is_shared_read_only_and_a_short_file_computed_again(cache, damage):
    # ``mapped``: a later process maps the file (the processes of a pool share its pages)
    # rather than reading it; computed or mapped, the array is read-only, so compiled code
    # that takes it sees one type
    made = _table_cache.load_or_compute("thing", lambda: np.arange(6.0), (6,), mapped=True)
    again = _table_cache.load_or_compute("thing", lambda: np.zeros(6), (6,), mapped=True)
    assert not made.flags.writeable and not again.flags.writeable
    assert isinstance(again, np.memmap) and not isinstance(made, np.memmap)
    np.testing.assert_array_equal(again, np.arange(6.0))
    (cache / "other.npy").write_bytes(damage)
    out = _table_cache.load_or_compute("other", lambda: np.ones(3), (3,), mapped=True)
    np.testing.assert_array_equal(out, np.ones(3))
    np.save(cache / "short.npy", np.ones(8))  # a header promising more than the file holds
    (cache / "short.npy").write_bytes((cache / "short.npy").read_bytes()[:-16])
    out = _table_cache.load_or_compute("short", lambda: np.zeros(8), (8,), mapped=True)
    np.testing.assert_array_equal(out, np.zeros(8))
    assert not isinstance(out, np.memmap)


def test_a_file_that_cannot_be_mapped_is_read_not_built_again(cache, monkeypatch):
    # some file systems refuse memory maps: the cached file is then read (read-only all the
    # same), not computed again and rewritten by every process
    _table_cache.load_or_compute("thing", lambda: np.arange(4.0), (4,), mapped=True)
    load = np.load

    def no_maps(path, mmap_mode=None, **kwargs):
        if mmap_mode is not None:
            raise OSError("mmap not supported")
        return load(path, **kwargs)

    monkeypatch.setattr(np, "load", no_maps)
    out = _table_cache.load_or_compute("thing", lambda: np.zeros(4), (4,), mapped=True)
    np.testing.assert_array_equal(out, np.arange(4.0))
    assert not out.flags.writeable and not isinstance(out, np.memmap)
