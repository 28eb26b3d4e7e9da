"""sample_many: identical results for any executor (serial, local processes, a Dask
LocalCluster), a store that survives a killed run and resumes it, clear errors."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bayespsf import load_scene, simulate
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.summary import QUANTILES, coverage, quantile_column
from bayespsf.model import Model
from bayespsf.parallel import Store, molecule_seed, sample_many
from bayespsf.psf import PARAMETER_NAMES

# short capped runs: the tests are about plumbing and reproducibility, not convergence
OPTIONS = {"max_steps": 60, "walkers": 12, "method": "mcmc"}
N_MOLECULES = 4


@pytest.fixture(scope="module")
def stack():
    scene = load_scene("ideal")
    counts, truth = simulate(scene, N_MOLECULES, seed=11)
    return counts, truth[list(PARAMETER_NAMES)].to_numpy(float), Model.from_scene(scene)


@pytest.fixture(scope="module")
def serial(stack):
    counts, truths, model = stack
    return sample_many(counts, model, seed=3, workers=1, truths=truths, **OPTIONS)


def without_timing(table):
    return table.drop(columns=["seconds"]).reset_index(drop=True)


def test_rows_columns_and_ranks(serial, stack):
    _, truths, _ = stack
    assert list(serial["molecule"]) == list(range(N_MOLECULES))
    assert serial["seed"].nunique() == N_MOLECULES
    for k, name in enumerate(PARAMETER_NAMES):
        np.testing.assert_array_equal(serial[f"{name}_truth"], truths[:, k])
        assert serial[f"{name}_rank"].between(0, 99).all()
        qs = serial[[quantile_column(name, q) for q in QUANTILES]].to_numpy()
        assert np.all(np.diff(qs, axis=1) >= 0)  # quantiles are ordered
    assert not serial["converged"].any()  # the 60-step cap is flagged, never hidden


def test_two_processes_give_identical_results(serial, stack):
    counts, truths, model = stack
    table = sample_many(counts, model, seed=3, workers=2, truths=truths, **OPTIONS)
    pd.testing.assert_frame_equal(without_timing(table), without_timing(serial))


def test_dask_local_cluster_gives_identical_results(serial, stack):
    distributed = pytest.importorskip("distributed")  # a dependency: installed by pyproject
    counts, truths, model = stack
    # ":0": the scheduler's HTTP server on a free port (None still binds 8787, which another
    # test's cluster may hold when the tests run in parallel: a warning, an error here)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, dashboard_address=":0", processes=True
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        by_client = sample_many(counts, model, seed=3, executor=client, truths=truths, **OPTIONS)
        by_address = sample_many(
            counts[:2], model, seed=3, executor=cluster.scheduler_address, **OPTIONS
        )
    pd.testing.assert_frame_equal(without_timing(by_client), without_timing(serial))
    assert list(by_address["seed"]) == list(serial["seed"][:2])
    np.testing.assert_array_equal(by_address["s_x_mean"], serial["s_x_mean"][:2])


KILLED_RUN = """
import sys
import numpy as np
from bayespsf import load_scene, simulate
from bayespsf.parallel.batch import sample_many
from bayespsf.model import Model
scene = load_scene("ideal")
counts, truth = simulate(scene, {n}, seed=11)
truths = truth[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy(float)
sample_many(counts, Model.from_scene(scene), seed=3, workers=1, truths=truths,
            store=sys.argv[1], max_steps={max_steps}, walkers={walkers}, method="mcmc")
"""


def test_killed_run_keeps_finished_molecules_and_resumes(serial, stack, tmp_path):
    counts, truths, model = stack
    store = tmp_path / "store"
    script = KILLED_RUN.format(n=N_MOLECULES, **OPTIONS)
    process = subprocess.Popen([sys.executable, "-c", script, str(store)])
    deadline = time.monotonic() + 120
    while not list(store.glob("posteriors-*.nc")):
        assert process.poll() is None, "the run ended before it could be killed"
        assert time.monotonic() < deadline, "no molecule finished in 120 s"
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    # the chain writes each molecule as it finishes, to a file of its own
    finished = {p.name: p.stat().st_mtime_ns for p in store.glob("posteriors-*.nc")}
    assert 1 <= len(finished) < N_MOLECULES
    assert not (store / "summary.csv").exists()
    table = sample_many(counts, model, seed=3, workers=1, truths=truths, store=store, **OPTIONS)
    for name, mtime in finished.items():  # finished molecules were read back, not redone
        assert (store / name).stat().st_mtime_ns == mtime
    assert len(list(store.glob("posteriors-*.nc"))) == N_MOLECULES
    assert sorted(Store(store).finished(N_MOLECULES)) == list(range(N_MOLECULES))
    assert not list(store.glob("*.partial"))
    pd.testing.assert_frame_equal(without_timing(table), without_timing(serial))
    on_disk = pd.read_csv(store / "summary.csv")
    np.testing.assert_allclose(on_disk["s_x_sd"], serial["s_x_sd"], rtol=1e-12)


def test_store_made_for_another_run_is_refused(stack, tmp_path):
    counts, _, model = stack
    sample_many(counts[:1], model, seed=3, workers=1, store=tmp_path, **OPTIONS)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["molecules"] == 1
    with pytest.raises(BayespsfInputError, match="seed"):
        sample_many(counts[:1], model, seed=4, workers=1, store=tmp_path, **OPTIONS)
    with pytest.raises(BayespsfInputError, match="data sha256"):
        sample_many(counts[1:2], model, seed=3, workers=1, store=tmp_path, **OPTIONS)
    narrow = Model.from_scene(
        load_scene("ideal").replace(prior={"N": {"kind": "log-uniform", "low": 10, "high": 1e5}})
    )
    with pytest.raises(BayespsfInputError, match="prior"):
        sample_many(counts[:1], narrow, seed=3, workers=1, store=tmp_path, **OPTIONS)
    # the manifest holds every sampler setting, defaults included: a store made with other
    # moves (or under another version's defaults) is refused, not resumed with mixed results
    assert manifest["sampler"]["moves"] == "laplace-de" and manifest["sampler"]["ess"] == 400
    with pytest.raises(BayespsfInputError, match="sampler"):
        sample_many(
            counts[:1], model, seed=3, workers=1, store=tmp_path, moves="stretch", **OPTIONS
        )


def test_the_model_check_is_stored_with_each_posterior(stack, tmp_path):
    # check=True: each row and each posterior file carry the bootstrap goodness-of-fit test
    # (bayespsf.inference.gof), its replicates drawn from the molecule's own seed, so the values
    # are those of bootstrap_check with those seeds, for the batched and the chain paths, on
    # one process or two
    from bayespsf.inference import bootstrap_check

    counts, _, model = stack
    seeds = [molecule_seed(5, i) for i in range(N_MOLECULES)]
    reference = bootstrap_check(counts, model, seed=seeds)
    expected = reference["gof_p"].to_numpy()
    batched = sample_many(
        counts, model, seed=5, workers=1, method="laplace", check=True, store=tmp_path / "s"
    )
    chain = sample_many(counts[:2], model, seed=5, workers=2, check=True, **OPTIONS)
    assert np.array_equal(batched["gof_p"].to_numpy(), expected)
    assert np.array_equal(chain["gof_p"].to_numpy(), expected[:2])
    assert np.array_equal(batched["gof_replicates"], reference["gof_replicates"])
    assert batched["gof_replicates"].between(10, 49).all()
    stored = json.loads(Store(tmp_path / "s").posterior(1).tree.attrs["summary_row"])
    assert stored["gof_p"] == expected[1]
    assert "gof_p" in pd.read_csv(tmp_path / "s" / "summary.csv")
    with pytest.raises(BayespsfInputError, match="model check"):  # a store made with it
        sample_many(counts, model, seed=5, workers=1, store=tmp_path / "s", method="laplace")
    assert "gof_p" not in sample_many(counts[:1], model, seed=5, workers=1, method="laplace")
    with pytest.raises(BayespsfInputError, match=r"check \(True, False or a discrepancy\) must"):
        sample_many(counts[:1], model, workers=1, method="laplace", check="no")
    # check="pearson": the same test with Pearson's discrepancy; a store made with the
    # default refuses it
    pearson = sample_many(counts, model, seed=5, workers=1, method="laplace", check="pearson")
    expected = bootstrap_check(counts, model, seed=seeds, discrepancy="pearson")["gof_p"]
    assert np.array_equal(pearson["gof_p"].to_numpy(), expected.to_numpy())
    with pytest.raises(BayespsfInputError, match="model check"):
        sample_many(
            counts,
            model,
            seed=5,
            workers=1,
            store=tmp_path / "s",
            method="laplace",
            check="pearson",
        )


def test_bad_input_is_named(stack):
    counts, truths, model = stack
    with pytest.raises(BayespsfInputError, match="stack"):
        sample_many(counts[0], model, workers=1)
    with pytest.raises(BayespsfInputError, match="truths"):
        sample_many(counts, model, workers=1, truths=truths[:2])
    with pytest.raises(BayespsfInputError, match="thin"):
        sample_many(counts, model, workers=1, thin=3)
    with pytest.raises(BayespsfInputError, match="workers"):
        sample_many(counts, model, workers=0)
    with pytest.raises(BayespsfInputError, match="executor"):
        sample_many(counts, model, executor=42)
    with pytest.raises(BayespsfInputError, match="seed"):
        sample_many(counts, model, seed=-1)


def test_molecule_seeds_are_distinct_and_stable():
    seeds = {molecule_seed(s, i) for s in range(20) for i in range(50)}
    assert len(seeds) == 1000
    assert molecule_seed(3, 7) == molecule_seed(3, 7)


def test_coverage_counts_intervals_that_hold_the_truth():
    rng = np.random.default_rng(0)
    rows = {}
    truth = rng.standard_normal(400)
    for name in PARAMETER_NAMES:
        rows[f"{name}_truth"] = truth
        # central 68% interval of N(0, 1): +-0.9945; the truth is N(0, 1), so coverage ~0.68
        rows[quantile_column(name, 0.16)] = np.full(400, -0.9945)
        rows[quantile_column(name, 0.84)] = np.full(400, 0.9945)
    table = coverage(pd.DataFrame(rows), 0.68)
    expected = np.mean(np.abs(truth) <= 0.9945)
    np.testing.assert_allclose(table["coverage"], expected)
    np.testing.assert_allclose(table["se"], np.sqrt(expected * (1 - expected) / 400))
    with pytest.raises(BayespsfInputError, match="prob"):
        coverage(pd.DataFrame(rows), 0.8)
    with pytest.raises(BayespsfInputError, match="x0_truth"):
        coverage(pd.DataFrame(rows).drop(columns="x0_truth"), 0.68)


def test_store_path_is_not_required_to_exist(stack, tmp_path):
    counts, _, model = stack
    store = Path(tmp_path) / "a" / "b"
    sample_many(counts[:1], model, seed=3, workers=1, store=store, **OPTIONS)
    assert (store / "posteriors-000000-000000.nc").exists()
    assert os.path.getsize(store / "summary.csv") > 0


def test_ranks_of_truths_drawn_like_the_posterior_are_uniform():
    # 300 synthetic posteriors of iid N(0, 1) draws, each truth drawn from the same law: the
    # truth's rank among the 99 chosen draws is uniform on 0..99, so 10 bins of ranks pass a
    # chi-square test (p > 1e-3 fails a correct implementation once in a thousand runs)
    from scipy import stats

    from bayespsf.inference import Posterior
    from bayespsf.inference.summary import molecule_row

    rng = np.random.default_rng(8)
    ranks = []
    for i in range(300):
        draws = rng.standard_normal((12, 40, 6))  # (walkers, thinned draws, parameters)
        truth = rng.standard_normal(6)
        post = Posterior.from_draws(
            draws, tau=np.full(6, 10.0), truth=truth, info={"steps": 500, "burn": 100}
        )
        row = molecule_row(post, i, seed=i)
        ranks.append([row[f"{n}_rank"] for n in PARAMETER_NAMES])
        assert row["x0_q0500"] == pytest.approx(np.median(draws[..., 0]))
        assert row["x0_ess"] == pytest.approx(12 * 400 / 10.0)
    ranks = np.array(ranks)
    assert ranks.min() >= 0 and ranks.max() <= 99
    for k in range(6):
        counts = np.bincount(ranks[:, k] // 10, minlength=10)
        assert stats.chisquare(counts).pvalue > 1e-3


def test_a_posterior_too_short_to_rank_gets_no_rank_instead_of_an_error():
    from bayespsf.inference import Posterior
    from bayespsf.inference.summary import RANK_DRAWS, molecule_row

    draws = np.random.default_rng(0).normal(100.0, 1.0, (2, 20, 6))  # 20 spaced draws < 99
    truth = np.full(6, 100.0)
    post = Posterior.from_draws(draws, tau=np.ones(6), info={"steps": 20}, truth=truth)
    row = molecule_row(post, 0, seed=1)
    assert RANK_DRAWS > 20 and np.isnan(row["s_x_rank"]) and row["s_x_truth"] == 100.0
    assert "s_x_rank" not in molecule_row(Posterior.from_draws(draws, tau=np.ones(6)), 0, 1)


def test_chunks_keep_every_worker_busy_and_memory_bounded():
    from bayespsf.parallel.batch import CHUNK, MIN_CHUNK, chunk_count

    assert chunk_count(24, 2, 400.0) == 2  # one stack, two workers: two tasks
    assert chunk_count(MIN_CHUNK, 8, 400.0) == 1  # too few ROIs to split
    assert chunk_count(10 * CHUNK, 2, 400.0) == 10  # large stacks: chunks of CHUNK
    assert chunk_count(1000, 1, 20_000.0) == 200  # ESS 20 000: 5 ROIs per chunk
    assert chunk_count(1000, 1, 1e7) == 500  # never fewer than 2 ROIs per chunk
    # more chunks than workers: a multiple of the workers, of at most CHUNK ROIs, where the
    # chunks stay at least MIN_CHUNK ROIs (chunks already smaller, at a high ESS, are kept)
    assert chunk_count(32_000, 16, 400.0) == 128  # 125 of CHUNK would leave 3 workers idle
    assert chunk_count(100_000, 16, 400.0) == 400
    assert chunk_count(11 * CHUNK, 2, 400.0) == 12
    assert chunk_count(1000, 16, 20_000.0) == 200  # 5 ROIs per chunk: kept
    for n, workers in [(5000, 3), (32_000, 16), (999, 7), (300, 16)]:
        parts = chunk_count(n, workers, 400.0)
        assert -(-n // parts) <= CHUNK and (parts <= workers or n // parts >= MIN_CHUNK)


def test_the_table_of_chunks_and_single_rows_is_that_of_every_row_in_order():
    """The summary table is assembled from the chunks' tables (the batched methods) and single
    rows (refused, resumed or chained ROIs, with other keys): it must equal
    ``pd.DataFrame`` of all the rows in molecule order, columns, their order, dtypes and
    values, wherever each kind of row comes first."""
    from bayespsf.parallel.batch import _table

    rng = np.random.default_rng(5)

    def made(i):  # a batched posterior's row
        return {
            "molecule": i,
            "seed": molecule_seed(3, i),
            "converged": True,
            "method": "importance",
            "x0_mean": rng.normal(),
            "chi2": rng.random(),
        }

    def refused(i):
        return {
            "molecule": i,
            "seed": molecule_seed(3, i),
            "converged": False,
            "status": "refused",
            "message": "saturated",
        }

    def chained(i):  # the chain's row: other keys, in another order, and an int column
        return {
            "molecule": i,
            "seed": molecule_seed(3, i),
            "converged": False,
            "steps": 60,
            "method": "mcmc",
            "x0_mean": rng.normal(),
            "acceptance": 0.3,
        }

    # seeds above 2**63 are uint64 in a table, smaller ones int64: these kinds mix both
    # (molecule_seed(3, i) is at or above 2**63 for i = 3, 4, 5)
    assert {molecule_seed(3, i) >= 2**63 for i in range(7)} == {True, False}
    for kinds in ("mmrmcmm", "rmmcmr", "cmmmmr", "mmmm", "rcr", "mmc"):
        rows = [{"m": made, "r": refused, "c": chained}[k](i) for i, k in enumerate(kinds)]
        chunked = [i for i, k in enumerate(kinds) if k == "m"]
        pieces = [pd.DataFrame([rows[i] for i in part]) for part in (chunked[:2], chunked[2:])]
        single = {i: rows[i] for i, k in enumerate(kinds) if k != "m"}
        table = _table([p for p in pieces if len(p)], single)
        pd.testing.assert_frame_equal(table, pd.DataFrame(rows), check_exact=True)


def test_a_table_of_batched_and_chain_rows_takes_its_unit_column_without_a_warning(
    monkeypatch,
):
    # the batched rows and a chain's row have different columns: their concatenation is a
    # frame of many blocks, to which adding photon_unit raised pandas' PerformanceWarning
    # (an error in this suite); here 5 ROIs are importance-sampled and one fails the Laplace
    # Student-t, which the chain then samples (the fitted mixture's rounds, which would take
    # it, are turned off: this process runs them)
    from bayespsf.inference import batched

    monkeypatch.setattr(batched, "ADAPT_ROUNDS", 0)
    scene = load_scene("ideal").replace(emitter={"photons": 1e6}, background={"kind": "none"})
    counts, truth = simulate(scene, 6, seed=2)
    table = sample_many(counts, Model.from_scene(scene), seed=1, workers=1, truths=truth.to_numpy())
    assert set(table["method"]) == {"importance", "mcmc"}
    assert (table["photon_unit"] == Model.from_scene(scene).photon_unit_label).all()


def test_a_store_without_draws_gives_the_same_table(stack, tmp_path):
    """``keep_draws=False``: the same summary table as with the draws kept (batched and chain
    posteriors), the store's files under half the size, its rerun resumed from them;
    False without a store, or a value that is not a bool, is refused by name."""
    counts, _, model = stack
    kept = sample_many(counts, model, seed=2, workers=1, store=tmp_path / "k", method="auto")
    bare = sample_many(
        counts, model, seed=2, workers=1, store=tmp_path / "b", method="auto", keep_draws=False
    )
    pd.testing.assert_frame_equal(kept.drop(columns="seconds"), bare.drop(columns="seconds"))
    size = [sum(p.stat().st_size for p in Store(tmp_path / s).files()) for s in ("k", "b")]
    assert size[1] < size[0] / 2
    again = sample_many(
        counts, model, seed=2, workers=1, store=tmp_path / "b", method="auto", keep_draws=False
    )
    pd.testing.assert_frame_equal(again, bare)
    chain = sample_many(
        counts[:1], model, seed=2, workers=1, store=tmp_path / "c", keep_draws=False, **OPTIONS
    )
    assert chain["method"].iloc[0] == "mcmc" and not Store(tmp_path / "c").keeps_draws()
    for bad in ({"keep_draws": False}, {"keep_draws": "no", "store": tmp_path / "x"}):
        with pytest.raises(BayespsfInputError, match="keep_draws must be True or False"):
            sample_many(counts[:1], model, workers=1, method="laplace", **bad)
