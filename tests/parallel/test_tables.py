"""``write_csv``: a table's rows formatted on the workers give pandas' own file, to the byte."""

from __future__ import annotations

import concurrent.futures as cf

import numpy as np
import pandas as pd
import pytest

from bayespsf.parallel import Store, local_executor
from bayespsf.parallel.tables import MIN_BLOCK, write_csv


def _awkward(n: int) -> pd.DataFrame:
    """Every kind of value a summary or localisation table holds, and those that CSV quotes:
    floats at the edges of their formatting (NaN, inf, -0.0, subnormal, 1e16, 1e-5), uint64
    seeds above 2**63, bools, nullable integers, strings with commas, quotes and newlines,
    None and empty strings."""
    rng = np.random.default_rng(4)
    edges = [np.nan, np.inf, -np.inf, -0.0, 5e-324, 1e16, 1e-5, 2.0, 1 / 3, 1.7976931348623157e308]
    values = rng.normal(size=n) * 10.0 ** rng.integers(-8, 18, n)
    values[: len(edges)] = edges
    words = np.array(["converged", "a, b", 'say "no"', "two\nlines", "", None], dtype=object)
    steps = pd.array(rng.integers(0, 9, n), dtype="Int64")
    steps[rng.random(n) < 0.2] = pd.NA
    return pd.DataFrame(
        {
            "molecule": np.arange(n),
            "seed": rng.integers(0, 2**64 - 1, n, dtype=np.uint64),
            "x0_mean": values,
            "x0_sd": rng.random(n),
            "converged": rng.random(n) > 0.3,
            "steps": steps,
            "why": words[rng.integers(0, len(words), n)],
        }
    )


@pytest.fixture(scope="module")
def workers():
    with local_executor(2) as runner:
        yield runner


def test_rows_formatted_on_workers_give_pandas_file_to_the_byte(tmp_path, workers):
    table = _awkward(2 * MIN_BLOCK + 777)  # three blocks, the last a part of one
    table.to_csv(tmp_path / "pandas.csv", index=False)
    expected = (tmp_path / "pandas.csv").read_bytes()
    for name, runner in (("here", None), ("workers", workers)):
        written = write_csv(table, tmp_path / f"{name}.csv", runner)
        assert written.read_bytes() == expected, name
    back = pd.read_csv(tmp_path / "workers.csv", float_precision="round_trip")
    np.testing.assert_array_equal(back["x0_mean"], table["x0_mean"])  # shortest digits


def test_the_blocks_go_to_the_runner_in_order(tmp_path):
    class Counting(cf.ThreadPoolExecutor):
        def __init__(self):
            super().__init__(max_workers=3)
            self.sent = []

        def submit(self, function, /, *args, **kwargs):
            self.sent.append(len(args[0]))
            return super().submit(function, *args, **kwargs)

    table = _awkward(9 * MIN_BLOCK + 5)
    with Counting() as runner:
        written = write_csv(table, tmp_path / "t.csv", runner)
        sizes = list(runner.sent)
    assert written.read_bytes() == table.to_csv(index=False).encode()
    # about four blocks a worker, each at least MIN_BLOCK rows, every row once
    assert len(sizes) >= 4 and min(sizes[:-1]) >= MIN_BLOCK and sum(sizes) == len(table)


class Refusing(cf.ThreadPoolExecutor):
    """A runner that fails the test if a block is sent to it."""

    def submit(self, *args, **kwargs):
        raise AssertionError("a block was sent")


def test_a_small_table_or_one_worker_is_written_here(tmp_path):
    table, large = _awkward(2 * MIN_BLOCK - 1), _awkward(3 * MIN_BLOCK)
    with Refusing(max_workers=2) as two, Refusing(max_workers=1) as one:
        write_csv(table, tmp_path / "small.csv", two)
        write_csv(large, tmp_path / "one.csv", one)
    assert (tmp_path / "small.csv").read_bytes() == table.to_csv(index=False).encode()
    assert (tmp_path / "one.csv").read_bytes() == large.to_csv(index=False).encode()


def test_dates_durations_and_compressed_files_are_written_whole_by_pandas(tmp_path):
    # pandas writes a column of dates at midnight as bare dates, and durations of whole days
    # without their time, only where every value of the column allows: a block would differ
    n = 3 * MIN_BLOCK
    one_late = pd.to_timedelta(np.r_[np.zeros(n - 1), 1.5], unit="h")
    tables = {
        "dates": pd.DataFrame({"t": pd.Timestamp("2020-01-01") + one_late}),
        "durations": pd.DataFrame({"d": pd.to_timedelta(np.r_[np.ones(n - 1), 1.5], unit="D")}),
        "categories": pd.DataFrame({"c": pd.Categorical(pd.Timestamp("2020-01-01") + one_late)}),
    }
    with Refusing(max_workers=2) as runner:
        for name, table in tables.items():
            written = write_csv(table, tmp_path / f"{name}.csv", runner)
            assert written.read_bytes() == table.to_csv(index=False).encode(), name
        write_csv(_awkward(n), tmp_path / "t.csv.gz", runner)
    assert pd.read_csv(tmp_path / "t.csv.gz").shape == (n, 7)  # pandas' own gzip


def test_a_store_summary_written_on_workers_is_the_same_file(tmp_path, workers):
    table = _awkward(2 * MIN_BLOCK + 1)
    store = Store(tmp_path / "store")
    store.path.mkdir()
    store.write_summary(table, workers)
    assert not (store.path / "summary.csv.partial").exists()
    assert (store.path / "summary.csv").read_bytes() == table.to_csv(index=False).encode()


def test_rows_formatted_on_a_dask_cluster_give_the_same_file(tmp_path):
    distributed = pytest.importorskip("distributed")  # a dependency: installed by pyproject
    from bayespsf.parallel import task_runner

    table = _awkward(3 * MIN_BLOCK)
    # ":0": the dashboard on a free port (another test's cluster may hold 8787: a warning)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, dashboard_address=":0", processes=True
        ) as cluster,
        distributed.Client(cluster) as client,
        task_runner(client, None) as runner,
    ):
        written = write_csv(table, tmp_path / "dask.csv", runner)
    assert written.read_bytes() == table.to_csv(index=False).encode()
