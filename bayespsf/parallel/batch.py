"""Posteriors for a stack of ROIs: in parallel, reproducible, resumable.

``sample_many`` gives the posterior of every ROI of a stack: by default (``method="auto"``)
through the batched engine (``bayespsf.inference.batched``: a stack MLE, then Laplace or
importance-sampled posteriors for many ROIs per vectorised call), with an emcee chain
(``bayespsf.sample_posterior``) only for the ROIs whose diagnostics need one; on local
processes (the default), in this process (``workers=1``), or on any
``concurrent.futures.Executor``, including a Dask ``distributed`` cluster (pass a ``Client``, its
``get_executor()``, or a scheduler address). Molecule ``i`` is sampled with the seed
``molecule_seed`` ``(seed, i)``, so its result depends on ``seed`` and ``i`` only, never on
the number of workers or the order in which they finish.

The store (a folder, ``Store``) holds the finished molecules' posteriors, the molecules of one
task to a file (``posteriors-000000-000255.nc``, written atomically: a killed run leaves no
half-written file; ``Store.posterior(i)`` reads molecule ``i`` back), the run's
``manifest.json`` (what the store was made for: a rerun with other data or settings is refused
by name), and ``summary.csv``, one row per molecule: per parameter the posterior mean, SD,
quantiles (the central 50/68/90/95% intervals), ESS, tau, and, when the truth is given, the
truth and its rank among ``RANK_DRAWS`` near-independent posterior draws (the statistic of
simulation-based calibration, Talts et al., arXiv:1804.06788). Each row is also stored with its
molecule's posterior, so the table is rebuilt from the files when a run resumes.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import time
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from bayespsf._runtime import one_blas_thread, progress_bar
from bayespsf._validate import real_array
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.backends import check_backend
from bayespsf.inference.gof import check_option, check_rows
from bayespsf.inference.summary import concat_tables, draws_rows, molecule_row
from bayespsf.model import Model
from bayespsf.parallel.device import device_posteriors
from bayespsf.parallel.executors import parallelism, run_tasks, task_runner
from bayespsf.parallel.seeds import molecule_seed, molecule_seeds
from bayespsf.parallel.store import NO_DRAWS, Store
from bayespsf.scene import Scene

if TYPE_CHECKING:
    from distributed import Client

SAMPLER_OPTIONS = ("ess", "walkers", "max_steps", "moves", "method", "max_seconds")
CHUNK = 256  # most ROIs per task of the batched methods (auto, laplace, importance)
MIN_CHUNK = 16  # fewest ROIs per task when a stack is split to keep every worker busy


def chunk_count(n: int, parallel: int, ess: float) -> int:
    """How many tasks ``n`` ROIs are split into for the batched methods: enough for each of
    the ``parallel`` workers to get one (chunks of at least ``MIN_CHUNK`` ROIs), of at most
    ``CHUNK`` ROIs at the default ESS of 400 and proportionally fewer above it (a chunk holds
    about ``50 ess`` draws of six parameters per ROI: 256 ROIs at ESS 20 000 would be ~1.6 GB).
    Where there are more chunks than workers, their number is rounded up to a multiple of
    ``parallel`` while the chunks keep at least ``MIN_CHUNK`` ROIs, so that every worker gets
    as many equal chunks (125 chunks on 16 workers would leave 3 idle for the last chunk's
    time; 128 do not). A ROI's result does not depend on its chunk."""
    largest = max(2, min(CHUNK, int(CHUNK * 400.0 / ess)))
    parts = max(-(-n // largest), min(parallel, -(-n // MIN_CHUNK)), 1)
    if parts > parallel > 1:
        parts = max(min(-(-parts // parallel) * parallel, n // MIN_CHUNK), parts)
    return parts


def _sample_one(task):
    """Worker side: one molecule's posterior and its summary row (picklable in and out)."""
    from bayespsf.inference import sample_posterior

    index, counts, model, seed, truth, scene, options, verdict, check = task
    # verdict: the method asked for and why the batched pass left this ROI to the chain, and
    # the batched pass's model check of it
    verdict = dict(verdict or {})
    checked = verdict.pop("check", None)
    started = time.perf_counter()
    try:
        post = sample_posterior(
            counts, model, seed=seed, truth=truth, scene=scene, progress=False, **options
        )
    except BayespsfInputError as error:  # e.g. a ROI outside the likelihood tier's support
        row = _outcome_row(index, seed, "failed", str(error))  # and why the chain was tried
        return index, None, row | ({"why": verdict["why"]} if "why" in verdict else {})
    if options.get("method") == "importance" and "why" in verdict:  # the device left it
        verdict["why"] = f"{verdict['why']}; on the host: {post.info['why']}"
    info = dict(post.info, **verdict, seconds=time.perf_counter() - started)  # the posterior's
    if check and checked is None:
        checked = check_rows(counts[None], model, [seed], check)[0]
    post.tree.attrs["sampler"] = json.dumps(info)
    row = molecule_row(post, index, seed) | (checked or {})
    post.tree.attrs["summary_row"] = json.dumps(row)
    return index, post, row


def _resolved_sampler_settings(options: dict) -> dict:
    """Every sampler setting a run uses, defaults included, so that a store made under other
    defaults (another bayespsf version) is refused rather than resumed with mixed results."""
    from bayespsf.inference import Settings, sample_posterior

    defaults = inspect.signature(sample_posterior).parameters
    resolved = {k: options.get(k, defaults[k].default) for k in SAMPLER_OPTIONS}
    return {**resolved, "chunk": Settings.chunk, "min_taus": Settings.min_taus}


def _manifest(counts, model, seed, options, truths, check: str | bool, backend: str) -> dict:
    from bayespsf.inference.gof import describe_check

    digest = hashlib.sha256(np.ascontiguousarray(counts, dtype=np.float64).tobytes())
    if truths is not None:
        digest.update(np.ascontiguousarray(truths, dtype=np.float64).tobytes())
    return (
        {
            "bayespsf": "sample_many store",
            "molecules": int(counts.shape[0]),
            "seed": int(seed),
            "sampler": _resolved_sampler_settings(options),
            "model": repr(model),
            "prior": model.prior,
            "clock-induced charge": model.clock_induced_charge,
            "data sha256": digest.hexdigest(),
        }
        | ({"backend": backend} if backend != "numpy" else {})
        | ({"model check": describe_check(check)} if check else {})
    )


# ------------------------------------------------------------------------------- the run


def sample_many(
    counts: ArrayLike,
    model: Model,
    seed: int = 0,
    executor: Executor | Client | str | None = None,
    workers: int | None = None,
    store: str | os.PathLike | None = None,
    truths: ArrayLike | None = None,
    scene: Scene | None = None,
    progress: bool | None = None,
    check: bool | str = False,
    backend: str = "numpy",
    keep_draws: bool = True,
    **options: Any,
) -> pd.DataFrame:
    """Sample the posterior of every ROI in ``counts``; return the summary table.

    Parameters
    ----------
    counts : array_like, shape (n, roi, roi)
        ROIs in ADU. Every ROI is validated before any sampling starts.
    model : Model
        Geometry, camera law, prior and photon unit.
    seed : int
        Molecule ``i`` uses ``molecule_seed`` ``(seed, i)``: results do not depend on the
        number of workers.
    executor : optional
        ``None`` (local processes), a ``concurrent.futures.Executor``, a Dask ``Client`` or a
        scheduler address such as ``"tcp://10.0.0.5:8786"``.
    workers : int, optional
        Local processes when ``executor`` is None (default: all cores; 1 runs in this process).
    store : str or path-like, optional
        Result folder (see the module docstring). A rerun with the same store resumes: finished
        molecules are read back, not sampled again.
    keep_draws : bool, default True
        Whether the store's files hold each molecule's draws (~27 kB per 13 x 13 ROI sampled
        by importance) or only its summary row, sampler record and counts (~5.4 kB; for
        datasets of 10^6 ROIs and more; ``Store.posterior`` then refuses). Needs a store.
    truths : array_like, shape (n, 6), optional
        True ``x0 y0 s_x s_y N b`` (simulations): adds truth and SBC-rank columns.
    scene : Scene, optional
        Kept in each result file.
    progress : bool, optional
        A progress bar on stderr (default: when stderr is a terminal).
    check : bool or str
        Also test whether the model can have made each ROI: the parametric-bootstrap
        goodness-of-fit test of ``bayespsf.inference.gof`` at the ROI's maximum-likelihood fit
        (up to 49 refitted replicates drawn from the ROI's own seed, stopped once 10 are as
        discrepant; on emccd-typical's ROIs at N = 1 000 the run takes about four times as
        long). Adds ``gof_p``, ``gof_discrepancy`` and ``gof_replicates`` to
        each row, stored with the posterior in its file. True uses the default discrepancy
        (``"likelihood"``); a name of ``bayespsf.inference.gof.DISCREPANCIES`` chooses one
        (``"pearson"`` is calibrated at a low background, where the default is conservative).
    backend : {"numpy", "jax"}
        Where the batched methods run: ``"numpy"`` in the worker processes, ``"jax"`` in this
        process on whatever device JAX finds (a GPU where one is installed;
        ``bayespsf.parallel.device``), Photon and EMCCD cameras. The chain, for the ROIs whose
        diagnostics need it, runs on the CPU workers with either.
    **options
        ``ess``, ``walkers``, ``max_steps``, ``moves``, ``method``, ``max_seconds`` of
        ``sample_posterior``. ``method`` defaults to ``"auto"`` here (``sample_posterior``'s
        default is the chain): the stack is fitted and sampled in chunks of ``CHUNK`` ROIs by
        the batched engine (``bayespsf.inference.batched``: the Laplace where its pilot passes,
        else importance sampling where its k-hat passes), and only the ROIs where both fail
        get an emcee chain. ``method="mcmc"`` runs the chain for every ROI.

    Returns
    -------
    pandas.DataFrame
        One row per molecule, sorted by molecule (``bayespsf.inference.summary.draws_row``);
        also written to ``store/summary.csv``. Columns: ``molecule``, ``seed``,
        ``converged``, ``status``, ``message``, ``method``, ``why``, ``steps``, ``draws``,
        ``acceptance``, ``seconds``; per parameter ``<p>`` of ``x0 y0 s_x s_y N b`` (nm,
        photons, photons per pixel) ``<p>_mean``, ``<p>_sd``, the quantiles ``<p>_q0025``,
        ``_q0050``, ``_q0160``, ``_q0250``, ``_q0500``, ``_q0750``, ``_q0840``, ``_q0950``,
        ``_q0975`` (per mille), ``<p>_tau``, ``<p>_ess``, and with ``truths`` ``<p>_truth``
        and ``<p>_rank`` (0-99; NaN where fewer than 99 near-independent draws); with
        ``check`` ``gof_p``, ``gof_discrepancy``, ``gof_replicates``; last ``photon_unit``.
        ``method`` says what made each posterior (``laplace``, ``importance``, ``mcmc``) and
        ``why`` why that method was chosen. ``status`` says what happened to each:
        ``converged``, ``not converged`` (``message``: the sampler's diagnosis, else
        ``why``), ``refused`` (the model cannot analyse that ROI: ``Model.roi_problems``) or
        ``failed`` (its sampling raised a named input error); one bad ROI never stops the
        stack, and its posterior columns are NaN.

    Raises
    ------
    BayespsfInputError
        Before any sampling: an unknown or out-of-range sampler option, ``seed`` or
        ``check``, ``walkers`` so many that a chain cannot be held in memory, with
        ``method="mcmc"`` a chain that may run for hours per ROI without ``max_seconds``
        (``check_chain_work``; under ``auto`` a ROI left to such a chain is ``failed``, with
        that message), counts that are not a real stack ``(n >= 1, roi, roi)``, ``truths`` not
        ``(n, 6)``, both ``executor`` and ``workers``, an unknown executor or an address no
        scheduler answers at, a store made for another run, or one in use by another run
        (a store is locked while a run uses it).

    See Also
    --------
    bayespsf.sample_posterior : the posterior of one ROI.
    bayespsf.inference.summary.coverage : interval coverage over this table's rows.
    Store : the result folder.
    molecule_seed : the seed of each molecule.

    Notes
    -----
    The seeds, the store's files and the summary's SBC ranks (Talts et al.,
    arXiv:1804.06788) are described in the module docstring.

    Examples
    --------
    >>> import bayespsf
    >>> scene = bayespsf.load_scene("paper-fig3")
    >>> counts, truth = bayespsf.simulate(scene, 2, seed=1)
    >>> model = bayespsf.Model.from_scene(scene)
    >>> table = bayespsf.sample_many(counts, model, seed=1, workers=1, truths=truth)
    >>> table[["molecule", "method", "status"]]
       molecule      method     status
    0         0  importance  converged
    1         1  importance  converged
    >>> table[["x0_mean", "x0_sd", "x0_q0025", "x0_q0975", "x0_truth"]].notna().all().all()
    np.True_
    """
    unknown = sorted(set(options) - set(SAMPLER_OPTIONS))
    if unknown:
        raise BayespsfInputError(
            f"unknown sampler option(s) {unknown}; sample_many takes {list(SAMPLER_OPTIONS)}"
        )
    from bayespsf.inference.settings import (
        check_chain_work,
        check_model,
        check_settings,
        check_walkers_fit,
    )

    check_model(model)
    check = check_option(check)
    check_backend(backend, model)  # an unsupported camera law is named before any work
    options.setdefault("method", "auto")
    settings = check_settings(seed=seed, **options)  # a bad setting fails here, not in workers
    check_walkers_fit(settings.walkers, model.roi)  # the ROIs left to the chain need them
    if settings.method == "mcmc":  # every ROI runs a chain (else only those left to it)
        check_chain_work(settings, model.roi)
    stack = model.check_shape(counts)
    if stack.ndim != 3:
        raise BayespsfInputError(f"counts must be a stack (n, roi, roi), got shape {stack.shape}")
    n = stack.shape[0]
    if n == 0:
        raise BayespsfInputError("counts: the stack has no ROIs")
    if truths is not None:
        truths = real_array("truths", truths)
        if truths.shape != (n, 6):
            raise BayespsfInputError(f"truths must have shape ({n}, 6), got {truths.shape}")
    if not isinstance(keep_draws, bool | np.bool_) or (store is None and not keep_draws):
        raise BayespsfInputError(
            f"keep_draws must be True or False, and False only with a store; got {keep_draws!r}"
            + ("" if store is not None else " without one")
        )
    problems = model.roi_problems(stack)
    rows: dict[int, dict] = {}
    saver = None
    if store is not None:
        saver = Store(store)
        saver.lock()
    try:
        if saver is not None:
            manifest = _manifest(stack, model, seed, options, truths, check, backend)
            saver.open(manifest | ({} if keep_draws else NO_DRAWS))
            rows = saver.finished(n)
        for i, problem in enumerate(problems):
            if problem is not None:
                rows[i] = _outcome_row(i, molecule_seed(seed, i), "refused", problem)
        todo = [i for i in range(n) if i not in rows]
        with (
            progress_bar(n, progress, initial=len(rows), unit="molecule") as bar,
            task_runner(executor, workers) as runner,
        ):
            made, pieces = None, []  # the chunks' tables (the batched methods)
            if settings.method != "mcmc" and backend == "jax" and todo:
                todo = np.asarray(todo)
                made, verdicts = device_posteriors(
                    todo,
                    stack if len(todo) == n else stack[todo],
                    model,
                    molecule_seeds(seed, todo),
                    None if truths is None else truths[todo],
                    settings,
                    scene,
                    None if saver is None else saver.path,
                    check,
                )
                bar.update(len(made))
                todo = sorted(verdicts)
                # importance sampling, then where it fails the chain, here: the host's runs
                # from a t fitted to the Student-t's draws, which the device has not
                host = "mcmc" if settings.method == "laplace" else "importance"
                options = {**options, "method": host}
            elif settings.method != "mcmc":  # the batched methods; the chain where they fail
                parts = chunk_count(len(todo), parallelism(runner), settings.ess)
                chunks = (
                    (
                        chunk,
                        stack[chunk],
                        model,
                        None if truths is None else truths[chunk],
                        settings,
                        scene,
                        None if saver is None else saver.path,
                        check,
                    )
                    for chunk in np.array_split(todo, parts)
                    if len(chunk)
                )
                verdicts = _run_chunks(chunks, runner, pieces, bar)
                todo = sorted(verdicts)
                options = {**options, "method": "mcmc"}
            else:
                verdicts = {}
            tasks = (
                (
                    i,
                    stack[i],
                    model,
                    molecule_seed(seed, i),
                    None if truths is None else truths[i],
                    scene,
                    options,
                    verdicts.get(i),
                    check,
                )
                for i in todo
            )
            _run(tasks, runner, saver, rows, bar)
            table = _table(pieces + ([] if made is None or not len(made) else [made]), rows)
            table["photon_unit"] = model.photon_unit_label
            if saver is not None:
                saver.write_summary(table, runner)  # its rows formatted on the workers
    finally:
        if saver is not None:
            saver.unlock()
    return table


def _run(tasks, runner, saver, rows, bar) -> None:
    """Sample the tasks, write each result as it comes, fill ``rows``."""
    for index, post, row in run_tasks(_sample_one, tasks, runner):
        if saver is not None and post is not None:
            saver.write_posterior(index, post)
        rows[index] = row
        bar.update(1)


def _run_chunks(chunks, runner, pieces: list, bar) -> dict[int, dict]:
    """The batched methods chunk by chunk (``_posteriors_of_chunk``, which also write each
    posterior to the store if there is one); appends each chunk's table of summary rows to
    ``pieces`` and returns, for each ROI that needs the chain, the method asked for and why
    the batched pass left it."""
    chain = {}
    for table, verdicts in run_tasks(_posteriors_of_chunk, chunks, runner):
        if len(table):
            pieces.append(table)
        chain.update(verdicts)
        bar.update(len(table))
    return chain


def _table(pieces: list[pd.DataFrame], rows: dict[int, dict]) -> pd.DataFrame:
    """The summary table, one row per molecule in molecule order: the chunks' tables
    (``pieces``, each in molecule order) and the single ``rows`` by molecule: the table that
    ``pd.DataFrame`` of every row in molecule order gives. The single rows go into tables of
    rows with the same keys; as every table's rows share their keys, a table's new columns
    come where its first molecule does, in the order ``pd.DataFrame`` names them."""
    alike: dict[tuple, list[dict]] = {}
    for i in sorted(rows):
        alike.setdefault(tuple(rows[i]), []).append(rows[i])
    pieces = sorted(
        [*pieces, *(pd.DataFrame(group) for group in alike.values())],
        key=lambda piece: piece["molecule"].iloc[0],
    )
    table = concat_tables(pieces)  # seeds kept whole where some tables' are uint64
    if table["molecule"].is_monotonic_increasing:  # one piece, or pieces in turn
        return table
    return table.sort_values("molecule", kind="stable", ignore_index=True)


@one_blas_thread
def _posteriors_of_chunk(task):
    """Worker side: the fit (``fit_screened``) and the chain-free posteriors
    (``bayespsf.inference.batched``) of a chunk of ROIs (molecule ``i`` seeded with
    ``molecule_seed(settings.seed, i)``), written to the store (a path, or None) together.
    Returns the table of their summary rows, in molecule order, and for each ROI that needs
    the chain its verdict: the method asked for, why, and its model check (picklable in
    and out; a table, not rows, as the parent takes a table's columns in a fraction of the time
    it takes rows')."""
    from bayespsf.inference import fit_screened
    from bayespsf.inference.batched import cheap_posteriors

    indices, stack, model, truths, settings, scene, store, check = task
    seeds = molecule_seeds(settings.seed, indices).tolist()
    started = time.perf_counter()
    # screened by ``sample_many``; the bound only for the model checks
    fits = fit_screened(stack, model, crlb=bool(check))
    outcomes = cheap_posteriors(stack, model, fits, seeds, settings)
    seconds = (time.perf_counter() - started) / len(indices)
    checks = check_rows(stack, model, seeds, check, fits) if check else [{}] * len(indices)
    made = [k for k, outcome in enumerate(outcomes) if outcome["draws"] is not None]
    infos = {k: dict(outcomes[k]["info"], seconds=seconds) for k in made}
    rows = draws_rows(  # the summary rows of all the chunk's posteriors at once
        [outcomes[k]["draws"] for k in made],
        [int(indices[k]) for k in made],
        [seeds[k] for k in made],
        list(infos.values()),
        None if truths is None else truths[made],
    )
    rows = [row | checks[k] for k, row in zip(made, rows, strict=True)]
    verdicts = {}
    for k, (index, outcome) in enumerate(zip(indices, outcomes, strict=True)):
        if outcome["draws"] is None:
            verdict = {"requested": settings.method, "why": outcome["info"]["why"]}
            verdicts[int(index)] = verdict | ({"check": checks[k]} if check else {})
    if store is not None and made:
        Store(store).write_outcomes(
            [int(indices[k]) for k in made],
            [{**outcomes[k], "info": infos[k]} for k in made],
            stack[made],
            rows,
            model,
            scene,
            None if truths is None else truths[made],
        )
    return pd.DataFrame(rows), verdicts


def _outcome_row(index: int, seed: int, status: str, message: str) -> dict:
    """The summary row of a molecule without a posterior: its status and the reason."""
    return {
        "molecule": int(index),
        "seed": int(seed),
        "converged": False,
        "status": status,
        "message": message,
    }


__all__ = ["chunk_count", "sample_many"]
