"""What runs many tasks: this process, a pool of local worker processes that die with their
parent, or a Dask ``distributed`` cluster (a ``Client``, its executor, or a scheduler address),
and how many tasks each runs at once."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.backends import jax_running

if TYPE_CHECKING:
    from distributed import Client

SCHEDULER_TIMEOUT = 10.0  # seconds to reach a Dask scheduler before the address is called wrong


def parallelism(runner: cf.Executor | None) -> int:
    """How many tasks ``runner`` runs at once.

    Parameters
    ----------
    runner : concurrent.futures.Executor or None
        From ``task_runner``.

    Returns
    -------
    int
        1 in this process (None); a Dask executor's worker count; a pool's size.

    Notes
    -----
    Neither ``concurrent.futures``' pools nor Dask's ``ClientExecutor`` expose it publicly,
    so their private ``_max_workers`` and ``_client`` are read where present, and the
    machine's core count stands in where not: it sizes the chunks and how many tasks are
    kept waiting, never the results.
    """
    if runner is None:
        return 1
    client = getattr(runner, "client", None) or getattr(runner, "_client", None)
    if client is not None and hasattr(client, "scheduler_info"):
        return max(1, len(client.scheduler_info().get("workers", {})))
    return int(getattr(runner, "_max_workers", None) or os.cpu_count() or 1)


def _die_with_parent(parent: int) -> None:
    """Worker initializer: ask the kernel to kill this worker when its parent dies (Linux
    ``prctl(PR_SET_PDEATHSIG, SIGKILL)``), so that a killed run leaves no orphaned workers; if
    the parent is already gone, exit."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def worker_start() -> str:
    """How a pool of local workers made now starts them: ``"fork"`` or ``"forkserver"``.

    Returns
    -------
    str
        ``"fork"`` (the fastest start) while this process runs one Python thread and JAX's
        runtime has not started; ``"forkserver"`` once other threads run (a Dask client, a progress
        monitor, a Jupyter kernel, a thread a closed Dask cluster leaves behind) or JAX has
        computed (its runtime threads, which Python does not count), where a fork is unsafe.
        JAX imported without computing (matplotlib imports it when it plots after arviz:
        ``bayespsf.inference.backends.jax_running``) runs no threads and allows a fork.

    See Also
    --------
    local_executor : the pool, which starts its workers this way.

    Examples
    --------
    >>> from bayespsf.parallel import worker_start
    >>> worker_start() in ("fork", "forkserver")
    True
    """
    return "fork" if threading.active_count() == 1 and not jax_running() else "forkserver"


def local_executor(workers: int | None = None) -> cf.ProcessPoolExecutor:
    """A pool of local worker processes to pass to several ``sample_many`` runs.

    Parameters
    ----------
    workers : int, optional
        Worker processes (>= 1); default one per core.

    Returns
    -------
    concurrent.futures.ProcessPoolExecutor
        Its workers, and their cached EMCCD tables, are reused from run to run; they die
        with this process (Linux). Shut it down when done.

    Raises
    ------
    BayespsfInputError
        If ``workers`` is below 1.

    See Also
    --------
    task_runner : what ``sample_many`` runs its tasks on.
    worker_start : how the workers of a pool made now start.

    Notes
    -----
    Workers are forked, the fastest start, while this process runs one Python thread; once
    threads run (a Dask client, a progress monitor, a Jupyter kernel, or a JAX that has computed,
    whose runtime threads Python does not count), where a fork is unsafe, they start from a
    forkserver, which imports the main module and ``bayespsf.parallel`` once, then forks the
    workers (``worker_start`` says which). The choice is made here, when the pool is made,
    and forked workers start here too (a pool forks them all at its first task): a pool made
    before a progress bar's thread starts, or before JAX computes, stays safe to use after.
    """
    workers = os.cpu_count() if workers is None else int(workers)
    if workers < 1:
        raise BayespsfInputError(f"workers must be >= 1, got {workers!r}")
    # fork is fastest and needs no __main__ guard, but is unsafe once threads run (a Dask
    # client, a progress monitor, JAX's runtime): then forkserver (Notes)
    method = worker_start()
    context = multiprocessing.get_context(method)
    if method == "forkserver":  # the server imports what the workers run, once
        context.set_forkserver_preload(["__main__", "bayespsf.parallel"])
    # a forkserver's workers are its children: they die with it, and it ends with this process
    parent = os.getpid() if method == "fork" else None
    pool = cf.ProcessPoolExecutor(
        workers, mp_context=context, initializer=_die_with_parent_of, initargs=(parent,)
    )
    if method == "fork":  # every worker forked now, while this process runs one thread
        pool.submit(os.getpid).result()
    return pool


def dask_settings() -> dict[str, object]:
    """Dask's configuration for a cluster that runs bayespsf alone.

    Returns
    -------
    dict
        A new dict for ``dask.config.set``, made before the cluster (a nanny passes it on to
        its worker): Dask's ``MALLOC_TRIM_THRESHOLD_`` unset in the workers' environment (it
        also fixes glibc's mmap threshold at 128 KB, so that every working array of a chunk
        above that is mapped afresh and faulted in), no statistical profiler in the workers
        (it samples each worker's stack every 10 ms), the event loop's health checked every
        200 ms rather than 20, and the system monitor read every 5 s rather than 0.5.

    Notes
    -----
    bayespsf does not set these itself: they are a cluster's, which may run other work, and
    without the profiler Dask's dashboard shows no profile of the workers' code. An idle
    worker spends 0.009 CPU seconds per second with them, 0.037-0.048 without (two workers
    on two cores; ``docs/scale.md``).

    Examples
    --------
    >>> import dask
    >>> from bayespsf.parallel import dask_settings
    >>> with dask.config.set(dask_settings()):
    ...     dask.config.get("distributed.worker.profile.enabled")
    False
    """
    return {
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
        "distributed.worker.profile.enabled": False,
        "distributed.admin.tick.interval": "200ms",
        "distributed.admin.system-monitor.interval": "5s",
    }


def _die_with_parent_of(parent: int | None) -> None:
    _die_with_parent(os.getppid() if parent is None else parent)


def _executor(executor, workers):
    """(executor, owned): what runs the tasks, and whether sample_many must shut it down."""
    if executor is None:
        if workers == 1:
            return None, False
        return local_executor(workers), True
    if workers is not None:
        raise BayespsfInputError("give either executor or workers, not both")
    if isinstance(executor, str):
        from distributed import Client

        try:
            client = Client(executor, timeout=SCHEDULER_TIMEOUT)
        except ValueError as exc:  # distributed's parse of the address
            raise BayespsfInputError(
                f"{executor!r} is not a Dask scheduler address ({exc}); give one such as "
                "'tcp://10.0.0.5:8786'"
            ) from None
        except (OSError, TimeoutError) as exc:
            raise BayespsfInputError(
                f"no Dask scheduler answered at {executor!r} within {SCHEDULER_TIMEOUT:g} s "
                f"({type(exc).__name__}); check the address and that the scheduler runs"
            ) from None
        return _AddressExecutor(client), True
    if hasattr(executor, "get_executor"):  # a dask.distributed.Client
        return executor.get_executor(), False
    if isinstance(executor, cf.Executor):
        return executor, False
    raise BayespsfInputError(
        "executor must be None, a concurrent.futures.Executor, a dask.distributed Client or "
        f"a scheduler address; got {type(executor).__name__}"
    )


@contextmanager
def task_runner(
    executor: cf.Executor | Client | str | None, workers: int | None
) -> Iterator[cf.Executor | None]:
    """What runs a function's tasks, shut down on leaving when it was made here.

    Parameters
    ----------
    executor : concurrent.futures.Executor, distributed.Client, str or None
        ``None`` (local processes, or this process with ``workers=1``), an executor, a Dask
        ``Client`` (its executor) or a Dask scheduler's address (a client is made and
        closed here).
    workers : int, optional
        Local processes when ``executor`` is None (default: one per core).

    Yields
    ------
    concurrent.futures.Executor or None
        The runner to pass to ``run_tasks``: None for this process. One made here is shut
        down on leaving, whatever went wrong.

    Raises
    ------
    BayespsfInputError
        If both ``executor`` and ``workers`` are given, ``executor`` is of another kind, an
        address is not one (no port), or no scheduler answers at the address within
        ``SCHEDULER_TIMEOUT`` seconds.

    See Also
    --------
    run_tasks : runs a function's tasks on the runner.
    """
    runner, owned = _executor(executor, workers)
    try:
        yield runner
    finally:
        if owned:
            runner.shutdown(wait=True, cancel_futures=True)


class _AddressExecutor(cf.Executor):
    """The executor of a Client made from a scheduler address (and closed with it): an
    executor, so that the runner can be passed on as one."""

    def __init__(self, client):
        self.client, self.inner = client, client.get_executor()

    def submit(self, fn, /, *args, **kwargs):
        return self.inner.submit(fn, *args, **kwargs)

    def shutdown(self, wait=True, cancel_futures=False):
        self.inner.shutdown(wait=wait)
        self.client.close()


def run_tasks[T, R](
    function: Callable[[T], R], tasks: Iterable[T], runner: cf.Executor | None
) -> Iterator[R]:
    """``function`` over ``tasks``: in this process, or on ``runner`` as they finish.

    Parameters
    ----------
    function : callable
        One task to its result (picklable, with its tasks and results, for a process pool
        or Dask).
    tasks : iterable
        The tasks.
    runner : concurrent.futures.Executor or None
        From ``task_runner``; None runs the tasks here, in order and lazily.

    Returns
    -------
    iterator
        The results: in the order of ``tasks`` in this process, in the order they finish
        on a runner (every task is submitted at once).

    See Also
    --------
    task_runner : the runner.
    """
    if runner is None:
        return map(function, tasks)
    futures = [runner.submit(function, task) for task in tasks]
    return (f.result() for f in cf.as_completed(futures))


def run_in_order[T, R](
    function: Callable[[T], R],
    tasks: Iterable[T],
    runner: cf.Executor | None,
    ahead: int | None = None,
) -> Iterator[R]:
    """``function`` over ``tasks``, the results in the tasks' order, a few tasks sent ahead.

    Parameters
    ----------
    function : callable
        As ``run_tasks``.
    tasks : iterable
        The tasks, read lazily (blocks of a movie: memory holds ``ahead`` of them).
    runner : concurrent.futures.Executor or None
        From ``task_runner``; None runs each task here when its result is asked for.
    ahead : int, optional
        Tasks sent and not yet returned, at most; default twice the runner's
        ``parallelism``, so that each worker has its next task waiting.

    Returns
    -------
    iterator
        The results, in the order of ``tasks``.

    See Also
    --------
    run_tasks : the results as they finish, every task sent at once.
    """
    if runner is None:
        yield from map(function, tasks)
        return
    ahead = 2 * parallelism(runner) if ahead is None else ahead
    pending = deque()
    for task in tasks:
        pending.append(runner.submit(function, task))
        if len(pending) >= ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


__all__ = [
    "SCHEDULER_TIMEOUT",
    "dask_settings",
    "local_executor",
    "parallelism",
    "run_in_order",
    "run_tasks",
    "task_runner",
    "worker_start",
]
