"""Time per molecule to reach a posterior ESS, per EMCCD likelihood tier, and emcee moves.

For molecules of the `emccd-typical` scene (spot fixed at the centre): for each tier, the wall
time of `sample_posterior` to ESS 400 and 1000 on every parameter, as a ratio to one `fit_mle`
of the same ROI with the same tier in the same run, and the log-posterior's evaluations per
second (32 walkers x 15x15 pixels per call). Then, on the `table` tier, the integrated
autocorrelation time of the default moves (``laplace-de``: 0.8 Laplace independence proposals,
0.15 DE, 0.05 DE-snooker) against 0.8 DE + 0.2 DE-snooker alone and emcee's stretch move.
The `exact` tier is measured at ESS 400 only (minutes per molecule).

    python benchmarks/posterior.py            # full run, rewrites its section of README.md
    python benchmarks/posterior.py --quick    # one molecule, ESS 400 (moves: 100), table tier,
                                              # prints only
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf._runtime import best_time
from bayespsf.inference import fit_mle, sample_posterior
from bayespsf.model import Model
from bayespsf.theory import scene_params


def run(quick: bool) -> tuple[pd.DataFrame, pd.DataFrame]:
    scene = load_scene("emccd-typical").replace(emitter={"position": "fixed"})
    molecules = 1 if quick else 3
    counts, _ = simulate(scene, molecules, seed=7)
    tiers = ["table"] if quick else ["table", "high-gain", "gaussian", "exact"]
    rows = []
    for tier in tiers:
        model = Model.from_scene(scene, likelihood=tier)
        c = model.check_counts(counts[0])
        z = model.to_unconstrained(scene_params(scene)) + 1e-3 * np.random.default_rng(
            0
        ).standard_normal((32, 6))
        model.log_posterior(z, c)  # builds the table once
        evals = 32 / best_time(lambda m=model, zz=z, cc=c: m.log_posterior(zz, cc), 5)
        targets = [400] if (quick or tier == "exact") else [400, 1000]
        for ess in targets:
            for k in range(1 if tier == "exact" else molecules):
                mle = best_time(
                    lambda m=model, i=k: fit_mle(counts[i], m), 1 if tier == "exact" else 3
                )
                start = time.perf_counter()
                post = sample_posterior(counts[k], model, seed=k, ess=ess, progress=False)
                seconds = time.perf_counter() - start
                rows.append(
                    {
                        "tier": tier,
                        "target ESS": ess,
                        "molecule": k,
                        "converged": post.converged,
                        "steps": post.info["steps"],
                        "min ess_bulk": post.summary()["ess_bulk"].min(),
                        "seconds": seconds,
                        "MLE seconds": mle,
                        "time / MLE": seconds / mle,
                        "log-posterior evals/s": evals,
                    }
                )
    model = Model.from_scene(scene)
    moves = []
    for name in ["laplace-de", "de-snooker", "stretch"]:
        for k in range(molecules):
            post = sample_posterior(
                counts[k], model, seed=k, ess=100 if quick else 400, moves=name, progress=False
            )
            moves.append(
                {
                    "moves": name,
                    "molecule": k,
                    "max tau (steps)": post.tau.max(),
                    "steps": post.info["steps"],
                    "acceptance": post.info["acceptance"],
                }
            )
    return pd.DataFrame(rows), pd.DataFrame(moves)


def markdown(costs: pd.DataFrame, moves: pd.DataFrame, command: str) -> str:
    from _report import machine

    return (
        f"Command: `{command}` on {machine()}.\n\n"
        + costs.to_markdown(index=False, floatfmt=".3g")
        + "\n\n"
        + moves.to_markdown(index=False, floatfmt=".3g")
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    args = parser.parse_args()
    costs, moves = run(args.quick)
    command = "python benchmarks/posterior.py" + (" --quick" if args.quick else "")
    text = markdown(costs, moves, command)
    from _report import publish

    publish("posterior", text, args.quick)
    return costs, moves


if __name__ == "__main__":
    main()
