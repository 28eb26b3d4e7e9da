"""sample_many under faults: bad ROIs, bad settings, a killed parent, two runs on one store, an
unreachable scheduler (nothing silent, nothing endless, no orphans)."""

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bayespsf import load_scene, simulate
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.parallel import executors, sample_many

FAST = {"ess": 50, "max_steps": 60, "method": "mcmc"}


@pytest.fixture(scope="module")
def stack():
    scene = load_scene("ideal")
    counts, _ = simulate(scene, 4, seed=2)
    return counts, Model.from_scene(scene)


def test_bad_rois_are_rows_and_the_rest_is_sampled(stack):
    counts, model = stack
    bad = counts.copy()
    bad[1, 3, 4] = np.nan
    bad[2] = 7.0
    table = sample_many(bad, model, workers=1, **{**FAST, "method": "importance"})
    assert table["status"].tolist()[1:3] == ["refused", "refused"]
    assert "NaN" in table.loc[1, "message"] and "same value" in table.loc[2, "message"]
    assert (
        table.loc[[0, 3], "s_x_mean"].notna().all() and table.loc[[1, 2], "s_x_mean"].isna().all()
    )


@pytest.mark.parametrize(
    "options,words",
    [
        ({"ess": float("nan")}, "ess must be"),
        ({"walkers": "32"}, "walkers must be an integer"),
        ({"max_steps": 0}, "max_steps must be"),
    ],
)
def test_bad_settings_fail_before_any_work(stack, options, words):
    counts, model = stack
    with pytest.raises(BayespsfInputError, match=words):
        sample_many(counts, model, workers=1, **options)


def test_an_empty_stack_is_named(stack):
    _, model = stack
    with pytest.raises(BayespsfInputError, match="no ROIs"):
        sample_many(np.empty((0, 15, 15)), model, workers=1)


RUN = """
import sys, numpy as np
from bayespsf import load_scene, simulate
from bayespsf.parallel.batch import sample_many
from bayespsf.model import Model
scene = load_scene("emccd-typical")
counts, _ = simulate(scene, 40, seed=1)
sample_many(counts, Model.from_scene(scene), workers=2, store=sys.argv[1], ess=4000,
            method="mcmc")
"""


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in path.read_text().split()] if path.exists() else []


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split()[2]
    except FileNotFoundError:
        return False
    return state != "Z"


def test_workers_die_with_their_killed_parent(tmp_path):
    # after SIGKILL of `bayespsf fit --workers 2` its workers stayed alive
    process = subprocess.Popen([sys.executable, "-c", RUN, str(tmp_path / "store")])
    deadline = time.monotonic() + 120
    while len(_children(process.pid)) < 2:
        assert process.poll() is None and time.monotonic() < deadline, "no workers started"
        time.sleep(0.1)
    workers = _children(process.pid)
    time.sleep(1.0)  # the workers are running their first molecules
    process.send_signal(signal.SIGKILL)
    process.wait()
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers)


def test_a_second_run_on_a_locked_store_is_refused(stack, tmp_path):
    # two processes on one store both did all the work
    counts, model = stack
    store = tmp_path / "store"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from bayespsf.parallel import Store; "
            "s = Store(sys.argv[1]); s.lock(); "
            "print('locked', flush=True); time.sleep(60)",
            str(store),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(BayespsfInputError, match=f"in use by process {holder.pid}"):
            sample_many(counts[:1], model, workers=1, store=store, **FAST)
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    # the lock dies with its process: the store is usable again, and a finished run releases it
    sample_many(counts[:1], model, workers=1, store=store, **FAST)
    sample_many(counts[:1], model, workers=1, store=store, **FAST)


def test_an_unreachable_scheduler_is_named_after_a_short_wait(stack, monkeypatch):
    counts, model = stack
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]  # closed once the block ends: nothing listens there
    monkeypatch.setattr(executors, "SCHEDULER_TIMEOUT", 2.0)
    with pytest.raises(
        BayespsfInputError,
        match=rf"no Dask scheduler answered at 'tcp://127\.0\.0\.1:{port}' within 2 s",
    ):
        sample_many(counts[:1], model, executor=f"tcp://127.0.0.1:{port}", **FAST)


FORKED = """
import os, sys
import arviz_base  # registers a lazy ``jax`` module (lazy_loader) without importing JAX
from bayespsf.inference.backends import jax_imported, release_programs
from bayespsf.parallel import local_executor
assert "jax" in sys.modules and not jax_imported()
with local_executor(2) as pool:
    print(pool.submit(os.getppid).result() == os.getpid())
release_programs()  # nothing to release: it must not import JAX to find that out
assert not jax_imported()
"""


def test_local_workers_are_forked_after_arviz_is_imported():
    # arviz-base registers a lazy ``jax`` entry without importing JAX; counted as JAX
    # running, it would send every pool made after arviz to a forkserver, whose workers
    # import bayespsf again. A forked worker's parent is this process; a forkserver's is the
    # server.
    result = subprocess.run(
        [sys.executable, "-c", FORKED], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "True"
