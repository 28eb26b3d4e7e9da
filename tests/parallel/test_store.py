"""The store's files: many molecules to a file, each read back as ``Posterior.save`` writes
one molecule."""

import json

import numpy as np
import pytest

from bayespsf import Model, load_scene
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import Posterior
from bayespsf.inference.result_file import molecule_attributes, result_attributes
from bayespsf.parallel import store as store_module
from bayespsf.parallel.store import STORE_FORMAT, Store

SCENE = load_scene("emccd-typical")
MODEL = Model.from_scene(SCENE)


def molecules(n, seed=0):
    """``n`` posteriors of unequal shapes (chains, draws), each with its own attributes."""
    rng = np.random.default_rng(seed)
    made = []
    for i in range(n):
        shape = (int(rng.integers(1, 5)), int(rng.integers(3, 40)), 6)
        made.append(
            {
                "draws": rng.normal(size=shape),
                "counts": rng.poisson(300, (MODEL.roi, MODEL.roi)).astype(float),
                "tau": rng.uniform(1, 30, 6),
                "info": {"method": "mcmc", "seed": i, "steps": int(rng.integers(10, 99))},
                "truth": rng.normal(size=6) if i % 2 else None,
                "row": {"molecule": 10 + i, "s_x_mean": float(rng.normal())},
            }
        )
    return made


def write(store, made, first=10):
    own = [
        molecule_attributes(m["tau"], m["info"], m["truth"]) | {"summary_row": json.dumps(m["row"])}
        for m in made
    ]
    store.write(
        [first + i for i in range(len(made))],
        [m["draws"] for m in made],
        np.stack([m["counts"] for m in made]),
        result_attributes(MODEL, SCENE),
        own,
    )


def test_each_molecule_reads_back_as_its_own_result_file_would(tmp_path):
    # draws of unequal chains and lengths share a file (padded with NaN); each reads back
    # bit for bit, with the attributes a result file of that molecule alone has
    made = molecules(5)
    store = Store(tmp_path / "s")
    store.path.mkdir()
    write(store, made)
    assert [p.name for p in store.files()] == ["posteriors-000010-000014.nc"]
    for i, m in enumerate(made):
        alone = Posterior.from_draws(
            m["draws"], m["tau"], m["info"], m["counts"], MODEL, m["truth"], SCENE
        )
        alone.tree.attrs["summary_row"] = json.dumps(m["row"])
        saved = Posterior.load(alone.save(tmp_path / f"alone-{i}.nc"))
        back = store.posterior(10 + i)
        assert dict(back.tree.attrs) == dict(saved.tree.attrs)
        assert np.array_equal(back.draws().to_numpy(), saved.draws().to_numpy())
        assert back.draws().shape == (m["draws"].shape[0] * m["draws"].shape[1], 6)
        assert np.array_equal(
            back.tree["observed_data"]["counts"].values, saved.tree["observed_data"]["counts"]
        )
        assert back.tau.equals(saved.tau) and back.info == m["info"]
    assert store.finished(100) == {10 + i: m["row"] for i, m in enumerate(made)}
    assert store.finished(12) == {10: made[0]["row"], 11: made[1]["row"]}  # indices < n
    with pytest.raises(BayespsfInputError, match="holds no posterior of molecule 15"):
        store.posterior(15)
    for index in (10.5, "10", True):  # read as molecule 10 (or 1) before it was refused
        with pytest.raises(BayespsfInputError, match="index must be a molecule's number"):
            store.posterior(index)
    assert store.posterior(np.int64(11)).info == made[1]["info"]
    with pytest.raises(BayespsfInputError, match=r"many molecules; read one with .*\.posterior"):
        Posterior.load(store.files()[0])


def test_a_chain_posterior_is_written_as_a_file_of_its_own(tmp_path):
    m = molecules(1, seed=3)[0]
    post = Posterior.from_draws(m["draws"], m["tau"], m["info"], m["counts"], MODEL, None, SCENE)
    post.tree.attrs["summary_row"] = json.dumps(m["row"])
    store = Store(tmp_path)
    store.write_posterior(7, post)
    assert [p.name for p in store.files()] == ["posteriors-000007-000007.nc"]
    back = store.posterior(7)
    assert dict(back.tree.attrs) == dict(post.tree.attrs)
    assert np.array_equal(back.draws().to_numpy(), post.draws().to_numpy())


def test_a_large_write_is_split_into_files_of_file_molecules(tmp_path, monkeypatch):
    monkeypatch.setattr(store_module, "FILE_MOLECULES", 3)
    made = molecules(7, seed=1)
    store = Store(tmp_path)
    write(store, made, first=0)
    names = [p.name for p in store.files()]
    assert names == [
        "posteriors-000000-000002.nc",
        "posteriors-000003-000005.nc",
        "posteriors-000006-000006.nc",
    ]
    assert sorted(store.finished(7)) == list(range(7))
    assert np.array_equal(
        store.posterior(4).draws().to_numpy()[:, 0], made[4]["draws"][..., 0].ravel()
    )


def test_a_damaged_file_is_named_with_the_way_on(tmp_path):
    store = Store(tmp_path)
    write(store, molecules(2))
    (path,) = store.files()
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # truncated
    for read in (lambda: store.finished(20), lambda: store.posterior(10)):
        with pytest.raises(BayespsfInputError, match="delete it and rerun") as error:
            read()
        assert str(path) in str(error.value)
    Posterior.from_draws(np.zeros((1, 2, 6))).save(path)  # a result file, not a store's
    with pytest.raises(BayespsfInputError, match="not a file of a bayespsf store"):
        store.finished(20)


def test_a_store_of_the_earlier_layout_is_refused_by_name(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"bayespsf": "sample_many store"}))
    with pytest.raises(BayespsfInputError, match="one file per molecule"):
        Store(tmp_path).open({"bayespsf": "sample_many store"})
    store = Store(tmp_path / "new")
    store.open({"seed": 1})
    manifest = json.loads((store.path / "manifest.json").read_text())
    assert manifest == {"store": STORE_FORMAT, "seed": 1}
    store.open({"seed": 1})  # the same run again
    with pytest.raises(BayespsfInputError, match="seed differ"):
        store.open({"seed": 2})


def test_a_killed_runs_partial_files_are_removed_by_the_next_run(tmp_path):
    store = Store(tmp_path)
    partial = tmp_path / "posteriors-000000-000255.nc.partial"
    partial.write_bytes(b"half")
    store.open({"seed": 1})  # without the lock another run may be writing it
    assert partial.exists()
    store.lock()
    try:
        store.open({"seed": 1})
    finally:
        store.unlock()
    assert not partial.exists()


def test_a_store_that_keeps_no_draws_keeps_the_rest(tmp_path):
    """A store opened with ``NO_DRAWS`` writes each molecule's summary row, sampler record and
    counts but no draws: its files are smaller, ``finished`` reads the rows back as from a
    store with draws, ``Store.posterior`` refuses by name, and a run that keeps draws is
    refused there as another run."""
    made = molecules(40, seed=5)
    kept, bare = Store(tmp_path / "kept"), Store(tmp_path / "bare")
    kept.open({"run": 1})
    bare.open({"run": 1} | store_module.NO_DRAWS)
    write(kept, made)
    write(bare, made)
    assert kept.keeps_draws() and not bare.keeps_draws()
    assert (
        bare.finished(100) == kept.finished(100) == {10 + i: m["row"] for i, m in enumerate(made)}
    )
    size = [sum(p.stat().st_size for p in s.files()) for s in (kept, bare)]
    assert size[1] < 0.8 * size[0]
    with pytest.raises(BayespsfInputError, match="keeps no draws"):
        bare.posterior(10)
    with pytest.raises(BayespsfInputError, match="draws differ"):
        bare.open({"run": 1})
