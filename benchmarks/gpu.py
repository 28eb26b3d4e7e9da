"""The JAX backend against the NumPy backend on the same ROIs: rates, the device, agreement.

On the same simulated ROIs (``emccd-typical`` by default: EMCCD table tier, 15 x 15 pixels,
N = 1000, b = 10), in one run:

1. **Agreement** on ``--compare`` ROIs: ``fit_mle`` through each backend (largest relative
   difference of the estimates, the Laplace SDs and the Cramér-Rao bounds over the ROIs both
   fitted), and ``sample_many(method="auto")`` through each (the difference of posterior means
   in posterior SDs, whose spread is Monte Carlo error: about ``sqrt(2 / ess)`` for two
   independent runs; the ratio of posterior SDs; the 90% interval coverage of each against the
   truth with its binomial SE). The NumPy backend runs on every core of the machine
   (``workers=os.cpu_count()``) and its rate is reported too.
2. **Rates on JAX's device** on ``--rois`` ROIs, after the same calls once (which compile every
   program shape they use): ``fit_mle(backend="jax")`` (the table included) and its engine
   alone; the posteriors on the device from given fits (``jax_sampling.posteriors``), with the
   draws scored per ROI and how many ROIs each importance proposal took; and
   ``sample_many(backend="jax", method="auto")`` (the fits, the posteriors, the summary table;
   the ROIs whose diagnostics need a chain run it on the CPU, counted in the table). The
   host's own work in ``fit_mle`` (the ROI checks and the table) is timed with the engine's
   results replayed, and in ``sample_many`` with every device program's outputs replayed
   (``host_seconds``): it bounds the whole call's rate on any device. The device's own time
   in ``sample_many`` is split by program, each waited for as it is called
   (``program_seconds``): the fit's engine, the pilot, the Laplace, the Gaussian round, the
   Student-t rounds, the law's reruns, Pearson's statistic; and the Gaussian round's program
   in parts on ``--parts`` ROIs (``round_parts``: its draws, the spot's factors, the draws
   scored, the weights smoothed and summarised), each with the work that XLA's cost model
   counts in its compiled program (floating-point operations and bytes accessed per ROI) and
   the rates its time gives them: on a GPU, whether a part is bound by arithmetic or by
   memory bandwidth.
3. **Streaming**: ``--stream`` ROIs through the fit and the posteriors in blocks of ``--rois``
   (the simulated block reused with each ROI's own seed, as a dataset's ROIs would be read
   block by block), with the peak resident memory of the process.

    pip install -e ".[gpu]"                   # JAX with CUDA (or ".[jax]" for the CPU)
    python benchmarks/gpu.py                  # the full run (minutes on one GPU)
    python benchmarks/gpu.py --quick          # a small run on any machine (the tests)

A full run on a GPU writes ``gpu.md`` and ``gpu.json`` to ``--out`` (default
``benchmarks/results``) and its section of benchmarks/README.md, with the machine and the
command; where JAX computes on the CPU it prints only.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf.inference import fit_mle
from bayespsf.inference.backends import device_name
from bayespsf.inference.jax_sampling import posteriors
from bayespsf.inference.settings import check_settings
from bayespsf.inference.summary import coverage
from bayespsf.model import Model
from bayespsf.parallel import sample_many
from bayespsf.parallel.seeds import molecule_seeds
from bayespsf.psf import PARAMETER_NAMES


def _options(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small run (the tests)")
    parser.add_argument("--scene", default="emccd-typical", help="a shipped scene")
    parser.add_argument(
        "--compare", type=int, default=2000, help="ROIs run through both (0: rates only)"
    )
    parser.add_argument("--rois", type=int, default=100_000, help="ROIs per timed block")
    parser.add_argument("--stream", type=int, default=1_000_000, help="ROIs streamed (0: none)")
    parser.add_argument(
        "--parts",
        type=int,
        default=None,
        help="ROIs of the Gaussian round's parts' timing (default 8192 on a GPU, 1024 else)",
    )
    parser.add_argument("--out", default="benchmarks/results", help="where gpu.md goes")
    options = parser.parse_args(argv)
    if options.parts is not None and options.parts < 1:
        parser.error(f"--parts: a whole number >= 1, got {options.parts}")
    if options.quick:
        options.compare, options.rois, options.stream, options.parts = 64, 64, 128, 64
    return options


def _timed(function):
    started = time.perf_counter()
    value = function()
    return value, time.perf_counter() - started


def agreement(counts, truth, model) -> tuple[dict, dict]:
    """Both backends on the same ROIs: the MLE's largest relative differences and the
    posteriors' agreement in posterior SDs."""
    cpu = os.cpu_count() or 1
    fit_mle(counts[:8], model)  # the camera's tables and the compiled kernels, not timed
    (mle_np, t_np), (mle_jax, _) = (
        _timed(lambda: fit_mle(counts, model)),
        _timed(lambda: fit_mle(counts, model, backend="jax")),
    )
    both = mle_np["converged"].to_numpy(bool) & mle_jax["converged"].to_numpy(bool)
    fit = {"ROIs": len(counts), "converged (numpy, jax)": (
        int(mle_np["converged"].sum()), int(mle_jax["converged"].sum()))}  # fmt: skip
    for prefix in ("", "sd_", "crlb_"):
        a = mle_np.loc[both, [prefix + p for p in PARAMETER_NAMES]].to_numpy(float)
        b = mle_jax.loc[both, [prefix + p for p in PARAMETER_NAMES]].to_numpy(float)
        fit[f"max rel. diff {prefix or 'estimate '}".strip()] = float(
            np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-12))
        )
    truths = truth.to_numpy(float)
    (post_np, t_post_np) = _timed(
        lambda: sample_many(counts, model, seed=7, workers=cpu, truths=truths)
    )
    post_jax = sample_many(counts, model, seed=7, workers=cpu, truths=truths, backend="jax")
    z = np.concatenate(
        [
            (post_np[f"{p}_mean"] - post_jax[f"{p}_mean"]) / post_np[f"{p}_sd"]
            for p in PARAMETER_NAMES
        ]
    )
    ratio = np.concatenate([post_jax[f"{p}_sd"] / post_np[f"{p}_sd"] for p in PARAMETER_NAMES])
    cov_np, cov_jax = coverage(post_np, 0.9), coverage(post_jax, 0.9)
    posterior = {
        "mean difference / posterior SD: mean": float(np.nanmean(z)),
        "mean difference / posterior SD: SD": float(np.nanstd(z)),
        "expected SD (Monte Carlo, 2 runs at ESS 400)": float(np.sqrt(2 / 400)),
        "posterior SD ratio jax/numpy: mean": float(np.nanmean(ratio)),
        "90% coverage numpy (min-max over parameters)": (
            float(cov_np["coverage"].min()), float(cov_np["coverage"].max())),
        "90% coverage jax (min-max over parameters)": (
            float(cov_jax["coverage"].min()), float(cov_jax["coverage"].max())),
        "binomial SE": float(np.sqrt(0.09 / len(counts))),
        "methods numpy": post_np["method"].value_counts().to_dict(),
        "methods jax": post_jax["method"].value_counts().to_dict(),
    }  # fmt: skip
    rates = {
        f"fit_mle numpy (one process, {len(counts)} ROIs)": len(counts) / t_np,
        f"sample_many auto numpy ({cpu} workers, {len(counts)} ROIs)": len(counts) / t_post_np,
    }
    return {"fit": fit, "posterior": posterior}, rates


def device_rates(counts, model) -> tuple[dict, dict]:
    """ROIs per second on JAX's device, after compiling on the same shapes; how the device's
    posteriors were made."""
    from bayespsf.inference import jax_mle

    n = len(counts)
    # the same calls first: they compile every program shape the timed calls use (the
    # Gaussian round's sizes and the law's reruns depend on the ROIs and their seeds)
    fits = fit_mle(counts, model, backend="jax")
    sample_many(counts, model, seed=2, workers=1, backend="jax")
    settings = check_settings(method="auto")
    seeds = molecule_seeds(2, np.arange(n))
    posteriors(counts, model, fits, seeds, settings)
    found, t_engine = _timed(lambda: jax_mle.maximise(model, counts, None, True, True))
    _, t_fit = _timed(lambda: fit_mle(counts, model, backend="jax"))
    with mock.patch.object(jax_mle, "maximise", lambda *args: found):  # the engine replayed
        t_host = min(_timed(lambda: fit_mle(counts, model, backend="jax"))[1] for _ in "123")
    out, t_device = _timed(lambda: posteriors(counts, model, fits, seeds, settings))
    table, t_post = _timed(lambda: sample_many(counts, model, seed=2, workers=1, backend="jax"))
    t_post_host = host_seconds(
        lambda: sample_many(counts, model, seed=2, workers=1, backend="jax"), table
    )
    programs = program_seconds(lambda: sample_many(counts, model, seed=2, workers=1, backend="jax"))
    sources = pd.Series(out["why"]).str.extract(r"sampling from the Laplace (\w+)")[0]
    rates = {
        f"fit_mle jax engine ({n} ROIs: fit, Laplace, CRLB)": n / t_engine,
        f"fit_mle jax ({n} ROIs, the table included)": n / t_fit,
        f"posteriors on the device ({n} ROIs, fits given)": n / t_device,
        f"sample_many auto jax ({n} ROIs, fits and summary table included)": n / t_post,
        "sample_many auto jax: methods": table["method"].value_counts().to_dict(),
    }
    made = {
        "ROIs": n,
        "fit_mle jax: the host's work per ROI (µs; ROI checks, table)": 1e6 * t_host / n,
        "sample_many auto jax: the host's work per ROI (µs)": 1e6 * t_post_host / n,
        "from the Laplace Gaussian": int((sources == "Gaussian").sum()),
        "from the Laplace Student-t": int((sources == "Student").sum()),
        "draws scored per ROI (mean)": float(np.mean(out["draws_scored"])),
    } | {
        f"sample_many auto jax, {'' if name == 'the whole call' else 'device program '}{name} "
        "(µs per ROI, programs waited for)": 1e6 * t / n
        for name, t in programs.items()
    }
    return rates, made


def host_seconds(call, expected: pd.DataFrame) -> float:
    """The seconds ``call`` (a ``backend="jax"`` call) spends on the host: it runs once with
    each device program's outputs recorded (taken to the host), then again with them replayed
    in the same order, so that the second run does everything but the device's work and the
    transfers (ROI checks, stages cut and gathered, seeds, reasons, tables): the best of three
    replays. Each replayed result must equal ``expected`` (``seconds`` aside): the replay is
    the same run. It replaces the backend's own program factory (``jax_sampling._program``)
    and engine (``jax_mle.maximise``) for these runs, as only a benchmark of the backend
    should."""
    from bayespsf.inference import jax_mle, jax_sampling

    outputs, fits = [], []
    program, maximise = jax_sampling._program, jax_mle.maximise

    def recorded(*args, **static):
        run = program(*args, **static)

        def record(*inputs):
            out = run(*inputs)
            out = out if isinstance(out, tuple) else (out,)
            outputs.append(tuple(None if o is None else np.asarray(o) for o in out))
            return outputs[-1]

        return record

    def fit(*args):
        fits.append(maximise(*args))
        return fits[-1]

    with mock.patch.object(jax_sampling, "_program", recorded):
        with mock.patch.object(jax_mle, "maximise", fit):
            call()

    def replayed():
        outputs_, fits_ = iter(outputs), iter(fits)
        with mock.patch.object(jax_sampling, "_program", lambda *a, **k: lambda *i: next(outputs_)):
            with mock.patch.object(jax_mle, "maximise", lambda *args: next(fits_)):
                table, seconds = _timed(call)
        pd.testing.assert_frame_equal(
            table.drop(columns="seconds"), expected.drop(columns="seconds")
        )
        return seconds

    return min(replayed() for _ in range(3))  # the best of three: less the machine's noise


def program_seconds(call) -> dict:
    """Where the device's time goes in ``call`` (a ``backend="jax"`` call): each device
    program of the posteriors (``jax_sampling._program``: the pilot, the Laplace, the
    Gaussian round, the Student-t rounds, the law's reruns, Pearson's statistic) waited for
    as it is called, and the fit's engine (``jax_mle.maximise``), in seconds by program. The
    calls run one after another here, without the overlap of a normal run; ``the whole call``
    is that run's seconds, the programs' and the host's."""
    import jax

    from bayespsf.inference import jax_mle, jax_sampling

    seconds: dict[str, float] = {}
    program, maximise = jax_sampling._program, jax_mle.maximise

    def add(name, started):
        seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - started

    def timed(*args, **static):
        run = program(*args, **static)  # as called: the same cached (compiled) program
        name = f"{args[0]} (the law itself)" if static.get("exact") else args[0]

        def waited(*inputs):
            started = time.perf_counter()
            out = jax.block_until_ready(run(*inputs))
            add(name, started)
            return out

        return waited

    def fit(*args):
        started = time.perf_counter()
        found = maximise(*args)  # host arrays: it has waited for the device
        add("fit (engine: fit, Laplace, CRLB)", started)
        return found

    with mock.patch.object(jax_sampling, "_program", timed):
        with mock.patch.object(jax_mle, "maximise", fit):
            _, whole = _timed(call)
    return seconds | {"the whole call": whole}


def round_parts(counts, model, fits, size: int = 374) -> dict:
    """The Gaussian round's program in parts, each compiled alone and timed on the same ROIs
    (µs per ROI): its draws; the draws and the spot's factors (``JaxModel.spot``); the draws
    scored (the law interpolated per pixel, ``jax_programs.log_posterior``); the weights
    smoothed, resampled and summarised (``jax_programs._weighted``, on random log ratios);
    and the whole program. ``size`` is emccd-typical's usual round at ESS 400. The parts are
    the backend's own internal functions, compiled here one by one. With each time, the work
    that XLA's cost model counts in the compiled program (``cost``: floating-point operations
    and bytes accessed per ROI, and the rates the time gives them), which says whether a part
    is bound by arithmetic or by memory on the device that ran it."""
    import jax
    import jax.numpy as jnp

    from bayespsf.inference import jax_programs as programs
    from bayespsf.inference.batched import PILOT, _choleskys, laplace_in_z
    from bayespsf.inference.jax_model import JaxModel
    from bayespsf.inference.jax_sampling import keys, seed_words
    from bayespsf.model import LOG_PARAMETERS

    n = len(counts)
    centre, cov = laplace_in_z(fits, model)
    chol = _choleskys(cov)
    fallback = np.clip(fits[list(PARAMETER_NAMES)].to_numpy(float), *model.prior_bounds())
    words = seed_words(molecule_seeds(5, np.arange(n)))
    jm, truth = JaxModel.from_model(model), np.full((n, 6), np.nan)
    ratio = np.random.default_rng(0).normal(0.0, 0.1, (n, PILOT + size))
    logs = jnp.asarray(LOG_PARAMETERS)

    def draws(centre, chol, words):
        return programs._gaussian_draws(centre, chol, keys(words), 4, size)

    def spot(jm, centre, chol, words):
        z, _ = draws(centre, chol, words)
        return jm.spot(z.at[..., logs].set(jnp.exp(z[..., logs])))

    def scored(jm, counts, centre, chol, words, fallback):
        z, _ = draws(centre, chol, words)
        return programs.log_posterior(jm, counts, z, fallback)

    def weighted(centre, chol, words, ratio, truth):
        z, _ = programs._gaussian_draws(centre, chol, keys(words), 4, PILOT + size)
        split = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, 5)))(keys(words))
        return jax.vmap(programs._weighted)(z, ratio, split[:, 0], split[:, 1], truth)

    def whole(jm, counts, centre, chol, words, fallback, truth, pilot_ratio):
        return programs.gaussian(
            jm, counts, centre, chol, keys(words), fallback, truth, pilot_ratio,
            size=size, exact=False,
        )  # fmt: skip

    parts = {
        "draws": (draws, (centre, chol, words)),
        "draws and the spot's factors": (spot, (jm, centre, chol, words)),
        "draws scored (the law interpolated)": (
            scored, (jm, counts, centre, chol, words, fallback)
        ),
        "weights smoothed, resampled, summarised": (
            weighted, (centre, chol, words, ratio, truth)
        ),
        "the whole program": (
            whole, (jm, counts, centre, chol, words, fallback, truth, ratio[:, :PILOT])
        ),
    }  # fmt: skip
    out = {}
    for name, (function, args) in parts.items():
        compiled = jax.jit(function).lower(*args).compile()
        jax.block_until_ready(compiled(*args))  # warmed
        best = min(_timed(lambda c=compiled, a=args: jax.block_until_ready(c(*a)))[1] for _ in "12")
        out[f"Gaussian round of {size} draws: {name} (µs per ROI, {n} ROIs)"] = 1e6 * best / n
        out[f"Gaussian round of {size} draws: {name} (XLA's cost model, per ROI)"] = cost(
            compiled, n, best
        )
    return out


def cost(compiled, n: int, seconds: float) -> str:
    """XLA's count of a compiled program's work (``Compiled.cost_analysis``) per ROI of its
    ``n``, and the rates that ``seconds`` of it give: floating-point operations and bytes read
    and written, as its fused kernels do them."""
    counted = compiled.cost_analysis()
    counted = counted[0] if isinstance(counted, list | tuple) else counted  # older JAX: a list
    if not counted:  # a platform whose compiler does not count
        return "not counted on this device"
    flops, moved = counted.get("flops", np.nan), counted.get("bytes accessed", np.nan)
    return (
        f"{flops / n / 1e6:.3g} MFLOP, {moved / n / 1e6:.3g} MB accessed "
        f"({flops / seconds / 1e9:.3g} GFLOP/s, {moved / seconds / 1e9:.3g} GB/s)"
    )


def stream(counts, model, total: int) -> dict:
    """``total`` ROIs through the fit and the posteriors, block by block, each ROI with its
    own seed (the block's counts reused); the peak resident memory of the process."""
    settings = check_settings(method="auto")
    block = len(counts)
    done, made, started = 0, 0, time.perf_counter()
    while done < total:
        k = min(block, total - done)
        seeds = molecule_seeds(3, done + np.arange(k))
        fits = fit_mle(counts[:k], model, backend="jax")
        out = posteriors(counts[:k], model, fits, seeds, settings)
        made += int(out["made"].sum())
        done += k
    seconds = time.perf_counter() - started
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB (Linux)
    return {
        "ROIs streamed": done,
        "block": block,
        "posteriors made on the device": made,
        "seconds": seconds,
        "ROIs per second": done / seconds if done else float("nan"),
        "peak resident memory (MiB)": peak,
        "one block's counts (MiB)": counts.nbytes / 2**20,
    }


def main(argv=None) -> dict:
    """Run the benchmark; return its results (also printed, and with a full run written)."""
    options = _options(argv)
    scene = load_scene(options.scene)
    model = Model.from_scene(scene)
    counts, truth = simulate(scene, max(options.compare, options.rois), seed=11)
    compare, rates = {"fit": {}, "posterior": {}}, {}
    if options.compare:
        compare, rates = agreement(counts[: options.compare], truth.iloc[: options.compare], model)
        print(json.dumps({"agreement": compare, "rates": rates}, default=str), flush=True)
    device, made = device_rates(counts[: options.rois], model)
    rates |= device
    import jax  # started by now: the NumPy backend's pool above may fork

    on_gpu = jax.devices()[0].platform != "cpu"
    part = counts[: min(options.rois, options.parts or (8192 if on_gpu else 1024))]
    made |= round_parts(part, model, fit_mle(part, model, backend="jax"))
    print(json.dumps({"rates": rates, "work per ROI": made}, default=str), flush=True)
    streamed = stream(counts[: options.rois], model, options.stream) if options.stream else {}
    flags = sys.argv[1:] if argv is None else list(argv)
    command = " ".join(["python benchmarks/gpu.py", *flags])
    result = {
        "command": command,
        "device": device_name(),
        "scene": options.scene,
        "agreement": compare,
        "rates (ROIs per second)": rates,
        "work per ROI": made,
        "stream": streamed,
    }
    text = render(result)
    print(text)
    if not on_gpu and not options.quick:
        print("JAX computes on the CPU here: printed only (the results files and the README's")
        print("section hold a GPU's run)")
    if on_gpu and not options.quick:
        out = Path(options.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "gpu.md").write_text(text, encoding="utf-8")
        (out / "gpu.json").write_text(json.dumps(result, indent=1, default=str), encoding="utf-8")
        from _report import write_section

        write_section("gpu", text)
    return result


def render(result: dict) -> str:
    """The results as markdown tables."""
    from _report import machine

    lines = [
        f"`{result['command']}` on {machine()}; JAX device: {result['device']}; "
        f"scene `{result['scene']}`.",
        "",
    ]
    for title, table in (
        ("Rates", result["rates (ROIs per second)"]),
        ("Work per ROI", result["work per ROI"]),
        ("MLE agreement", result["agreement"]["fit"]),
        ("Posterior agreement", result["agreement"]["posterior"]),
        ("Streaming", result["stream"]),
    ):
        if not table:  # --compare 0 or --stream 0
            continue
        frame = pd.DataFrame({"": list(table), title: [_cell(v) for v in table.values()]})
        lines += [frame.to_markdown(index=False), ""]
    return "\n".join(lines)


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


if __name__ == "__main__":
    main()
