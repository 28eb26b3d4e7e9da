"""Posteriors for a stack of ROIs: in parallel, reproducible, resumable.

``sample_many`` gives the posterior of every ROI of a stack: by default (``method="auto"``)
through the batched engine (``bayespsf.stack_posterior``: a stack MLE, then Laplace or
importance-sampled posteriors for many ROIs per vectorised call), with an emcee chain
(``bayespsf.sample_posterior``) only for the ROIs whose diagnostics need one; on local
processes (the default), in this process (``workers=1``), or on any
``concurrent.futures.Executor``, including a Dask ``distributed`` cluster (pass a ``Client``, its
``get_executor()``, or a scheduler address). Molecule ``i`` is sampled with the seed
``molecule_seed`` ``(seed, i)``, so its result depends on ``seed`` and ``i`` only, never on
the number of workers or the order in which they finish.

The store (a folder) holds one self-describing result file per finished molecule
(``molecule-000123.nc``, written atomically: a killed run leaves no half-written file), the run's
``manifest.json`` (what the store was made for: a rerun with other data or settings is refused
by name), and ``summary.csv``, one row per molecule: per parameter the posterior mean, SD,
quantiles (the central 50/68/90/95% intervals), ESS, tau, and, when the truth is given, the
truth and its rank among ``RANK_DRAWS`` near-independent posterior draws (the statistic of
simulation-based calibration, Talts et al., arXiv:1804.06788). Each row is also stored in its
molecule's file, so the table is rebuilt from the files when a run resumes.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import inspect
import json
import multiprocessing
import os
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf._checks import real_array
from bayespsf._progress import progress_bar
from bayespsf._threads import one_blas_thread
from bayespsf.errors import BayespsfInputError
from bayespsf.model import Model
from bayespsf.posterior_rows import (  # noqa: F401  (public in bayespsf.batch since issue 5)
    QUANTILES,
    RANK_DRAWS,
    central_interval,
    coverage,
    draws_row,
    molecule_row,
    quantile_column,
)

SAMPLER_OPTIONS = ("ess", "walkers", "max_steps", "moves", "method", "max_seconds")
CHUNK = 256  # most ROIs per task of the batched methods (auto, laplace, importance)
MIN_CHUNK = 16  # fewest ROIs per task when a stack is split to keep every worker busy
SCHEDULER_TIMEOUT = 10.0  # seconds to reach a Dask scheduler before the address is called wrong


def chunk_count(n: int, parallel: int, ess: float) -> int:
    """How many tasks ``n`` ROIs are split into for the batched methods: enough for each of
    the ``parallel`` workers to get one (chunks of at least ``MIN_CHUNK`` ROIs), of at most
    ``CHUNK`` ROIs at the default ESS of 400 and proportionally fewer above it (a chunk holds
    about ``50 ess`` draws of six parameters per ROI: 256 ROIs at ESS 20 000 would be ~1.6 GB).
    A ROI's result does not depend on its chunk."""
    largest = max(2, min(CHUNK, int(CHUNK * 400.0 / ess)))
    return max(-(-n // largest), min(parallel, -(-n // MIN_CHUNK)), 1)


def _parallelism(runner) -> int:
    """The number of tasks ``runner`` runs at once (1 in this process)."""
    if runner is None:
        return 1
    client = getattr(runner, "client", None) or getattr(runner, "_client", None)  # Dask's
    if client is not None and hasattr(client, "scheduler_info"):
        return max(1, len(client.scheduler_info().get("workers", {})))
    return int(getattr(runner, "_max_workers", None) or os.cpu_count() or 1)


def molecule_seed(seed: int, index: int) -> int:
    """The seed of molecule ``index`` in a run seeded with ``seed`` (NumPy ``SeedSequence``
    of the pair, so nearby seeds and indices give unrelated streams)."""
    state = np.random.SeedSequence([int(seed), int(index)]).generate_state(2, np.uint32)
    return int(state[0]) << 32 | int(state[1])


# --------------------------------------------------------------------------------- workers


def _sample_one(task):
    """Worker side: one molecule's posterior and its summary row (picklable in and out)."""
    from bayespsf.sampling import sample_posterior

    index, counts, model, seed, truth, scene, options, verdict, check = task
    # verdict: the method asked for and why the batched pass left this ROI to the chain, and
    # the batched pass's model check of it
    verdict = dict(verdict or {})
    checked = verdict.pop("check", None)
    started = time.perf_counter()
    try:
        post = sample_posterior(counts, model, seed=seed, truth=truth, scene=scene,
                                progress=False, **options)  # fmt: skip
    except BayespsfInputError as error:  # e.g. a ROI outside the likelihood tier's support
        return index, None, _outcome_row(index, seed, "failed", str(error))
    info = dict(post.info, **verdict, seconds=time.perf_counter() - started)  # the posterior's
    if check and checked is None:
        checked = _model_checks(counts[None], model, [seed], check)[0]
    post.tree.attrs["sampler"] = json.dumps(info)
    row = molecule_row(post, index, seed) | (checked or {})
    post.tree.attrs["summary_row"] = json.dumps(row)
    return index, post, row


def _check_kind(check) -> str | bool:
    """``sample_many``'s ``check`` as False or the name of the discrepancy to test with."""
    from bayespsf.model_check import check_discrepancy

    if isinstance(check, bool | np.bool_):
        return "likelihood" if check else False
    return check_discrepancy("check (True, False or a discrepancy)", check)


def _model_checks(stack, model, seeds, discrepancy: str, fits=None) -> list[dict]:
    """The parametric-bootstrap goodness-of-fit test of each ROI (``bayespsf.model_check``),
    its replicates drawn from the ROI's own seed: ``gof_p``, ``gof_discrepancy``,
    ``gof_replicates`` per ROI."""
    from bayespsf.model_check import bootstrap_check

    table = bootstrap_check(stack, model, seed=[int(s) for s in seeds], fits=fits,
                            discrepancy=discrepancy)  # fmt: skip
    return [{"gof_p": float(p), "gof_discrepancy": float(t), "gof_replicates": int(k)}
            for p, t, k in table[["gof_p", "gof_discrepancy", "gof_replicates"]].itertuples(
                index=False)]  # fmt: skip


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


def local_executor(workers: int | None = None) -> cf.ProcessPoolExecutor:
    """A pool of local worker processes (default: one per core) to pass to several
    ``sample_many`` runs, so that workers and their cached EMCCD tables are reused."""
    workers = os.cpu_count() if workers is None else int(workers)
    if workers < 1:
        raise BayespsfInputError(f"workers must be >= 1, got {workers!r}")
    # fork is fastest and needs no __main__ guard, but is unsafe once threads run (a Dask
    # client, a progress monitor): then forkserver, which re-imports the main module
    method = "fork" if threading.active_count() == 1 else "forkserver"
    context = multiprocessing.get_context(method)
    # a forkserver's workers are its children: they die with it, and it ends with this process
    parent = os.getpid() if method == "fork" else None
    return cf.ProcessPoolExecutor(
        workers, mp_context=context, initializer=_die_with_parent_of, initargs=(parent,)
    )


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
def task_runner(executor, workers):
    """What runs a function's tasks (``_executor``: None for this process, local processes, or
    a Dask executor), shut down on leaving when it was made here, whatever went wrong."""
    runner, owned = _executor(executor, workers)
    try:
        yield runner
    finally:
        if owned:
            runner.shutdown(wait=True, cancel_futures=True)


class _AddressExecutor:
    """The executor of a Client that sample_many made from a scheduler address (and closes)."""

    def __init__(self, client):
        self.client, self.inner = client, client.get_executor()

    def submit(self, fn, *args):
        return self.inner.submit(fn, *args)

    def shutdown(self, wait=True, cancel_futures=False):
        self.inner.shutdown(wait=wait)
        self.client.close()


# ----------------------------------------------------------------------------------- store


class Store:
    """A result folder: manifest, one NetCDF file per molecule, summary.csv."""

    def __init__(self, path):
        self.path = Path(path)
        self._lock = None

    def lock(self) -> None:
        """Hold the store's lock for this run (``fcntl.flock``, released when the run ends or
        its process dies): a second run on the same store is refused at once, naming the
        process that holds it, instead of doing all the work again beside the first."""
        import fcntl

        self.path.mkdir(parents=True, exist_ok=True)
        handle = (self.path / ".lock").open("a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise BayespsfInputError(
                f"store {self.path} is in use by process {holder}; wait for that run to end, "
                "or use another store folder"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self._lock = handle

    def unlock(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def molecule_path(self, index: int) -> Path:
        return self.path / f"molecule-{index:06d}.nc"

    def open(self, manifest: dict) -> None:
        """Create the store, or check that an existing one was made for this run."""
        self.path.mkdir(parents=True, exist_ok=True)
        file = self.path / "manifest.json"
        if file.exists():
            old = json.loads(file.read_text())
            keys = [*manifest, *(k for k in old if k not in manifest)]  # either side's
            differ = [k for k in keys if old.get(k) != manifest.get(k)]
            if differ:
                raise BayespsfInputError(
                    f"store {self.path} was made for another run: {', '.join(differ)} differ "
                    "(use a new store folder, or delete this one)"
                )
        else:
            _atomic_write_text(file, json.dumps(manifest, indent=1))

    def finished(self, n: int) -> dict[int, dict]:
        """Summary rows of the molecules already in the store (read from the files' attributes,
        without loading their draws)."""
        import xarray as xr

        rows = {}
        for index in range(n):
            path = self.molecule_path(index)
            if path.exists():
                tree = xr.open_datatree(path)
                try:
                    rows[index] = json.loads(tree.attrs["summary_row"])
                finally:
                    tree.close()
        return rows

    def write(self, index: int, posterior) -> None:
        path = self.molecule_path(index)
        partial = path.with_suffix(".nc.partial")
        posterior.save(partial)
        os.replace(partial, path)

    def write_summary(self, table: pd.DataFrame) -> None:
        partial = self.path / "summary.csv.partial"
        table.to_csv(partial, index=False)
        os.replace(partial, self.path / "summary.csv")


def _atomic_write_text(path: Path, text: str) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    os.replace(partial, path)


def _resolved_sampler_settings(options: dict) -> dict:
    """Every sampler setting a run uses, defaults included, so that a store made under other
    defaults (another bayespsf version) is refused rather than resumed with mixed results."""
    from bayespsf.sampler_settings import Settings
    from bayespsf.sampling import sample_posterior

    defaults = inspect.signature(sample_posterior).parameters
    resolved = {k: options.get(k, defaults[k].default) for k in SAMPLER_OPTIONS}
    return {**resolved, "chunk": Settings.chunk, "min_taus": Settings.min_taus}


def _manifest(counts, model, seed, options, truths, check: str | bool) -> dict:
    digest = hashlib.sha256(np.ascontiguousarray(counts, dtype=np.float64).tobytes())
    if truths is not None:
        digest.update(np.ascontiguousarray(truths, dtype=np.float64).tobytes())
    return {
        "bayespsf": "sample_many store",
        "molecules": int(counts.shape[0]),
        "seed": int(seed),
        "sampler": _resolved_sampler_settings(options),
        "model": repr(model),
        "prior": model.prior,
        "clock-induced charge": model.clock_induced_charge,
        "data sha256": digest.hexdigest(),
    } | ({"model check": "parametric bootstrap (bayespsf.model_check)"
           + ("" if check == "likelihood" else f", discrepancy {check}")}
          if check else {})  # fmt: skip


# ------------------------------------------------------------------------------- the run


def sample_many(
    counts,
    model: Model,
    seed: int = 0,
    executor=None,
    workers: int | None = None,
    store=None,
    truths=None,
    scene=None,
    progress: bool | None = None,
    check: bool | str = False,
    **options,
) -> pd.DataFrame:
    """Sample the posterior of every ROI in ``counts``; return the summary table.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU. Every ROI is validated before any sampling starts.
    model : Model
    seed : int
        Molecule ``i`` uses ``molecule_seed`` ``(seed, i)``: results do not depend on the
        number of workers.
    executor : optional
        ``None`` (local processes), a ``concurrent.futures.Executor``, a Dask ``Client`` or a
        scheduler address such as ``"tcp://10.0.0.5:8786"``.
    workers : int, optional
        Local processes when ``executor`` is None (default: all cores; 1 runs in this process).
    store : path, optional
        Result folder (see the module docstring). A rerun with the same store resumes: finished
        molecules are read back, not sampled again.
    truths : array_like, shape (n, 6), optional
        True parameters (simulations): adds truth and SBC-rank columns.
    scene : Scene, optional
        Kept in each result file.
    progress : bool, optional
        A progress bar on stderr (default: when stderr is a terminal).
    check : bool or str
        Also test whether the model can have made each ROI: the parametric-bootstrap
        goodness-of-fit test of ``bayespsf.model_check`` at the ROI's maximum-likelihood fit
        (49 refitted replicates drawn from the ROI's own seed; it costs about as much again as
        the batched posteriors). Adds ``gof_p``, ``gof_discrepancy`` and ``gof_replicates`` to
        each row, stored with the posterior in its file. True uses the default discrepancy
        (``"likelihood"``); a name of ``bayespsf.model_check.DISCREPANCIES`` chooses one
        (``"pearson"`` is calibrated at a low background, where the default is conservative).
    **options
        ``ess``, ``walkers``, ``max_steps``, ``moves``, ``method``, ``max_seconds`` of
        ``sample_posterior``. ``method`` defaults to ``"auto"`` here (``sample_posterior``'s
        default is the chain): the stack is fitted and sampled in chunks of ``CHUNK`` ROIs by
        the batched engine (``bayespsf.stack_posterior``: the Laplace where its pilot passes,
        else importance sampling where its k-hat passes), and only the ROIs where both fail
        get an emcee chain. ``method="mcmc"`` runs the chain for every ROI.

    Returns
    -------
    pandas.DataFrame
        One row per molecule, sorted by molecule (see ``molecule_row``); also written to
        ``store/summary.csv``. ``method`` says what made each posterior (``laplace``,
        ``importance``, ``mcmc``) and ``why`` why that method was chosen. ``status`` says
        what happened to each: ``converged``, ``not converged`` (``message``: the sampler's
        diagnosis), ``refused`` (the model cannot analyse that ROI: ``Model.roi_problems``) or
        ``failed`` (its sampling raised a named input error); one bad ROI never stops the
        stack. A store is locked while a run uses
        it: a second run on it is refused at once.
    """
    unknown = sorted(set(options) - set(SAMPLER_OPTIONS))
    if unknown:
        raise BayespsfInputError(
            f"unknown sampler option(s) {unknown}; sample_many takes {list(SAMPLER_OPTIONS)}"
        )
    from bayespsf.sampler_settings import check_settings

    check = _check_kind(check)
    options.setdefault("method", "auto")
    settings = check_settings(seed=seed, **options)  # a bad setting fails here, not in workers
    stack = model._check_shape(counts)
    if stack.ndim != 3:
        raise BayespsfInputError(f"counts must be a stack (n, roi, roi), got shape {stack.shape}")
    n = stack.shape[0]
    if n == 0:
        raise BayespsfInputError("counts: the stack has no ROIs")
    if truths is not None:
        truths = real_array("truths", truths)
        if truths.shape != (n, 6):
            raise BayespsfInputError(f"truths must have shape ({n}, 6), got {truths.shape}")
    problems = model.roi_problems(stack)
    rows: dict[int, dict] = {}
    saver = None
    if store is not None:
        saver = Store(store)
        saver.lock()
    try:
        if saver is not None:
            saver.open(_manifest(stack, model, seed, options, truths, check))
            rows = saver.finished(n)
        for i, problem in enumerate(problems):
            if problem is not None:
                rows[i] = _outcome_row(i, molecule_seed(seed, i), "refused", problem)
        todo = [i for i in range(n) if i not in rows]
        with (progress_bar(n, progress, initial=len(rows), unit="molecule") as bar,
              task_runner(executor, workers) as runner):  # fmt: skip
            if settings.method != "mcmc":  # the batched methods; the chain where they fail
                parts = chunk_count(len(todo), _parallelism(runner), settings.ess)
                chunks = (
                    (chunk, stack[chunk], model, [molecule_seed(seed, i) for i in chunk],
                     None if truths is None else truths[chunk], settings, scene,
                     None if saver is None else saver.path, check)
                    for chunk in np.array_split(todo, parts)
                    if len(chunk)
                )  # fmt: skip
                verdicts = _run_chunks(chunks, runner, rows, bar)
                todo = sorted(verdicts)
                options = {**options, "method": "mcmc"}
            else:
                verdicts = {}
            tasks = (
                (i, stack[i], model, molecule_seed(seed, i),
                 None if truths is None else truths[i], scene, options, verdicts.get(i), check)
                for i in todo
            )  # fmt: skip
            _run(tasks, runner, saver, rows, bar)
        table = pd.DataFrame([rows[i] for i in sorted(rows)])
        table["photon_unit"] = model.photon_unit_label
        if saver is not None:
            saver.write_summary(table)
    finally:
        if saver is not None:
            saver.unlock()
    return table


def _results(function, tasks, runner):
    """``function`` over ``tasks``: in this process, or on ``runner`` as they finish."""
    if runner is None:
        return map(function, tasks)
    futures = [runner.submit(function, task) for task in tasks]
    return (f.result() for f in cf.as_completed(futures))


def _run(tasks, runner, saver, rows, bar) -> None:
    """Sample the tasks, write each result as it comes, fill ``rows``."""
    for index, post, row in _results(_sample_one, tasks, runner):
        if saver is not None and post is not None:
            saver.write(index, post)
        rows[index] = row
        bar.update(1)


def _run_chunks(chunks, runner, rows, bar) -> dict[int, dict]:
    """The batched methods chunk by chunk (``_posteriors_of_chunk``, which also write each
    posterior to the store if there is one); fills ``rows`` and returns, for each ROI that
    needs the chain, the method asked for and why the batched pass left it."""
    chain = {}
    for results in _results(_posteriors_of_chunk, chunks, runner):
        for index, row, verdict in results:
            if row is None:
                chain[index] = verdict
            else:
                rows[index] = row
        bar.update(len(results) - sum(row is None for _, row, _ in results))
    return chain


@one_blas_thread
def _posteriors_of_chunk(task):
    """Worker side: ``fit_mle`` and the chain-free posteriors (``bayespsf.stack_posterior``)
    of a chunk of ROIs, each written to the store (a path, or None) as it is made; per ROI
    ``(index, summary row, None)``, or ``(index, None, verdict)`` if the chain is needed
    (picklable in and out)."""
    from bayespsf.estimators import fit_mle
    from bayespsf.stack_posterior import as_posterior, cheap_posteriors

    indices, stack, model, seeds, truths, settings, scene, store, check = task
    started = time.perf_counter()
    fits = fit_mle(stack, model)
    outcomes = cheap_posteriors(stack, model, fits, seeds, settings)
    seconds = (time.perf_counter() - started) / len(indices)
    checks = _model_checks(stack, model, seeds, check, fits) if check else [{}] * len(indices)
    results = []
    for k, (index, outcome) in enumerate(zip(indices, outcomes, strict=True)):
        if outcome["draws"] is None:
            verdict = {"requested": settings.method, "why": outcome["info"]["why"]}
            results.append((int(index), None, verdict | ({"check": checks[k]} if check else {})))
            continue
        outcome = {**outcome, "info": dict(outcome["info"], seconds=seconds)}
        truth = None if truths is None else truths[k]
        row = draws_row(outcome["draws"], int(index), seeds[k], outcome["info"], truth)
        row |= checks[k]
        if store is not None:
            post = as_posterior(outcome, stack[k], model, truth, scene)
            post.tree.attrs["summary_row"] = json.dumps(row)
            Store(store).write(int(index), post)
        results.append((int(index), row, None))
    return results


def _outcome_row(index: int, seed: int, status: str, message: str) -> dict:
    """The summary row of a molecule without a posterior: its status and the reason."""
    return {"molecule": int(index), "seed": int(seed), "converged": False, "status": status,
            "message": message}  # fmt: skip


__all__ = ["coverage", "local_executor", "molecule_row", "molecule_seed", "sample_many"]
