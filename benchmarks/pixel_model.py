"""Pixel-integrated against sampled Gaussian: the bias of s_x against a/s0, and what each costs.

Many fitters model a pixel by the Gaussian density at its centre times its area (the paper's
Eq. A3.1, `Model(pixel_model="sampled")`) instead of the integral over the pixel (our default).
A camera integrates, so on real data the sampled model's width converges to the width of the
pixel-convolved spot, ``sqrt(s0**2 + a**2 / 12)`` (the paper's Eq. tophat), not to s0. For the
`ideal` scene (photon counting, N = 1000, b = 10, s0 = 130 nm, spot at a random sub-pixel
position, ROI covering +-4 s0): per a/s0, the mean and SD of the MLE of s_x under each pixel
model over 300 images, the noiseless limit (the MLE on the expected image at N = 1e8), the
Eq. tophat prediction, and for 20 molecules per a/s0 the posterior mean's bias and the 68%
interval's coverage of s0. Cost: one log-posterior call (32 walkers) and one posterior per
molecule under each pixel model, as ratios sampled / integrated in the same run.

    python benchmarks/pixel_model.py           # full run, rewrites its section of README.md
    python benchmarks/pixel_model.py --quick   # two pixel sizes, few images, prints only
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

S0 = 130.0
RATIOS = (0.3, 0.5, 0.77, 1.0, 1.5, 2.0, 2.5)


def scene_for(ratio: float, photons: float = 1000.0, background: float = 10.0):
    a = ratio * S0
    roi = max(7, 2 * int(np.ceil(4 * S0 / a)) + 1)
    return load_scene("ideal").replace(
        geometry={"pixel_size": a, "roi": roi},
        emitter={"photons": photons, "s0x": S0, "s0y": S0},
        background={"mean": background},
    )


def noiseless_limit(ratio: float, pixel_model: str) -> float:
    """s_x / s0 of the MLE on the (rounded) expected image of a very bright spot."""
    scene = scene_for(ratio).replace(emitter={"position": "fixed"})
    truth = np.array([0.0, 0.0, S0, S0, 1e8, 100.0])
    image = np.round(Model.from_scene(scene).expected(truth))
    return float(fit_mle(image, Model.from_scene(scene, pixel_model=pixel_model))["s_x"][0]) / S0


def run(quick: bool) -> pd.DataFrame:
    ratios = (0.5, 2.0) if quick else RATIOS
    images, posteriors = (20, 2) if quick else (300, 20)
    rows = []
    for k, ratio in enumerate(ratios):
        scene = scene_for(ratio)
        counts, _ = simulate(scene, images, seed=100 + k)
        z = Model.from_scene(scene).to_unconstrained([0.0, 0.0, S0, S0, 1000.0, 10.0])
        walkers = z + 1e-3 * np.random.default_rng(k).standard_normal((32, 6))
        row = {
            "a/s0": ratio,
            "roi": scene.geometry["roi"],
            "Eq. tophat sqrt(1 + (a/s0)^2/12)": np.sqrt(1 + ratio**2 / 12),
        }
        seconds = {}
        for pixel_model in ("integrated", "sampled"):
            model = Model.from_scene(scene, pixel_model=pixel_model)
            fits = fit_mle(counts, model)
            ok = fits[fits["converged"]]
            sx = ok["s_x"].to_numpy() / S0
            row[f"{pixel_model}: MLE mean s_x / s0"] = sx.mean()
            row[f"{pixel_model}: MLE mean err"] = sx.std(ddof=1) / np.sqrt(len(sx))
            row[f"{pixel_model}: noiseless limit / s0"] = noiseless_limit(ratio, pixel_model)
            c = model.check_counts(counts[0])
            row[f"{pixel_model}: log-posterior call s"] = best_time(
                lambda m=model, cc=c, w=walkers: m.log_posterior(w, cc), 20
            )
            means, covered, spent = [], [], []
            for i in range(posteriors):
                start = time.perf_counter()
                post = sample_posterior(counts[i], model, seed=i, progress=False)
                spent.append(time.perf_counter() - start)
                draws = post.draws()["s_x"]
                lo, hi = draws.quantile([0.16, 0.84])
                means.append(draws.mean() / S0)
                covered.append(lo <= S0 <= hi)
            row[f"{pixel_model}: posterior mean s_x / s0"] = np.mean(means)
            row[f"{pixel_model}: posterior mean err"] = np.std(means, ddof=1) / np.sqrt(posteriors)
            row[f"{pixel_model}: 68% coverage of s0"] = np.mean(covered)
            seconds[pixel_model] = np.median(spent)
        row["log-posterior cost sampled / integrated"] = (
            row["sampled: log-posterior call s"] / row["integrated: log-posterior call s"]
        )
        row["posterior time sampled / integrated"] = seconds["sampled"] / seconds["integrated"]
        rows.append(row)
        print(f"a/s0 = {ratio}", flush=True)
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame, command: str) -> str:
    from _report import machine

    shown = df.drop(columns=[c for c in df.columns if c.endswith("call s")])
    return f"Command: `{command}` on {machine()}.\n\n" + shown.T.to_markdown(floatfmt=".4g")


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    args = parser.parse_args(argv)
    df = run(args.quick)
    text = markdown(df, "python benchmarks/pixel_model.py" + (" --quick" if args.quick else ""))
    from _report import publish

    publish("pixel_model", text, args.quick)
    return df


if __name__ == "__main__":
    main()
