"""What runs the tasks (bayespsf.parallel.executors): results in order with a bounded number of
tasks sent ahead, and local worker processes that are forked while the caller runs one thread."""

import concurrent.futures as cf
import os
import subprocess
import sys
import time

import pytest

from bayespsf.parallel import run_in_order


def _printed(script: str, env=None) -> list[str]:
    """What ``script`` prints, word by word, run in a fresh interpreter (which must succeed)."""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.split()


def _slow_first(i: int) -> int:
    time.sleep(0.02 * (5 - i) if i < 5 else 0.0)  # the first tasks finish last
    return i * i


@pytest.mark.parametrize("ahead", [1, 2, 3])
def test_results_come_in_the_tasks_order_with_at_most_ahead_sent(ahead):
    drawn = []

    def tasks():
        for i in range(8):
            drawn.append(i)
            yield i

    with cf.ThreadPoolExecutor(3) as threads:
        for k, result in enumerate(run_in_order(_slow_first, tasks(), threads, ahead=ahead)):
            assert result == k * k
            assert max(drawn) <= k + ahead  # task k + ahead + 1 is not read before result k
    assert drawn == list(range(8))


def test_in_this_process_each_task_runs_when_its_result_is_asked_for():
    drawn = []

    def tasks():
        for i in range(3):
            drawn.append(i)
            yield i

    results = run_in_order(_slow_first, tasks(), None)
    assert drawn == []
    assert next(results) == 0 and drawn == [0]
    assert list(results) == [1, 4] and drawn == [0, 1, 2]


def test_forked_workers_start_with_the_pool():
    # in a process that runs one thread the pool forks its workers when it is made, not at its
    # first task (when a progress bar's monitor thread may run: a fork is unsafe then); a
    # fresh interpreter, since the test runner's own threads make the pool use a forkserver
    script = (
        "import multiprocessing, threading\n"
        "from bayespsf.parallel import local_executor\n"
        "assert threading.active_count() == 1\n"
        "with local_executor(2) as pool:\n"
        "    print(len(multiprocessing.active_children()))\n"
        "    print(sum(pool.map(abs, [-1, -2, -3])))\n"
    )
    assert _printed(script) == ["2", "6"]


def test_workers_start_by_fork_until_a_thread_runs_then_from_a_forkserver():
    # worker_start says what local_executor does: a fresh interpreter forks; once another
    # thread runs (here one that waits, as a closed Dask cluster's does) the pool's context is
    # a forkserver, and its workers are the server's children, not this process's
    script = (
        "import os, threading\n"
        "from bayespsf.parallel import local_executor, worker_start\n"
        "print(worker_start())\n"
        "stop = threading.Event()\n"
        "thread = threading.Thread(target=stop.wait)\n"
        "thread.start()\n"
        "print(worker_start())\n"
        "with local_executor(1) as pool:\n"
        "    print(pool.submit(os.getppid).result() == os.getpid())\n"
        "stop.set()\n"
        "thread.join()\n"
    )
    assert _printed(script) == ["fork", "forkserver", "False"]


@pytest.mark.parametrize(
    "imports",
    [
        "import jax\n",
        # matplotlib reads jax.Array where arviz-base registered a lazy jax module, so drawing
        # a figure after arviz imports JAX
        "import arviz_base, matplotlib\n"
        "matplotlib.use('Agg')\n"
        "import matplotlib.pyplot as plt\n"
        "plt.figure().gca().axvline(1.0)\n",
    ],
    ids=["import", "figure"],
)
def test_jax_imported_but_not_computing_leaves_pools_forking(imports):
    # importing JAX starts no threads; its first computation does. A pool made in between is
    # forked (a forkserver's workers start cold: two workers of sample_many ran 1.30x one
    # process where forked ones run 1.72x); one made after starts from a forkserver
    script = (
        "import os\n"
        "from bayespsf.inference.backends import jax_imported, jax_running\n"
        "from bayespsf.parallel import local_executor, worker_start\n"
        f"{imports}"
        "print(jax_imported(), jax_running(), worker_start())\n"
        "with local_executor(1) as pool:\n"
        "    print(pool.submit(os.getppid).result() == os.getpid())\n"
        "import jax.numpy as jnp\n"
        "float(jnp.ones(2).sum())\n"
        "print(jax_running(), worker_start())\n"
    )
    assert _printed(script) == ["True", "False", "fork", "True", "True", "forkserver"]


def test_dask_settings_reach_the_workers_of_a_local_cluster():
    # made under dask_settings(), a LocalCluster's worker has no malloc trim threshold in its
    # environment and each of the other settings in its configuration (a fresh interpreter
    # without the variable: a nanny of an earlier cluster, in an earlier test, leaves it set in
    # the process that made it, and a later cluster's workers inherit it, as docs/scale.md says)
    script = (
        "import os, dask\n"
        "from distributed import Client, LocalCluster\n"
        "from bayespsf.parallel import dask_settings\n"
        "def seen(keys):\n"
        "    return os.environ.get('MALLOC_TRIM_THRESHOLD_'), [dask.config.get(k) for k in keys]\n"
        "if __name__ == '__main__':\n"
        "    settings = dask_settings()\n"
        "    keys = [k for k in settings if 'pre-spawn-environ' not in k]\n"
        "    with (\n"
        "        dask.config.set(settings),\n"
        "        LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=':0') as c,\n"
        "        Client(c) as client,\n"
        "    ):\n"
        "        ((trim, values),) = client.run(seen, keys).values()\n"
        "    print(trim, values == [settings[k] for k in keys], values)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    printed = _printed(script, env)
    assert printed[:2] == ["None", "True"], printed


def test_a_runner_made_from_an_address_passes_keywords_on_as_an_executor_does():
    # the executor that wraps a scheduler address's client takes submit's keywords, as every
    # concurrent.futures.Executor does, and closes its client when shut down
    from bayespsf.parallel.executors import _AddressExecutor

    class Client:  # what the wrapper uses of a distributed.Client
        closed = False

        def get_executor(self):
            return cf.ThreadPoolExecutor(1)

        def close(self):
            self.closed = True

    client = Client()
    runner = _AddressExecutor(client)
    assert runner.submit(divmod, 7, 2).result() == (3, 1)
    assert runner.submit(sorted, [3, 1, 2], reverse=True).result() == [3, 2, 1]
    runner.shutdown()
    assert client.closed
