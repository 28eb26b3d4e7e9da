"""What accuracy costs in time: the accuracy-time frontier of the width's posterior.

For molecules of the ``emccd-typical`` scene at low, medium and high photon counts, every EMCCD
likelihood tier is run at several effective-sample-size targets, beside the two cheap ends a
user might pick instead of a posterior: the maximum-likelihood fit with the Cramér-Rao bound
at the estimate as its error bar ("MLE + CRLB"), and the Laplace approximation (the MLE with the
inverse observed information). For each run, per molecule:

- time, as a ratio to one maximum-likelihood fit of the same ROI (``table`` tier, best of 3) in
  the same process: machines differ, ratios travel;
- the error of the posterior SD of s_x against a reference posterior of the same ROI, and the
  posterior mean's offset from the reference mean in reference SDs;
- whether the central 68% and 95% intervals hold the true s_x (coverage over molecules).

The ``table`` tier is also run by Laplace importance sampling (``method="importance"``, PSIS,
falling back to MCMC where k-hat > 0.7) at the same ESS targets.

Where JAX is installed, the JAX backend adds rows ``importance (JAX)`` and ``auto (JAX)``:
``sample_many(..., backend="jax", method=...)`` for the tiers it supports (``table``,
``high-gain``, ``gaussian``, ``poisson``; ``--quick``: ``table`` at ESS 100) at the same ESS
targets, scored like the NumPy rows. The backend works on stacks: each photon level's molecules
run as one stack, timed after a warm-up call on the same stack (compilation excluded), and a
molecule's time is the stack's over its molecules. The backend pads a stack to its fixed chunk
sizes, so a stack of a few molecules pays for a whole chunk: a larger stack costs less per
molecule. On the CPU, JAX's programs use every core, where each NumPy row runs in one worker
process. Without JAX these rows are skipped, and the run and its report say so.

The reference is a long ``table``-tier run (ESS 40 000 on every parameter), corrected to the
``exact`` law by importance weights on 400 of its draws (the weighted against the unweighted SD
of those draws; the table is within 4e-5 of exact per pixel, so the correction is small and it
is reported). An ``exact``-tier chain of that length would take hours per molecule.

Run it as ``bayespsf bench [--quick]`` or ``python benchmarks/frontier.py`` (which also writes
its section of ``benchmarks/README.md``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf._runtime import best_time
from bayespsf.inference.estimators import fit_mle
from bayespsf.inference.sampling import sample_posterior
from bayespsf.inference.summary import quantile_column
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.theory import crlb

SX = PARAMETER_NAMES.index("s_x")


@dataclass(frozen=True)
class Plan:
    """What a frontier run covers."""

    photons: dict = field(default_factory=lambda: {"low": 200, "medium": 1000, "high": 5000})
    molecules: int = 12
    tiers: tuple = ("table", "high-gain", "gaussian", "poisson")
    budgets: tuple = (100, 400, 1000, 4000)
    exact_budgets: tuple = (100, 400)
    exact_molecules: int = 2
    reference_ess: float = 40_000.0
    reweighted_draws: int = 400
    scene: str = "emccd-typical"
    seed: int = 2026
    jax_tiers: tuple = ("table", "high-gain", "gaussian", "poisson")
    jax_budgets: tuple | None = None  # the JAX rows' ESS targets (None: ``budgets``)


FULL = Plan()
QUICK = Plan(
    photons={"low": 200, "high": 5000},
    molecules=1,
    tiers=("table", "high-gain", "gaussian", "poisson"),
    budgets=(100, 1000),
    exact_budgets=(),
    exact_molecules=0,
    reference_ess=4000.0,
    reweighted_draws=50,
    jax_tiers=("table",),
    jax_budgets=(100,),
)
JAX_METHODS = ("importance", "auto")
JAX_MISSING = 'JAX rows skipped: JAX is not installed (pip install "bayespsf[jax]").'
REFERENCE = ("ref mean", "ref sd", "ref exact correction", "ref converged", "ref ess")


def _row(level, n_photons, k, method, tier, budget, seconds, unit, sd, mean, q68, q95, truth):
    return {
        "level": level,
        "N": n_photons,
        "molecule": k,
        "method": method,
        "tier": tier,
        "ESS target": budget,
        "seconds": seconds,
        "time / MLE": seconds / unit,
        "sd": sd,
        "mean": mean,
        "covers 68%": q68[0] <= truth <= q68[1],
        "covers 95%": q95[0] <= truth <= q95[1],
    }


def _gaussian_row(level, n_photons, k, method, seconds, unit, mean, sd, truth):
    """A row of a cheap end: a point estimate with a Gaussian error bar ``sd``."""
    q68, q95 = (mean - sd, mean + sd), (mean - 1.96 * sd, mean + 1.96 * sd)
    return _row(
        level, n_photons, k, method, "table", np.nan, seconds, unit, sd, mean, q68, q95, truth
    )


def _reference(counts, scene, plan, seed):
    """Reference mean and SD of s_x: a long table run, its SD corrected to the exact law."""
    table = Model.from_scene(scene, likelihood="table")
    exact = Model.from_scene(scene, likelihood="exact")
    post = sample_posterior(counts, table, seed=seed, ess=plan.reference_ess, progress=False)
    draws = post.draws().to_numpy()
    pick = draws[np.linspace(0, len(draws) - 1, plan.reweighted_draws).astype(int)]
    log_w = exact.log_likelihood(counts, pick) - table.log_likelihood(counts, pick)
    w = np.exp(log_w - log_w.max())
    x = pick[:, SX]
    weighted_mean = np.sum(w * x) / np.sum(w)
    weighted_sd = np.sqrt(np.sum(w * (x - weighted_mean) ** 2) / np.sum(w))
    correction = weighted_sd / x.std() - 1.0
    sd = draws[:, SX].std(ddof=1) * (1.0 + correction)
    return {
        "ref mean": draws[:, SX].mean() + (weighted_mean - x.mean()),
        "ref sd": sd,
        "ref exact correction": correction,
        "ref converged": post.converged,
        "ref ess": float(post.summary()["ess_bulk"].min()),
    }


def molecule(task) -> list[dict]:
    """Every method on one ROI: the rows of ``frontier`` for it."""
    level, n_photons, k, counts, truth, scene, plan = task
    seed = int(np.random.SeedSequence([plan.seed, n_photons, k]).generate_state(1)[0])
    table = Model.from_scene(scene, likelihood="table")
    fit_mle(counts, table)  # builds the table once, outside any timing
    unit = best_time(lambda: fit_mle(counts, table, laplace=False), 3)
    # the reference has its own stream: a run that shared it would be the first part of the
    # reference chain, and its error against it would be understated
    reference_seed = int(np.random.SeedSequence([plan.seed, n_photons, k, 1]).generate_state(1)[0])
    reference = _reference(counts, scene, plan, reference_seed)
    rows = []

    start = time.perf_counter()
    fit = fit_mle(counts, table, laplace=False).iloc[0]
    ok = bool(fit["converged"])
    sd = float(crlb(table, fit[list(PARAMETER_NAMES)].to_numpy(float))["s_x"]) if ok else np.nan
    seconds = time.perf_counter() - start
    mean = float(fit["s_x"])
    rows.append(_gaussian_row(level, n_photons, k, "MLE + CRLB", seconds, unit, mean, sd, truth))
    start = time.perf_counter()
    fit = fit_mle(counts, table).iloc[0]
    seconds = time.perf_counter() - start
    mean, sd = float(fit["s_x"]), float(fit["sd_s_x"])
    rows.append(_gaussian_row(level, n_photons, k, "Laplace", seconds, unit, mean, sd, truth))

    runs = [("posterior", tier, b) for tier in plan.tiers for b in plan.budgets]
    runs += [("importance", "table", b) for b in plan.budgets]
    if k < plan.exact_molecules:
        runs += [("posterior", "exact", b) for b in plan.exact_budgets]
    for method, tier, budget in runs:
        model = Model.from_scene(scene, likelihood=tier)
        options = {"method": "importance"} if method == "importance" else {}
        start = time.perf_counter()
        try:
            post = sample_posterior(counts, model, seed=seed, ess=budget, progress=False, **options)
        except ValueError as error:  # a tier without support on this ROI (BayespsfInputError)
            rows.append(
                {
                    **_row(
                        level,
                        n_photons,
                        k,
                        method,
                        tier,
                        budget,
                        np.nan,
                        unit,
                        np.nan,
                        np.nan,
                        (0, 0),
                        (0, 0),
                        truth,
                    ),
                    "note": str(error)[:80],
                }
            )
            continue
        seconds = time.perf_counter() - start
        draws = post.draws()["s_x"]
        q = draws.quantile([0.025, 0.16, 0.84, 0.975]).to_numpy()
        row = _row(
            level,
            n_photons,
            k,
            method,
            tier,
            budget,
            seconds,
            unit,
            draws.std(),
            draws.mean(),
            q[1:3],
            q[[0, 3]],
            truth,
        )
        row.update(
            converged=post.converged,
            steps=post.info.get("steps", 0),
            ess=float(post.info["ess"])
            if post.method == "importance"
            else float(post.summary()["ess_bulk"].min()),
            fell_back_to_mcmc=method == "importance" and post.method == "mcmc",
        )
        rows.append(row)
    for row in rows:
        _score(row, {**reference, "MLE seconds": unit})
    return rows


def _score(row: dict, reference: dict) -> None:
    """Add the reference columns to ``row`` and its errors against the reference."""
    row.update(reference)
    row["sd error"] = row["sd"] / reference["ref sd"] - 1.0
    row["mean offset"] = (row["mean"] - reference["ref mean"]) / reference["ref sd"]


def jax_installed() -> bool:
    """Whether the JAX backend can run here (``check_backend("jax")`` passes)."""
    from bayespsf.errors import BayespsfInputError
    from bayespsf.inference.backends import check_backend

    try:
        check_backend("jax")
    except BayespsfInputError:
        return False
    return True


def jax_rows(plan: Plan, tasks: list, rows: list[dict], progress=print) -> list[dict]:
    """The JAX backend's rows (module docstring): per photon level, tier, method and ESS
    target, the level's molecules as one stack through ``sample_many(backend="jax")``, timed
    after a warm-up call on the same stack; scored against the references of ``rows`` (the
    NumPy rows of the same molecules, which also give each molecule's MLE time)."""
    from bayespsf.inference.backends import device_name, release_programs
    from bayespsf.parallel import sample_many

    known = {(r["N"], r["molecule"]): r for r in rows}
    out = []
    budgets = plan.jax_budgets or plan.budgets
    # a tier's programs serve every level (same stack shape): compiled once per tier, then
    # released, so that few memory maps are held at once
    for tier, (level, n_photons) in itertools.product(plan.jax_tiers, plan.photons.items()):
        if level == next(iter(plan.photons)):
            release_programs()
        part = [task for task in tasks if task[0] == level]
        stack, scene = np.stack([task[3] for task in part]), part[0][5]
        seed = int(np.random.SeedSequence([plan.seed, n_photons, 2]).generate_state(1)[0])
        model = Model.from_scene(scene, likelihood=tier)
        for method, budget in itertools.product(JAX_METHODS, budgets):
            run = {"seed": seed, "workers": 1, "progress": False, "backend": "jax"}
            run |= {"method": method, "ess": budget}
            sample_many(stack, model, **run)  # compiles the stack's programs: not timed
            start = time.perf_counter()
            table = sample_many(stack, model, **run)
            seconds = (time.perf_counter() - start) / len(part)
            for task, (_, r) in zip(part, table.iterrows(), strict=True):
                k, truth = task[2], task[4]
                first = known[(n_photons, k)]
                q = [r[quantile_column("s_x", p)] for p in (0.025, 0.16, 0.84, 0.975)]
                row = _row(level, n_photons, k, f"{method} (JAX)", tier, budget, seconds,
                           first["MLE seconds"], r["s_x_sd"], r["s_x_mean"], q[1:3],
                           q[::3], truth)  # fmt: skip
                row.update(converged=bool(r["converged"]), steps=r["steps"], ess=r["s_x_ess"])
                row.update(fell_back_to_mcmc=r["method"] == "mcmc", device=device_name())
                _score(row, {key: first[key] for key in (*REFERENCE, "MLE seconds")})
                out.append(row)
            progress(f"frontier: JAX, {level} N, {tier}, {method}, ESS {budget}")
    return out


def frontier(plan: Plan = FULL, workers: int | None = None, progress=print) -> pd.DataFrame:
    """One row per molecule and method (see the module docstring); ``workers`` local
    processes (default: all cores; 1 runs here)."""
    from bayespsf.parallel import local_executor

    base = load_scene(plan.scene)
    tasks = []
    for level, n_photons in plan.photons.items():
        scene = base.replace(emitter={"photons": float(n_photons)})
        counts, truth = simulate(scene, plan.molecules, seed=plan.seed + int(n_photons))
        tasks += [
            (level, n_photons, k, counts[k], float(truth["s_x"].iloc[k]), scene, plan)
            for k in range(plan.molecules)
        ]
    rows = []
    if workers == 1:
        for i, task in enumerate(tasks):
            rows += molecule(task)
            progress(f"frontier: {i + 1}/{len(tasks)} molecules")
    else:
        with local_executor(workers) as pool:
            for i, result in enumerate(pool.map(molecule, tasks)):
                rows += result
                progress(f"frontier: {i + 1}/{len(tasks)} molecules")
    if not jax_installed():  # after the pool: no worker is forked from a process running JAX
        progress(JAX_MISSING)
    elif plan.jax_tiers:
        rows += jax_rows(plan, tasks, rows, progress)
    return pd.DataFrame(rows)


def summarise(rows: pd.DataFrame) -> pd.DataFrame:
    """Per photon level, method, tier and ESS target: median time / MLE, the median absolute
    and the RMS error of the posterior SD of s_x against the reference and the RMS offset of
    its mean (reference SDs), over the molecules whose reference converged (a dim molecule's
    heavy-tailed posterior can defeat the reference run: those are counted, not compared), the
    68% / 95% coverage of the true s_x with its binomial SE (all molecules), and the median ESS
    reached."""
    keys = ["level", "N", "method", "tier", "ESS target"]
    ok = rows[np.isfinite(rows["sd"])]

    def one(g):
        n = len(g)
        c68, c95 = g["covers 68%"].mean(), g["covers 95%"].mean()
        compared = g[g["ref converged"].astype(bool)]
        return pd.Series(
            {
                "molecules": n,
                "reference converged": len(compared),
                "time / MLE": _median(g["time / MLE"]),
                "seconds": _median(g["seconds"]),
                "SD error (median |.|)": np.median(np.abs(compared["sd error"])),
                "SD error (RMS)": np.sqrt(np.mean(compared["sd error"] ** 2)),
                "mean offset (RMS, ref SDs)": np.sqrt(np.mean(compared["mean offset"] ** 2)),
                "coverage 68%": c68,
                "coverage 68% SE": np.sqrt(0.68 * 0.32 / n),
                "coverage 95%": c95,
                "coverage 95% SE": np.sqrt(0.95 * 0.05 / n),
                "median ESS": _median(g["ess"]) if "ess" in g else np.nan,
            }
        )

    table = ok.groupby(keys, dropna=False, sort=False).apply(one, include_groups=False)
    failed = rows[~np.isfinite(rows["sd"])].groupby(keys, dropna=False, sort=False).size()
    table["ROIs it cannot score"] = failed.reindex(table.index).fillna(0).astype(int)
    return table.reset_index()


def _median(values) -> float:
    """Median of the finite values, NaN if none (pandas 2.3 warns on an all-NaN median)."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(np.median(finite)) if finite.size else np.nan


def which_tier(summary: pd.DataFrame) -> pd.DataFrame:
    """One row per method and tier at an ESS target of 400 (or the cheap ends): time and SD
    error per photon level, and coverage pooled over the levels."""
    part = summary[(summary["ESS target"] == 400) | summary["ESS target"].isna()]
    out = []
    for (method, tier), g in part.groupby(["method", "tier"], sort=False):
        n = g["molecules"].sum()
        row = {"method": method, "tier": tier}
        for _, r in g.iterrows():
            row[f"time / MLE ({r['level']})"] = r["time / MLE"]
            row[f"SD error ({r['level']})"] = r["SD error (median |.|)"]
        for level in (68, 95):
            pooled = np.sum(g[f"coverage {level}%"] * g["molecules"]) / n
            row[f"coverage {level}%"] = pooled
            row[f"coverage {level}% SE"] = np.sqrt(level / 100 * (1 - level / 100) / n)
        out.append(row)
    return pd.DataFrame(out)


def figure(summary: pd.DataFrame, path) -> None:
    """Error of the posterior SD of s_x against time per molecule, one curve per tier and one
    panel per photon level; the cheap ends as single markers."""
    import matplotlib.pyplot as plt

    levels = list(dict.fromkeys(summary["level"]))
    fig, axes = plt.subplots(1, len(levels), figsize=(4.2 * len(levels), 4), squeeze=False)
    for ax, level in zip(axes[0], levels, strict=True):
        part = summary[summary["level"] == level]
        curves = part[part["ESS target"].notna()]
        for i, ((method, tier), g) in enumerate(curves.groupby(["method", "tier"])):
            g = g.sort_values("ESS target")
            label = {"posterior": tier, "importance": f"{tier}, importance (PSIS)"}
            label = label.get(method, f"{tier}, {method}")
            style = {"posterior": "o-", "importance": "s--"}.get(method, "^:")
            ax.plot(g["time / MLE"], g["SD error (median |.|)"], style, color=f"C{i}", label=label)
            for _, r in g.iterrows():
                ax.annotate(
                    f"{r['ESS target']:g}",
                    (r["time / MLE"], r["SD error (median |.|)"]),
                    fontsize=6,
                    xytext=(2, 2),
                    textcoords="offset points",
                )
        for marker, method in (("s", "MLE + CRLB"), ("D", "Laplace")):
            g = part[part["method"] == method]
            ax.plot(
                g["time / MLE"],
                g["SD error (median |.|)"],
                marker,
                color="k",
                mfc="none",
                label=method,
            )
        ax.set(
            xscale="log",
            yscale="log",
            xlabel="time per molecule / one MLE fit",
            ylabel="median |error| of the SD of s_x",
            title=f"{level} N ({part['N'].iloc[0]:g})",
        )
        ax.grid(True, which="both", lw=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(
        "Accuracy against time (labels: ESS target); reference: long exact-law posterior",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


__all__ = [
    "FULL",
    "JAX_METHODS",
    "JAX_MISSING",
    "QUICK",
    "Plan",
    "figure",
    "frontier",
    "jax_installed",
    "jax_rows",
    "molecule",
    "summarise",
    "which_tier",
]


def report(rows: pd.DataFrame, out, command: str) -> str:
    """Write ``frontier.csv`` (every run), ``frontier-summary.csv``, ``frontier.png`` and
    ``frontier.md`` into ``out``; return the markdown (the which-tier table, then the summary)."""
    from pathlib import Path

    from bayespsf._runtime import machine

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(rows)
    rows.to_csv(out / "frontier.csv", index=False)
    summary.to_csv(out / "frontier-summary.csv", index=False)
    figure(summary, out / "frontier.png")
    correction = rows.groupby(["N", "molecule"])["ref exact correction"].first().abs().max()
    on_jax = rows["method"].str.endswith("(JAX)")
    if on_jax.any():
        jax_note = (
            '\n\nRows `(JAX)`: `sample_many(backend="jax")` on '
            f"{', '.join(rows.loc[on_jax, 'device'].astype(str).unique())}, each level's "
            "molecules as one stack, timed after a warm-up call on the same stack (compilation "
            "excluded); time per molecule = the stack's time / its molecules (the backend pads a "
            "stack to fixed chunk sizes, so a small stack pays for a whole chunk; on the CPU, "
            "JAX uses every core)."
        )
    else:
        jax_note = "" if jax_installed() else "\n\n" + JAX_MISSING
    shown = summary.drop(columns=["coverage 68% SE", "coverage 95% SE", "seconds"])
    text = (
        f"Command: `{command}` on {machine()}.\n\n"
        "### Which tier: ESS target 400 and the cheap ends\n\n"
        + which_tier(summary).to_markdown(index=False, floatfmt=".3g")
        + "\n\n### Every tier and ESS target\n\n"
        + shown.to_markdown(index=False, floatfmt=".3g")
        + f"\n\nReference: `table` tier at ESS {rows['ref ess'].min():.0f}+ (smallest over "
        f"molecules) corrected to the exact law; the largest correction of its SD was "
        f"{correction:.1e} (relative). Figure: frontier.png; every run: frontier.csv."
        + jax_note
        + "\n"
    )
    (out / "frontier.md").write_text(text)
    return text
