"""Shared plumbing of the validation scripts: arguments, output files, the machine line."""

from __future__ import annotations

import argparse
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from bayespsf._runtime import machine

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from report import write_section

RESULTS = Path(__file__).with_name("results")


def parser(doc: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=doc.strip().split("\n")[0])
    p.add_argument("--quick", action="store_true", help="a small run (the test suite runs it)")
    p.add_argument("--out", type=Path, default=RESULTS, help="output folder")
    return p


def write(
    out: Path, stem: str, table, text: str, command: str, started: float, summary: str | None = None
) -> None:
    """Write ``stem.csv`` and ``stem.md`` (the table, the command, the wall time, the machine);
    a full run into the default folder also puts ``summary`` into validation/README.md's
    section ``stem``."""
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / f"{stem}.csv", index=False)
    seconds = time.perf_counter() - started
    footer = f"Command: `{command}`; wall time {seconds:.0f} s on {machine()}."
    (out / f"{stem}.md").write_text(f"{text}\n\n{footer}\n")
    if summary is not None and out.resolve() == RESULTS.resolve():
        link = f"Full table: [results/{stem}.md](results/{stem}.md). {footer}"
        write_section(RESULTS.parent / "README.md", stem, f"{summary.strip()}\n\n{link}")


def study(doc: str, argv, name: str, posteriors: bool = True, arguments=None):
    """Parse a study script's arguments: (args, start time, output stem); ``arguments`` adds
    the script's own options to the parser."""
    p = parser(doc)
    if arguments is not None:
        arguments(p)
    args = (add_run_arguments(p) if posteriors else p).parse_args(argv)
    if getattr(args, "backend", "numpy") == "jax":
        if args.method == "mcmc":
            p.error(
                "--backend jax runs the batched methods: give --method auto, importance or laplace"
            )
        from bayespsf.errors import BayespsfInputError
        from bayespsf.inference.backends import check_backend

        try:
            check_backend("jax")  # JAX importable, else the extras that install it, named
        except BayespsfInputError as error:
            p.error(f"--backend jax: {error}")
    args.out.mkdir(parents=True, exist_ok=True)
    return args, time.perf_counter(), _stem(args, name)


def _stem(args, name: str) -> str:
    """Output stem: ``name``, ``_<method>`` for posteriors not made by the chain alone
    (``_auto``, ``_importance``, ``_laplace``), ``_jax`` for the JAX backend, ``_quick``."""
    return name + _method_suffix(args) + ("_quick" if args.quick else "")


def _method_suffix(args) -> str:
    method = getattr(args, "method", "mcmc")
    jax = "_jax" if getattr(args, "backend", "numpy") == "jax" else ""
    return ("" if method == "mcmc" else f"_{method}") + jax


def finish(args, name: str, table, text: str, started: float, summary: str | None = None):
    """Write a study's results (see :func:`write`), print them, return the table."""
    command = f"python validation/{name}.py" + (" --quick" if args.quick else "")
    if getattr(args, "method", "mcmc") != "mcmc":
        command += f" --method {args.method}"
    if getattr(args, "backend", "numpy") != "numpy":
        command += f" --backend {args.backend}"
    for option in ("molecules", "configurations"):  # a study's own options, when given
        if getattr(args, option, None) is not None:
            command += f" --{option} {getattr(args, option)}"
    stem = _stem(args, name)
    # a quick run is a try-out: it writes its own *_quick files, never the README's sections
    write(args.out, stem, table, text, command, started, None if args.quick else summary)
    print(text)
    return table


def per_movie_report(title: str, table, movies, stem: str, alt: str) -> tuple[str, str]:
    """(text, README summary) of a study over repeated movies: its summary table, then one
    row per movie, and its figure ``stem.png``."""
    fmt = {"index": False, "floatfmt": ".4g"}
    text = (
        f"# {title}\n\n{table.to_markdown(**fmt)}\n\nPer movie:\n\n{movies.to_markdown(**fmt)}"
        f"\n\nFigure: [{stem}.png]({stem}.png)."
    )
    return text, f"{table.to_markdown(**fmt)}\n\n![{alt}](results/{stem}.png)"


@contextmanager
def saved_figure(path: Path, figsize, columns: int = 1):
    """The axes of a new figure of ``columns`` panels, saved to ``path`` and closed on exit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, columns, figsize=figsize)
    try:
        yield axes
        fig.tight_layout()
        fig.savefig(path, dpi=120)
    finally:
        plt.close(fig)


@contextmanager
def per_movie_figure(path: Path, ylabel: str):
    """The axes of a figure with one point per movie, saved to ``path`` on exit."""
    with saved_figure(path, (6, 3)) as ax:
        yield ax
        ax.set_xlabel("movie")
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)


def add_run_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """--workers / --scheduler / --store: where the posteriors run and where they are kept."""
    p.add_argument("--workers", type=int, default=None, help="local processes (default: cores)")
    p.add_argument("--scheduler", default=None, help="a Dask scheduler address (a cluster)")
    p.add_argument(
        "--store", type=Path, default=None, help="keep every posterior here; a rerun resumes"
    )
    p.add_argument(
        "--method",
        choices=("mcmc", "auto", "importance", "laplace"),
        default="mcmc",
        help="posterior by emcee (default); auto: the batched engine (Laplace where its pilot "
        "passes, else importance sampling, else emcee); importance; laplace",
    )
    p.add_argument(
        "--backend",
        choices=("numpy", "jax"),
        default="numpy",
        help="where the batched methods run (default numpy; jax: JAX's device, a GPU where "
        "JAX finds one; needs --method auto, importance or laplace)",
    )
    return p


class Runner:
    """Runs sample_many for each point of a study on one pool of workers (or a Dask cluster)."""

    def __init__(self, args, study: str):
        from bayespsf.parallel.executors import local_executor

        self.args, self.study = args, study
        if args.scheduler is not None:
            self.executor = args.scheduler
            self.pool = None
        elif args.workers == 1:
            self.executor = self.pool = None
        else:
            self.executor = self.pool = local_executor(args.workers)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)

    def posteriors(self, point: str, counts, model, truths, seed: int, scene=None, **options):
        from bayespsf.parallel import sample_many

        method = getattr(self.args, "method", "mcmc")
        study = self.study + _method_suffix(self.args)
        store = None if self.args.store is None else self.args.store / study / point
        print(f"  {point}: {len(counts)} posteriors", flush=True)
        return sample_many(
            counts,
            model,
            seed=seed,
            executor=self.executor,
            workers=1 if self.executor is None else None,
            store=store,
            truths=truths,
            scene=scene,
            backend=getattr(self.args, "backend", "numpy"),
            **({"method": method} | options),
        )


def sd_and_error(x) -> tuple[float, float]:
    """Sample SD and its Monte Carlo standard error ``sd / sqrt(2 (n - 1))`` (normal data)."""
    x = np.asarray(x, dtype=np.float64)
    sd = float(x.std(ddof=1))
    return sd, sd / np.sqrt(2 * (x.size - 1))


def mean_and_error(x) -> tuple[float, float]:
    x = np.asarray(x, dtype=np.float64)
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(x.size))
