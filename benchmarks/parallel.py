"""Parallel throughput: ``sample_many`` on one process, on local worker processes and on a Dask
cluster of as many one-thread workers, for each number of workers asked, and a dataset of 10^5
ROIs on the most workers (targets: two workers >= 1.8x one; on 16 cores, 16 local workers >=
14x one and a 16-worker Dask cluster >= 12x; 10^5 emccd-typical posteriors in <= 10 minutes on
2 cores). Also ``bayespsf analyze --per-frame`` (``localize_frames``: detection, the fits and
the posteriors of every spot of every frame) and ``bayespsf analyze`` (``analyze``: immobile
molecules, from the movie to the selection, the posteriors, each molecule's joint posterior, the
checks and the files) on simulated movies, for each number of local workers. The movies and the
local pools run before the Dask clusters, whose closing leaves threads in this process: after
it, a pool starts its workers from a forkserver, not by the fork of a command-line run (each
table says how its workers started).

Every timing runs on the same ROIs, 2 000 per worker of the largest count (4 000 for 1 and 2
workers, 32 000 up to 16), so that starting a pool counts little and each worker gets many
chunks, as in a dataset. Run it on an otherwise idle machine: a speed-up means nothing when
other jobs share the cores. The table names the machine and the command, and the CPU time
that the calling process spends per ROI while workers run (its own share of the cores).

    python benchmarks/parallel.py                        # 1 and 2 workers; rewrites its section
                                                         # of README.md
    python benchmarks/parallel.py --workers 1,2,4,8,16   # the scaling table on a bigger machine
                                                         # (printed; --publish writes it too)
    python benchmarks/parallel.py --quick                # a small run that prints only (tests)
    python benchmarks/parallel.py --frames 0 --immobile 0  # without the movies
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import machine, publish  # noqa: E402

from bayespsf import load_scene, simulate, simulate_movie  # noqa: E402
from bayespsf.analysis import analyze, localize_frames  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.movie import Rules  # noqa: E402
from bayespsf.parallel import dask_settings, sample_many, worker_start  # noqa: E402


def _cpu() -> float:
    """CPU seconds of this process so far, all its threads (user and system)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _timed(function):
    """``function()``, its seconds, and the CPU seconds this process spent meanwhile (with
    workers elsewhere: the calling process's own work, and a LocalCluster's scheduler)."""
    started, cpu = time.perf_counter(), _cpu()
    out = function()
    return out, time.perf_counter() - started, _cpu() - cpu


def _warm(counts, model) -> int:
    """A Dask worker's imports, compiled kernels and EMCCD tables, made before the timing."""
    sample_many(counts, model, workers=1, progress=False)
    return os.getpid()


def _on_dask(counts, model, workers: int, tuned: bool):
    """``sample_many`` on a ``LocalCluster`` of ``workers`` one-thread workers, each warmed
    first, with its seconds and this process's CPU seconds (``_timed``). ``tuned``:
    ``bayespsf.parallel.dask_settings()`` (docs/scale.md), else Dask's defaults, whose worker
    environment sets ``MALLOC_TRIM_THRESHOLD_=65536``, which makes glibc hand every freed
    working array back to the system."""
    import dask
    from distributed import Client, LocalCluster

    config = dask_settings() if tuned else {}
    saved = os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)  # a nanny leaves it set here
    try:
        with (
            dask.config.set(config),
            # ":0": the dashboard on a free port (None binds 8787, which another cluster, as
            # in the test suite's parallel runs, may hold: a warning, an error under pytest)
            LocalCluster(
                n_workers=workers, threads_per_worker=1, dashboard_address=":0", processes=True
            ) as cluster,
            Client(cluster) as client,
        ):
            client.run(_warm, counts[:4], model)  # every worker, not only the first task's
            return _timed(lambda: sample_many(counts, model, executor=client))
    finally:
        os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        if saved is not None:
            os.environ["MALLOC_TRIM_THRESHOLD_"] = saved


def parallel(n: int, dataset: int, workers=(1, 2), dask: bool = True) -> pd.DataFrame:
    """``sample_many(method="auto")`` on ``n`` emccd-typical ROIs (N = 1000) in this process,
    then for each number ``w`` > 1 of ``workers`` on ``w`` local worker processes, then a
    ``dataset`` of ROIs (0: none) on the most local workers, then for each ``w`` > 1 on a Dask
    ``LocalCluster`` of ``w`` one-thread workers, twice: with Dask's defaults and with
    ``dask_settings()`` (``_on_dask``). The clusters run last: a closed
    cluster leaves threads in this process, after which local pools start their workers from
    a forkserver, not by the fork that a command-line run uses (``worker_start``)."""
    scene = load_scene("emccd-typical")
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, max(n, dataset), seed=3)
    sample_many(counts[:4], model, workers=1)  # warm-up
    rows = []

    def row(how, w, start, result, seconds, cpu, reference=None):
        count = len(result)
        same = (
            np.nan
            if reference is None
            else bool(
                np.array_equal(result["s_x_mean"].to_numpy(), reference["s_x_mean"].to_numpy())
            )
        )
        rows.append(
            {
                "how": how,
                "workers": w,
                "workers start by": start,
                "ROIs": count,
                "seconds": seconds,
                "ROIs/s": count / seconds,
                "same posteriors as one process": same,
                "calling process CPU per ROI (µs)": 1e6 * cpu / count,
            }
        )

    one, *times = _timed(lambda: sample_many(counts[:n], model, workers=1))
    row("one process", 1, "", one, *times)
    for w in (w for w in workers if w > 1):
        start = worker_start()
        local, *times = _timed(lambda w=w: sample_many(counts[:n], model, workers=w))
        row("local worker processes", w, start, local, *times, one)
    if dataset:
        most, start = max(workers), worker_start()
        data, *times = _timed(lambda: sample_many(counts[:dataset], model, workers=most))
        row("local worker processes (dataset)", most, start, data, *times)
    for w in (w for w in workers if w > 1 and dask):
        for tuned in (False, True):
            result, *times = _on_dask(counts[:n], model, w, tuned)
            how = "Dask LocalCluster, 1 thread per worker" + (", tuned" if tuned else "")
            row(how, w, "spawn (Dask nanny)", result, *times, one)
    table = pd.DataFrame(rows)
    table["speed-up vs one process"] = table["ROIs/s"] / table["ROIs/s"].iloc[0]
    table["per worker"] = table["speed-up vs one process"] / table["workers"]
    return table


def _on_movie(scene, workers, run, unit: str, same: str) -> pd.DataFrame:
    """``run(movie, out, w)`` on a movie simulated from ``scene``, for each number of local
    ``workers`` (1: this process); ``run`` gives the tables to compare and the count of
    ``unit`` it made. One row per number of workers: seconds, ``unit`` per second, whether
    the tables are the one process's (the column ``same``), and the calling process's CPU
    time as a share of the one-process run's, with the shares that follow (``_shares``)."""
    rows, first, alone = [], None, None
    frames = scene.movie["frames"]
    with tempfile.TemporaryDirectory() as folder:
        movie = simulate_movie(scene, seed=0, out=f"{folder}/m").files["movie"]
        for w in workers:
            start = "" if w == 1 else worker_start()
            (tables, count), seconds, cpu = _timed(lambda w=w: run(movie, f"{folder}/w{w}", w))
            first, alone = (tables, cpu) if first is None else (first, alone)
            equal = all(a.equals(b) for a, b in zip(tables, first, strict=True))
            rows.append(
                {
                    "how": "one process" if w == 1 else "local worker processes",
                    "workers": w,
                    "workers start by": start,
                    "frames": frames,
                    unit: count,
                    "seconds": seconds,
                    f"{unit}/s": count / seconds,
                    same: np.nan if w == 1 else equal,
                    "calling process CPU / one process's": cpu / alone,
                }
            )
    return _shares(pd.DataFrame(rows), f"{unit}/s")


def per_frame(frames: int, workers, side: int = 256, molecules: int = 50) -> pd.DataFrame:
    """``localize_frames`` (``bayespsf analyze --per-frame``, default ``method="auto"``) on a
    simulated emccd-typical movie of ``frames`` frames of ``side`` x ``side`` pixels with
    ``molecules`` molecules (~47 windows per frame at 256 x 256; chunks of 512 windows, so 200
    frames keep 16 workers busy for one round of chunks and part of a second, and blocks of
    frames cut so that each worker detects two), on each number
    of local ``workers`` (1: this process):
    seconds, windows per second, whether the table is the one process's (all but the timing
    column), and the calling process's CPU time as a share of the one-process run's (all the
    work): the part that does not run on the workers (reading the frames, folding the windows
    into chunks, the files), which bounds the speed-up (Amdahl)."""
    scene = load_scene("emccd-typical").replace(
        movie={"frames": frames, "height": side, "width": side, "molecules": molecules}
        | {"dark_frames": 0, "bleach_mean": 1000.0, "two_fluorophores": 0.0, "moving": 0.0}
    )
    model = Model.from_scene(scene)

    def run(movie, out, w):
        found = localize_frames(movie, model, s0=130.0, out=out, workers=w, progress=False)
        locs = found.locs.drop(columns="seconds")
        return [locs], len(locs)

    return _on_movie(scene, workers, run, "windows", "same table as one process")


def _shares(table: pd.DataFrame, speed: str) -> pd.DataFrame:
    """The speed-up over the one-process row, per worker, and the most that 16 workers could
    give if nothing of the calling process's work overlapped theirs (Amdahl)."""
    table["speed-up vs one process"] = table[speed] / table[speed].iloc[0]
    table["per worker"] = table["speed-up vs one process"] / table["workers"]
    share = table["calling process CPU / one process's"]
    table["16 workers at most (Amdahl)"] = 1.0 / (share + (1.0 - share) / 16)
    table.loc[0, "16 workers at most (Amdahl)"] = np.nan
    return table


def immobile(frames: int, workers, side: int = 256, molecules: int = 40) -> pd.DataFrame:
    """``analyze`` (``bayespsf analyze``: immobile molecules) on a simulated paper-movie of
    ``frames`` frames of ``side`` x ``side`` pixels with ``molecules`` molecules (the shipped
    scene's 300, 256 and 40 by default: ~2 400 valid frames), the spot's SD estimated, on each
    number of local ``workers`` (1: this process): seconds, analysed frames per second,
    whether the tables are the one process's (all but the timing columns), and the calling
    process's CPU time as a share of the one-process run's (reading the movie, detecting,
    tracing, the tables, the files: the part that does not run on the workers)."""
    scene = load_scene("paper-movie").replace(
        movie={"frames": frames, "height": side, "width": side, "molecules": molecules}
        | {"dark_frames": 0}
    )
    model = Model.from_scene(scene)
    rules = Rules(min_valid_frames=min(75, frames // 3))  # the paper's 75 on a long movie

    def run(movie, out, w):
        result = analyze(movie, model, out=out, rules=rules, workers=w, progress=False)
        tables = [
            t.drop(columns=[c for c in t.columns if c.endswith("seconds")])
            for t in (result.frames, result.molecules, result.width_by_window)
        ]
        return tables, len(result.frames)

    return _on_movie(scene, workers, run, "analysed frames", "same tables as one process")


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small run that prints only")
    parser.add_argument(
        "--workers", default="1,2", help="comma-separated numbers of workers (default 1,2)"
    )
    parser.add_argument(
        "--rois",
        type=int,
        default=None,
        help="ROIs per timing (default 2000 per worker of the largest count: 4000 at 2)",
    )
    parser.add_argument(
        "--dataset", type=int, default=100_000, help="ROIs of the dataset run (0: none)"
    )
    parser.add_argument("--no-dask", action="store_true", help="local processes only")
    parser.add_argument(
        "--frames",
        type=int,
        default=200,
        help="frames of the per-frame movie, 256 x 256 pixels (default 200; 0: none)",
    )
    parser.add_argument(
        "--immobile",
        type=int,
        default=300,
        help="frames of the immobile-molecule movie, 256 x 256 pixels (default 300; 0: none)",
    )
    parser.add_argument(
        "--publish", action="store_true", help="write the table into README.md with --workers"
    )
    args = parser.parse_args(argv)
    workers = sorted({int(w) for w in args.workers.split(",")})
    if workers[0] < 1:
        parser.error(f"--workers: whole numbers >= 1, got {args.workers}")
    if args.rois is not None and args.rois < 1:
        parser.error(f"--rois: a whole number >= 1, got {args.rois}")
    if args.dataset < 0:
        parser.error(f"--dataset: a whole number >= 0 (0: no dataset run), got {args.dataset}")
    if args.frames < 0:
        parser.error(f"--frames: a whole number >= 0 (0: no movie), got {args.frames}")
    if args.immobile < 0:
        parser.error(f"--immobile: a whole number >= 0 (0: no movie), got {args.immobile}")
    # enough ROIs that starting the workers counts little and every worker gets many chunks
    rois = 2000 * workers[-1] if args.rois is None else args.rois
    n, dataset = (16, min(32, args.dataset)) if args.quick else (rois, args.dataset)
    # the movies first: the Dask clusters of parallel() leave a thread behind (its docstring)
    movie, sections = None, []
    if args.frames:
        frames = 2 if args.quick else args.frames
        movie = per_frame(frames, workers, **(dict(side=64, molecules=3) if args.quick else {}))
        sections.append(
            f'`bayespsf analyze --per-frame` (`localize_frames`, `method="auto"`) on '
            f"{frames} simulated emccd-typical frames of {64 if args.quick else 256} x "
            f"{64 if args.quick else 256} pixels:\n\n"
            f"{movie.to_markdown(index=False, floatfmt='.3g')}\n\n"
        )
    still = None
    if args.immobile:
        frames = 40 if args.quick else args.immobile
        side = 96 if args.quick else 256  # the spot's SD is estimated from >= 5 spots
        still = immobile(frames, workers, side, **(dict(molecules=6) if args.quick else {}))
        sections.append(
            f"`bayespsf analyze` (`analyze`, immobile molecules) on {frames} simulated "
            f"paper-movie frames of {side} x {side} pixels:\n\n"
            f"{still.to_markdown(index=False, floatfmt='.3g')}\n\n"
        )
    table = parallel(n, dataset, workers, dask=not args.no_dask)
    intro = '`sample_many` (default `method="auto"`, emccd-typical, N = 1000):'
    text = f"{intro}\n\n{table.to_markdown(index=False, floatfmt='.3g')}\n\n"
    text += "".join(sections)
    flags = [] if argv is None else list(argv)
    flags = sys.argv[1:] if argv is None else flags
    command = " ".join(["python benchmarks/parallel.py", *flags])
    text += f"Command: `{command}` on {machine()}."
    default = args.workers == "1,2" and not args.no_dask and args.frames == 200
    default = default and args.immobile == 300
    publish("parallel", text, args.quick or not (default or args.publish))
    return table, movie, still


if __name__ == "__main__":
    main()
