"""Where a posterior's time goes, what is arithmetic and what is overhead, and what the
alternatives would give.

1. `cProfile` of `sample_posterior` on molecules of `emccd-typical` (table tier, N = 1000):
   cumulative time of each stage (MLE start; log-posterior split into PSF, likelihood, prior
   and its own glue; proposals; convergence checks) and the rest, which is emcee's per-step
   bookkeeping.
2. One log-posterior call of 32 walkers: its parts timed apart (best of many), beside the
   compiled (numba) table interpolation alone, i.e. the arithmetic floor of the likelihood.
3. emcee's own cost per step: the same sampler and moves on a log-probability that costs
   nothing (a Gaussian in 6 dimensions), steps per second.
4. Importance sampling instead of MCMC (`sample_posterior(method="importance")`: Laplace
   Student-t draws scored in one vectorised call, Pareto-smoothed weights): its time per
   molecule against one MLE, its Pareto k-hat (reliable below 0.7) and its ESS.

    python benchmarks/hot_path.py            # full run, rewrites its section of README.md
    python benchmarks/hot_path.py --quick    # fewer molecules and repeats, prints only
"""

from __future__ import annotations

import argparse
import time

import emcee
import numpy as np
import pandas as pd

from bayespsf import load_scene, psf, simulate
from bayespsf._runtime import best_time
from bayespsf.cameras import _emccd_table
from bayespsf.inference import fit_mle, sample_posterior
from bayespsf.inference.sampling import IndependenceMove, _moves
from bayespsf.model import Model


def _setup(molecules: int):
    scene = load_scene("emccd-typical").replace(emitter={"photons": 1000.0})
    model = Model.from_scene(scene)
    counts, _ = simulate(scene, molecules, seed=21)
    rois = [model.check_counts(c) for c in counts]
    # one-time costs outside every timing: the table's build, numba's compilation, the imports
    # of arviz and arviz_stats on a process's first posterior
    sample_posterior(rois[0], model, seed=99, progress=False)
    sample_posterior(rois[0], model, seed=99, progress=False, method="importance")
    return model, rois


def stages(model, rois) -> pd.DataFrame:
    """Seconds per stage of sample_posterior over ``rois``: wall-clock timers around each
    stage's entry point (a profiler's per-call overhead would inflate emcee's many small
    Python calls), the rest being emcee's own bookkeeping."""
    import bayespsf.inference.sampling as sampling

    spent = dict.fromkeys(
        [
            "MLE start (fit_mle + Laplace)",
            "log-posterior calls",
            "proposals (independence t, DE, snooker)",
            "convergence checks (tau by FFT)",
            "result object (Posterior: xarray DataTree)",
        ],
        0.0,
    )

    inside = []  # the stages being timed, innermost last

    def timed(function, stage):
        def wrapper(*args, **kwargs):
            if inside:  # a nested call (the start scores its walkers): its outer stage counts it
                return function(*args, **kwargs)
            inside.append(stage)
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent[stage] += time.perf_counter() - start
                inside.pop()

        return wrapper

    patches = [
        (sampling, "_start", "MLE start (fit_mle + Laplace)"),
        (sampling, "_autocorrelation_time", "convergence checks (tau by FFT)"),
        (IndependenceMove, "_propose", "proposals (independence t, DE, snooker)"),
        (emcee.moves.DEMove, "get_proposal", "proposals (independence t, DE, snooker)"),
        (emcee.moves.DESnookerMove, "get_proposal", "proposals (independence t, DE, snooker)"),
        (sampling.Posterior, "from_draws", "result object (Posterior: xarray DataTree)"),
    ]
    originals = [(owner, name, owner.__dict__[name]) for owner, name, _ in patches]
    for owner, name, stage in patches:
        setattr(owner, name, timed(getattr(owner, name), stage))
    model.log_posterior = timed(model.log_posterior, "log-posterior calls")
    try:
        start = time.perf_counter()
        for k, c in enumerate(rois):
            sample_posterior(c, model, seed=k, progress=False)
        total = time.perf_counter() - start
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
        del model.log_posterior
    parts = dict(spent)
    parts["emcee bookkeeping and the rest"] = total - sum(parts.values())
    table = pd.DataFrame({"stage": list(parts), "seconds": list(parts.values())})
    table["share"] = table["seconds"] / total
    table.loc[len(table)] = ["total", total, 1.0]
    table["per molecule (ms)"] = 1e3 * table["seconds"] / len(rois)
    return table


def log_posterior_parts(model, c, repeat: int) -> pd.DataFrame:
    """One vectorised log-posterior call of 32 walkers, and its parts, in microseconds."""
    rng = np.random.default_rng(3)
    fit = fit_mle(c, model).iloc[0]
    p = fit[list(psf.PARAMETER_NAMES)].to_numpy(float) * (1 + 0.01 * rng.standard_normal((32, 6)))
    z = model.to_unconstrained(p)
    lam = psf.expected_counts_unchecked(p, model.roi, model.pixel_size)
    t = model.camera.gain_units(c)
    tt, ll = np.broadcast_arrays(t, lam)
    tt, ll = np.ascontiguousarray(tt).ravel(), np.ascontiguousarray(ll).ravel()
    table = _emccd_table.table_for(model.camera.readout_in_gain_units)

    timings = {
        "whole log_posterior (32 walkers)": lambda: model.log_posterior(z, c),
        "PSF (its two axes' compiled loops, the outer product)": lambda: (
            psf.expected_counts_unchecked(p, model.roi, model.pixel_size)
        ),
        "likelihood: camera.log_likelihood_unchecked": lambda: (
            model.camera.log_likelihood_unchecked(c, lam)
        ),
        "likelihood: the table's interpolation alone": lambda: table.log_p(tt, ll),
        "prior": lambda: model.log_prior(p),
    }
    rows = [{"part": k, "microseconds": 1e6 * best_time(f, repeat)} for k, f in timings.items()]
    return pd.DataFrame(rows)


def emcee_floor(steps: int) -> pd.DataFrame:
    """Steps per second of emcee with our moves on a free log-probability (6-D Gaussian)."""
    rows = []
    for name in ("laplace-de", "de-snooker"):
        proposal = IndependenceMove(np.zeros(6), np.eye(6)) if name == "laplace-de" else None
        sampler = emcee.EnsembleSampler(
            32,
            6,
            lambda z: -0.5 * np.sum(z * z, axis=1),
            vectorize=True,
            moves=_moves(name, proposal),
        )
        sampler.random_state = np.random.RandomState(0).get_state()
        start = time.perf_counter()
        sampler.run_mcmc(np.random.default_rng(0).standard_normal((32, 6)), steps)
        seconds = time.perf_counter() - start
        rows.append(
            {
                "moves": name,
                "steps/s with a free log-probability": steps / seconds,
                "microseconds per step": 1e6 * seconds / steps,
            }
        )
    return pd.DataFrame(rows)


def importance(model, rois) -> pd.DataFrame:
    """``sample_posterior(method="importance")`` at ESS 400, per molecule, against one MLE."""
    rows = []
    for k, c in enumerate(rois):
        start = time.perf_counter()
        post = sample_posterior(c, model, seed=k, method="importance", progress=False)
        seconds = time.perf_counter() - start
        mle = best_time(lambda cc=c: fit_mle(cc, model, laplace=False), 3)
        rows.append(
            {
                "molecule": k,
                "Pareto k-hat": post.info.get("khat", np.nan),
                "ESS": post.info.get("ess", np.nan),
                "draws scored": post.info.get("draws_scored"),
                "seconds": seconds,
                "time / MLE": seconds / mle,
            }
        )
    return pd.DataFrame(rows)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    args = parser.parse_args(argv)
    molecules, repeat, steps = (2, 20, 300) if args.quick else (20, 300, 3000)
    model, rois = _setup(molecules)
    parts = stages(model, rois)
    call = log_posterior_parts(model, rois[0], repeat)
    floor = emcee_floor(steps)
    psis = importance(model, rois)
    from _report import machine

    command = "python benchmarks/hot_path.py" + (" --quick" if args.quick else "")
    text = (
        f"Command: `{command}` on {machine()}.\n\n"
        f"**Stages of sample_posterior** ({molecules} molecules, table tier, N = 1000):\n\n"
        + parts.to_markdown(index=False, floatfmt=".3g")
        + "\n\n**One log-posterior call** (32 walkers x 225 pixels; best of "
        f"{repeat}):\n\n"
        + call.to_markdown(index=False, floatfmt=".3g")
        + f"\n\n**emcee's own cost per step** ({steps} steps, 32 walkers, free "
        "log-probability):\n\n"
        + floor.to_markdown(index=False, floatfmt=".3g")
        + "\n\n**Importance sampling instead of MCMC** (method='importance', ESS 400):\n\n"
        + psis.describe()
        .loc[["mean", "min", "50%", "max"]]
        .drop(columns="molecule")
        .to_markdown(floatfmt=".3g")
    )
    from _report import publish

    publish("hot_path", text, args.quick)
    return parts, call, floor, psis


if __name__ == "__main__":
    main()
