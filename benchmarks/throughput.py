"""Throughput: ROIs per second for a stack, bayespsf against picasso on the same ROIs.

The peers a localisation user would otherwise pick, in the same run, on the same simulated
15 x 15 ROIs (the counts converted to photons with the camera's mean gain for picasso, as its
Localize does), one thread each (``NUMBA_NUM_THREADS=1`` and one BLAS thread, set before any
import):

* picasso ``gaussmle`` (``sigmaxy``): the pixel-integrated Newton MLE of Smith et al., Nat.
  Methods 7 (2010) (deprecated in picasso 0.11, still its most-cited fitter);
* picasso ``fitting.gaussfit.fit_spots(mle=True)``: its current Levenberg-Marquardt Poisson MLE
  of the sampled Gaussian, and ``mle=False``, its least squares;
* bayespsf ``fit_mle`` with the stack engine (Laplace SDs and correlations included, and
  without them), the one-ROI scipy path and the stack engine one ROI per call; the batched
  posteriors of ``sample_many`` (``laplace``, ``importance`` and the default ``auto``, in this
  process); and per-ROI posteriors: importance sampling (``method="importance"``) and the
  emcee chain.

Each method is compiled / warmed up on a few ROIs first (not timed). Reported: ROIs per second,
the ratio to picasso ``gaussmle`` on the same ROIs, and the mean of s_x minus the truth with its
standard error (nm) over the timed ROIs. The targets' two ratios (``fit_mle`` and ``auto`` to
``gaussmle``) are then measured again in rounds, each method in turn with ``gaussmle`` (five
rounds; ``alternated``): a shared machine's slow spells move one timing of the first table, and
fall on both sides of a round's ratio. Then, for the stack engine: time per ROI against ROI
size, photon count and stack size, with the peak memory (tracemalloc) of the call. Workers and
Dask: ``benchmarks/parallel.py``.

    pip install -e ".[bench]"
    python benchmarks/throughput.py            # full run, rewrites its section of README.md
    python benchmarks/throughput.py --quick    # a small run that prints only (the tests):
                                               # one scene, the cold start from the cache
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # picasso and bayespsf compile with numba
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _report import machine, publish  # noqa: E402

from bayespsf import load_scene, simulate  # noqa: E402
from bayespsf.inference import fit_mle, sample_posterior  # noqa: E402
from bayespsf.model import Model  # noqa: E402
from bayespsf.parallel import sample_many  # noqa: E402


def picasso_fitters():
    """picasso's fitters by name: each takes ROIs in photons ``(n, s, s)`` and returns
    ``s_x`` in pixels per ROI."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # picasso's own deprecation and import chatter
        from picasso import gaussmle
        from picasso.fitting import gaussfit, seeds

    def newton(spots):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            thetas, *_ = gaussmle.gaussmle(spots, eps=0.001, max_it=1000, method="sigmaxy")
        return thetas[:, 4]  # x, y, photons, bg, sx, sy

    def fit_spots(mle):
        def fit(spots):
            start = seeds.initial_parameters_gauss(spots, spots.shape[-1])
            thetas, *_ = gaussfit.fit_spots(gaussfit.ELLIPTIC, spots, start, mle=mle)
            return thetas[:, 3]  # photons, x, y, sx, sy, bg

        return fit

    return {
        "picasso gaussmle (sigmaxy)": newton,
        "picasso LM MLE (fit_spots)": fit_spots(True),
        "picasso least squares (fit_spots)": fit_spots(False),
    }


def _timed(function, *args):
    started = time.perf_counter()
    out = function(*args)
    return out, time.perf_counter() - started


def peers(scene_name: str, n: int, posteriors: int, chains: int) -> pd.DataFrame:
    """Every method on the same ``n`` ROIs of a scene (posteriors on the first few)."""
    scene = load_scene(scene_name)
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, n, seed=1)
    spots = model.to_photons(counts).astype(np.float32)
    a = scene.geometry["pixel_size"]
    true_sx = truth["s_x"].to_numpy()
    rows = []

    def row(method, seconds, count, sx):
        error = np.asarray(sx, dtype=float) - true_sx[:count]
        error = error[np.isfinite(error)]
        se = error.std(ddof=1) / np.sqrt(len(error)) if len(error) > 1 else np.nan
        rows.append(
            {
                "scene": scene_name,
                "method": method,
                "ROIs": count,
                "seconds": seconds,
                "ROIs/s": count / seconds,
                "s_x - truth (nm)": error.mean(),
                "SE (nm)": se,
            }
        )

    for name, fit in picasso_fitters().items():
        fit(spots[:4])  # numba compilation
        sx, seconds = _timed(fit, spots)
        row(name, seconds, n, a * sx)
    fit_mle(counts[:4], model)  # the table tier's build and numba compilation
    fits, seconds = _timed(fit_mle, counts, model)
    row("bayespsf fit_mle (stack, with Laplace)", seconds, n, fits["s_x"])
    fits, seconds = _timed(lambda: fit_mle(counts, model, laplace=False))
    row("bayespsf fit_mle + CRLB (stack, no Laplace)", seconds, n, fits["s_x"])
    few = min(n, max(posteriors, 20))
    fits, seconds = _timed(lambda: fit_mle(counts[:few], model, engine="scipy"))
    row("bayespsf fit_mle (scipy, one ROI at a time)", seconds, few, fits["s_x"])
    started = time.perf_counter()
    sx = [fit_mle(counts[i : i + 1], model)["s_x"].iloc[0] for i in range(few)]
    row("bayespsf fit_mle (stack engine, one ROI per call)", time.perf_counter() - started, few, sx)
    for method, ess in (("laplace", 400), ("importance", 400), ("auto", 400), ("auto", 100)):
        sample_many(counts[:4], model, workers=1, method=method, ess=ess)  # warm-up
        table, seconds = _timed(
            lambda m=method, e=ess: sample_many(counts, model, workers=1, method=m, ess=e)
        )
        used = ", ".join(f"{k} {v}" for k, v in table["method"].value_counts().items())
        row(
            f"bayespsf sample_many {method}, ESS {ess} (batched; {used})",
            seconds,
            n,
            table["s_x_mean"],
        )
    for method, count in (("importance", posteriors), ("mcmc", chains)):
        sample_posterior(counts[-1], model, seed=0, method=method)  # imports arviz once
        started = time.perf_counter()
        means = [
            sample_posterior(counts[i], model, seed=i, method=method).draws()["s_x"].mean()
            for i in range(count)
        ]
        label = "importance sampling" if method == "importance" else "emcee chain"
        row(f"bayespsf posterior ({label}, per ROI)", time.perf_counter() - started, count, means)
    table = pd.DataFrame(rows)
    reference = table.loc[table["method"] == "picasso gaussmle (sigmaxy)", "ROIs/s"].iloc[0]
    table["ROIs/s / gaussmle"] = table["ROIs/s"] / reference
    return table


def alternated(scene_name: str, n: int, rounds: int) -> pd.DataFrame:
    """picasso ``gaussmle``, ``fit_mle`` (with the Laplace) and ``sample_many`` (``auto``, ESS
    400) on the same ``n`` ROIs in turn, ``rounds`` times: each round's ratios to that round's
    ``gaussmle`` (CPU seconds of this process, one thread), so that a slow spell of a shared
    machine falls on a ratio's both sides. One row per method: the median ratio, its range
    and each round's."""
    scene = load_scene(scene_name)
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, n, seed=2)
    spots = model.to_photons(counts).astype(np.float32)
    newton = picasso_fitters()["picasso gaussmle (sigmaxy)"]
    ours = {
        "bayespsf fit_mle (stack, with Laplace)": lambda: fit_mle(counts, model),
        "bayespsf sample_many auto, ESS 400": lambda: sample_many(counts, model, workers=1),
    }
    newton(spots[:4]), fit_mle(counts[:4], model), sample_many(counts[:4], model, workers=1)
    ratios = {name: [] for name in ours}
    for _ in range(rounds):
        started = time.process_time()
        newton(spots)
        reference = time.process_time() - started
        for name, run in ours.items():
            started = time.process_time()
            run()
            ratios[name].append(reference / (time.process_time() - started))
    return pd.DataFrame(
        [
            {
                "scene": scene_name,
                "method": name,
                "ROIs": n,
                "rounds": rounds,
                "median ROIs/s / gaussmle": np.median(values),
                "lowest": min(values),
                "highest": max(values),
                "each round": " ".join(f"{v:.3f}" for v in values),
            }
            for name, values in ratios.items()
        ]
    )


def scaling(quick: bool) -> pd.DataFrame:
    """The stack engine's time per ROI and peak memory against ROI size, N and stack size."""
    base = load_scene("emccd-typical")
    plans = [("roi", v) for v in ((7,) if quick else (7, 11, 15, 25))]
    plans += [("N", v) for v in ((1e4,) if quick else (100.0, 1e3, 1e4, 1e5))]
    plans += [("stack", v) for v in ((1, 50) if quick else (1, 10, 100, 1000, 10_000, 100_000))]
    rows = []
    for kind, value in plans:
        scene, n = base, 50 if quick else 1000
        if kind == "roi":
            scene = base.replace(geometry={"roi": value})
        elif kind == "N":
            scene = base.replace(emitter={"photons": value})
        else:
            n = value
        model = Model.from_scene(scene)
        counts, _ = simulate(scene, n, seed=2)
        fit_mle(counts[:2], model)
        tracemalloc.start()
        fits, seconds = _timed(fit_mle, counts, model)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        rows.append(
            {
                "varied": kind,
                "value": value,
                "ROIs": n,
                "ms per ROI": 1e3 * seconds / n,
                "ROIs/s": n / seconds,
                "peak MB": peak / 2**20,
                "converged": float(fits["converged"].mean()),
            }
        )
    return pd.DataFrame(rows)


COLD = """
import sys, time
started = time.perf_counter()
import numpy as np
from bayespsf import Model, fit_mle, load_scene
imported = time.perf_counter()
counts = np.load(sys.argv[1])  # as a user's first fit reads its data: nothing compiled yet
model = Model.from_scene(load_scene("emccd-typical"))
began = time.perf_counter()
fit_mle(counts, model)
print(imported - started, time.perf_counter() - began)
"""


def cold_start(quick: bool = False) -> pd.DataFrame:
    """The first fit of a new process (emccd-typical, table tier): on a machine without the
    EMCCD tables (they are built) and then in a second process (they are read from the on-disk
    cache); imports timed apart. Each process reads its ROI from a file this one wrote, so that
    nothing is compiled before the timed fit (the simulator runs a compiled loop), as in a
    user's first fit of data. ``quick``: only a process reading this machine's own cache,
    which this process's fits have filled (building the tables takes ~15 s)."""
    import subprocess
    import sys
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ} if quick else {**os.environ, "BAYESPSF_CACHE": cache}
        roi = os.path.join(cache, "roi.npy")
        np.save(roi, simulate(load_scene("emccd-typical"), 1, seed=0)[0])
        processes = ("first process on the machine", "a later process")
        for when in processes[1:] if quick else processes:
            out = subprocess.run(
                [sys.executable, "-c", COLD, roi],
                env=env,
                capture_output=True,
                text=True,
                check=True,
            ).stdout.split()
            rows.append(
                {"process": when, "imports (s)": float(out[0]), "first fit (s)": float(out[1])}
            )
    return pd.DataFrame(rows)


def markdown(
    peer_table: pd.DataFrame,
    scale_table: pd.DataFrame,
    command: str,
    cold: pd.DataFrame | None = None,
    turns: pd.DataFrame | None = None,
) -> str:
    fmt = {"floatfmt": ".3g", "index": False}
    return (
        "Same ROIs, one thread each; `ROIs/s / gaussmle` is the ratio to picasso's `gaussmle` in "
        "the same run.\n\n"
        f"{peer_table.to_markdown(**fmt)}\n\n"
        + (
            ""
            if turns is None
            else "The same ratios with `gaussmle` and each method run in turn, round after "
            "round on other ROIs of the same scene (CPU seconds; each round's ratio to its own "
            f"`gaussmle`):\n\n{turns.to_markdown(**fmt)}\n\n"
        )
        + "The stack engine (`fit_mle`, Laplace included) against ROI size, photon count and stack "
        "size (emccd-typical otherwise), with the call's peak memory:\n\n"
        f"{scale_table.to_markdown(**fmt)}\n\n"
        + (
            ""
            if cold is None
            else "The first fit of a new process (the EMCCD tables built, "
            f"then read from the on-disk cache):\n\n{cold.to_markdown(**fmt)}\n\n"
        )
        + f"Command: `{command}` on {machine()}."
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small run that prints only")
    args = parser.parse_args(argv)
    n, posteriors, chains = (40, 3, 2) if args.quick else (2000, 40, 5)
    names = ("emccd-typical",) if args.quick else ("emccd-typical", "ideal")
    peer_table = pd.concat(
        [peers(name, n, posteriors, chains) for name in names], ignore_index=True
    )
    turns = pd.concat(
        [alternated(name, n, 2 if args.quick else 5) for name in names], ignore_index=True
    )
    scale_table = scaling(args.quick)
    cold = cold_start(args.quick)
    command = "python benchmarks/throughput.py" + (" --quick" if args.quick else "")
    text = markdown(peer_table, scale_table, command, cold, turns)
    publish("throughput", text, args.quick)
    return peer_table, scale_table, cold, turns


if __name__ == "__main__":
    main()
