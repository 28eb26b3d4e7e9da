"""Axial position z: the posterior against the Cramér-Rao bound, a first-order error and the
unified interval, by coverage of the truth.

Scenes: the shipped ``astigmatic`` scene (EMCCD gain 200, readout 50 e-, 100 nm pixels,
s0 = 130 nm, Huang curves in focus at -200 nm for x and +200 nm for y, depth 400 nm) with the
emitter fixed at each z of ``Z_ASTIGMATIC`` and N of ``PHOTONS``; and the paper's symmetric
defocus (DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), Discussion:
s(z) = s0 sqrt(1 + (z / D)^2), D = 400 nm) on the same camera near focus (``Z_SYMMETRIC``).

Besides these fixed points, a point per N with z drawn per ROI from the posterior's own prior
(uniform on its z range; ``z`` blank in the tables): there a calibrated posterior must cover at
its nominal rates whatever the curve (Cook, Gelman & Rubin, JCGS 15 (2006)), while at one fixed
z a Bayesian interval need not (in focus on the symmetric curve, z = 0 is the edge of |z|).

Per point, ``MOLECULES`` ROIs, each analysed three ways:

- **posterior**: ``bayespsf.axial.posterior.z_posterior`` (z uniform on [-800, 800] nm;
  [-600, 600] for the symmetric curve), its 68% and 95% central intervals;
- **first order**: what localisation software reports (picasso's ``lpz``, ThunderSTORM's
  ``uncertainty_z``): the 6-parameter MLE's widths mapped to the nearest z of the curves in
  the metric of their Laplace covariance S, with SD ``1 / sqrt(g' S^-1 g)``
  (``bayespsf.axial.bounds.first_order_z_sd``), intervals z +- 1 and 1.96 SD;
- **pushed Laplace**: 400 draws of the widths from the MLE's Laplace approximation pushed
  through the curves (``bayespsf.axial.push.z_draws``), their 68% and 95% central intervals.

For the symmetric curve, z and -z give the same image: every method is scored on |z|, which
is what the image can tell. The posterior by its highest-density region
(``ZPosterior.covers``: a kernel density of the draws and their mirror images, so that in
focus the region is one interval across z = 0); the pushed draws by the shortest interval
holding 68% or 95% of them folded (a central interval of |z| could never cover z = 0, its
edge). And a fourth method there:

- **unified**: Feldman & Cousins' interval of |z| from the MLE widths
  (``bayespsf.axial.unified.distance_from_focus``), built to cover at every fixed z.

Reported per point and method: coverage of the true z (binomial SE), mean SD over
sqrt(CRLB_z) (``bayespsf.axial.bounds.crlb_z`` at the truth), the share of ROIs whose SD is
unusable (infinite, or wider than the z range: the first order's where both curves' slopes
vanish at the estimate), and the share of posteriors whose importance weights passed
(k-hat <= 0.7; for the other methods: the MLE converged).

    python validation/axial.py            # 100 molecules per point (25 minutes on 2 cores)
    python validation/axial.py --quick    # 6 molecules at 4 points
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import load_scene, simulate
from bayespsf.axial import (
    crlb_z,
    distance_from_focus,
    first_order_z_sd,
    nearest_z,
    z_draws,
    z_posterior,
)
from bayespsf.inference import covariance, fit_mle
from bayespsf.model import Model
from bayespsf.psf import Defocus

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

Z_ASTIGMATIC = (-600.0, -400.0, -200.0, 0.0, 200.0, 400.0, 600.0)
PHOTONS = (300.0, 1000.0, 3000.0, 10_000.0)
Z_SYMMETRIC = (0.0, 50.0, 100.0, 200.0)
PHOTONS_SYMMETRIC = (1000.0, 10_000.0)
MOLECULES = 100
PUSHED_DRAWS = 400
METHODS = ("posterior", "first order", "pushed Laplace", "unified")
RANGE = {"astigmatic": (-800.0, 800.0), "symmetric": (-600.0, 600.0)}


def scene_at(curve: str, z0: float, photons: float):
    """The scene of one point: the emitter at ``z0``, or (``z0`` NaN) z drawn per ROI from the
    posterior's own uniform prior on ``RANGE[curve]``."""
    base = load_scene("astigmatic")
    low, high = RANGE[curve]
    axial = (
        {"z": "uniform", "z_low": low, "z_high": high} if np.isnan(z0) else {"z": "fixed", "z0": z0}
    )
    if curve == "symmetric":
        axial.update(curve="symmetric", depth=400.0)
    return base.replace(axial=axial, emitter={**base.emitter, "photons": photons})


def defocus_of(scene) -> Defocus:
    return Defocus.from_scene(scene)


def _interval_hits(low68, high68, low95, high95, truth) -> tuple[bool, bool]:
    return bool(low68 <= truth <= high68), bool(low95 <= truth <= high95)


def _intervals(draws: np.ndarray, shortest: bool) -> list[float]:
    """The 68% and 95% intervals of ``draws``: central, or the shortest holding that share
    (of folded draws |z|: one that starts at the smallest draw reaches down to 0, the edge of
    the support)."""
    if not shortest:
        return list(np.quantile(draws, [0.16, 0.84, 0.025, 0.975]))
    out = []
    ordered = np.sort(draws)
    for level in (0.68, 0.95):
        k = int(np.ceil(level * len(ordered)))
        start = int(np.argmin(ordered[k - 1 :] - ordered[: len(ordered) - k + 1]))
        out += [0.0 if start == 0 else ordered[start], ordered[start + k - 1]]
    return out


def one_point(task) -> list[dict]:
    """Every method on ``MOLECULES`` ROIs at one (curve, z, N): one row per ROI and method."""
    curve, z0, photons, molecules, seed = task
    scene = scene_at(curve, z0, photons)
    model, defocus = Model.from_scene(scene), defocus_of(scene)
    z_range = RANGE[curve]
    counts, truth = simulate(scene, molecules, seed)
    true_z = truth["z"].to_numpy() if "z" in truth else np.full(molecules, z0)
    fits = fit_mle(counts, model)
    cov = covariance(fits)
    rng = np.random.default_rng(seed)
    folded = curve == "symmetric"
    rows = []
    for k in range(molecules):
        theta = np.array([0.0, 0.0, true_z[k], photons, truth["b"].iloc[k]])
        bound = crlb_z(model, defocus, theta)["z"]
        target = abs(true_z[k]) if folded else true_z[k]
        base = {
            "curve": curve,
            "z": z0,
            "N": photons,
            "true z": true_z[k],
            "sqrt CRLB_z": bound if np.isfinite(bound) else np.nan,
            "molecule": k,
        }
        post = z_posterior(counts[k], model, defocus, z_range=z_range, seed=seed * 1000 + k)
        z = post.draws["z"].to_numpy()
        if folded:
            z = np.abs(z)
            in68, in95 = post.covers(true_z[k], 0.68), post.covers(true_z[k], 0.95)
        else:
            in68, in95 = _interval_hits(*_intervals(z, False), target)
        rows.append(
            {
                **base,
                "method": "posterior",
                "estimate": float(np.mean(z)),
                "sd": float(np.std(z)),
                "in68": in68,
                "in95": in95,
                "passed": bool(post.info["converged"]),
            }
        )
        fit = fits.iloc[k]
        widths = cov[k][2:4, 2:4]
        ok = bool(fit["converged"]) and np.all(np.isfinite(widths))
        if ok:
            search = (0.0, z_range[1]) if folded else z_range
            z_hat = float(nearest_z(defocus, fit["s_x"], fit["s_y"], search, widths)[0])
            sd = float(first_order_z_sd(defocus, z_hat, widths))
            draws = np.random.default_rng(rng.integers(2**63)).multivariate_normal(
                [fit["s_x"], fit["s_y"]], widths, PUSHED_DRAWS
            )
            positive = np.all(draws > 0, axis=1)
            pushed = z_draws(defocus, draws[positive, 0], draws[positive, 1], rng, z_range, widths)
            pushed = np.abs(pushed) if folded else pushed
            p = _intervals(pushed, folded)
        else:
            z_hat, sd, pushed, p = np.nan, np.nan, np.array([np.nan]), [np.nan] * 4
        in68, in95 = _interval_hits(
            z_hat - sd, z_hat + sd, z_hat - 1.96 * sd, z_hat + 1.96 * sd, target
        )
        rows.append(
            {
                **base,
                "method": "first order",
                "estimate": z_hat,
                "sd": sd,
                "in68": in68,
                "in95": in95,
                "passed": ok,
            }
        )
        in68, in95 = _interval_hits(*p, target)
        rows.append(
            {
                **base,
                "method": "pushed Laplace",
                "estimate": float(np.mean(pushed)),
                "sd": float(np.std(pushed)),
                "in68": in68,
                "in95": in95,
                "passed": ok,
            }
        )
        if folded:
            rows.append({**base, **_unified(defocus, fit, widths, ok, target)})
    return rows


def _unified(defocus, fit, widths, ok: bool, target: float) -> dict:
    """The unified interval's row: its 68% and 95% intervals of |z| from the MLE widths; as
    estimate the root of tau's estimate (0 below focus), and no SD (it is not a posterior
    or a first-order error)."""
    row = {"method": "unified", "sd": np.nan, "passed": ok}
    if not ok:
        return {**row, "estimate": np.nan, "in68": False, "in95": False}
    i68, i95 = (
        distance_from_focus(defocus, fit["s_x"], fit["s_y"], widths, level).iloc[0]
        for level in (0.68, 0.95)
    )
    hits = _interval_hits(i68["lower"], i68["upper"], i95["lower"], i95["upper"], target)
    return {
        **row,
        "estimate": float(np.sqrt(max(i95["tau_hat"], 0.0))),
        "in68": hits[0],
        "in95": hits[1],
    }


def _median(values: pd.Series) -> float:
    """The median of the finite values; NaN where there are none (in focus on the symmetric
    curve, where z's bound is infinite)."""
    finite = values[np.isfinite(values)]
    return float(finite.median()) if len(finite) else np.nan


def summarise(per_roi: pd.DataFrame) -> pd.DataFrame:
    rows = []
    keys = ["curve", "z", "N", "method"]
    for (curve, z0, photons, method), g in per_roi.groupby(keys, sort=False, dropna=False):
        n = len(g)
        finite = np.isfinite(g["sd"])
        target = g["true z"].abs() if curve == "symmetric" else g["true z"]
        rows.append(
            {
                "curve": curve,
                "z": z0,
                "N": photons,
                "method": method,
                "ROIs": n,
                "coverage 68%": g["in68"].mean(),
                "coverage 95%": g["in95"].mean(),
                "SE 68%": np.sqrt(0.68 * 0.32 / n),
                "SE 95%": np.sqrt(0.95 * 0.05 / n),
                "sqrt CRLB (nm)": _median(g["sqrt CRLB_z"]),
                "median SD (nm)": g["sd"].median() if g["sd"].notna().any() else np.nan,
                "mean SD / sqrt CRLB": (g["sd"][finite] / g["sqrt CRLB_z"][finite]).mean(),
                "RMSE / sqrt CRLB": float(
                    np.sqrt(np.mean(((g["estimate"] - target) / g["sqrt CRLB_z"]) ** 2))
                )
                if g["sqrt CRLB_z"].notna().all()
                else np.nan,
                "SD unusable": np.nan
                if method == "unified"
                else float(np.mean(~(g["sd"] < RANGE[curve][1] - RANGE[curve][0]))),
                "passed": g["passed"].mean(),
            }
        )
    table = pd.DataFrame(rows)
    for level in ("68%", "95%"):
        nominal = float(level[:-1]) / 100
        table[f"within 2 SE {level}"] = (
            np.abs(table[f"coverage {level}"] - nominal) <= 2 * table[f"SE {level}"]
        )
    return table


def tasks(quick: bool) -> list[tuple]:
    if quick:
        points = [
            ("astigmatic", 0.0, 1000.0),
            ("astigmatic", np.nan, 3000.0),
            ("symmetric", 0.0, 1000.0),
            ("symmetric", 200.0, 10_000.0),
        ]
        molecules = 6
    else:
        points = [("astigmatic", z, n) for n in PHOTONS for z in Z_ASTIGMATIC]
        points += [("symmetric", z, n) for n in PHOTONS_SYMMETRIC for z in Z_SYMMETRIC]
        points += [("astigmatic", np.nan, n) for n in PHOTONS]
        points += [("symmetric", np.nan, n) for n in PHOTONS_SYMMETRIC]
        molecules = MOLECULES
    return [(c, z, n, molecules, 100 + i) for i, (c, z, n) in enumerate(points)]


def main(argv=None):
    args, started, stem = study(__doc__, argv, "axial", posteriors=False)
    todo = tasks(args.quick)
    workers = min(len(todo), os.cpu_count() or 1)
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            results = list(pool.map(one_point, todo))
    else:
        results = [one_point(t) for t in todo]
    per_roi = pd.DataFrame([row for rows in results for row in rows])
    per_roi.to_csv(args.out / f"{stem}_per_roi.csv", index=False)
    table = summarise(per_roi)
    figure(table, args.out / f"{stem}.png")
    fmt = {"index": False, "floatfmt": ".3g"}
    verdict = "68% and 95% coverage within 2 binomial SE of nominal, the posterior's: " + verdicts(
        table
    )
    text = (
        f"# Axial z: posterior, first-order, pushed-Laplace and unified intervals\n\n{verdict}\n\n"
        f"{table.to_markdown(**fmt)}\n\nFigure: [{stem}.png]({stem}.png)."
    )
    summary = (
        f"{verdict}\n\n{compact(table).to_markdown(**fmt)}\n\n![z SD against z](results/{stem}.png)"
    )
    return finish(args, "axial", table, text, started, summary)


def verdicts(table: pd.DataFrame) -> str:
    """How many points of each kind (curve; z fixed or drawn from the prior) the posterior's
    coverage met, in words."""
    parts = []
    for method in ("posterior", "unified"):
        rows = table[table["method"] == method]
        for (curve, drawn), g in rows.groupby(["curve", rows["z"].isna()], sort=False):
            met = int((g["within 2 SE 68%"] & g["within 2 SE 95%"]).sum())
            kind = "z drawn from the prior" if drawn else "fixed z"
            name = "" if method == "posterior" else "the unified interval, "
            parts.append(f"{name}{curve} curve, {kind}: {met} of {len(g)} points")
    return "; ".join(parts) + "."


def compact(table: pd.DataFrame) -> pd.DataFrame:
    """One row per point: each method's 68% and 95% coverage, and the posterior's SD over
    sqrt(CRLB_z) and the share of its importance weights that passed (the README's table)."""
    keys = ["curve", "z", "N"]
    posterior = table[table["method"] == "posterior"].reset_index(drop=True)
    out = posterior[keys].copy()
    short = {
        "posterior": "post",
        "first order": "1st order",
        "pushed Laplace": "pushed",
        "unified": "unified",
    }
    for method, name in short.items():
        rows = table[table["method"] == method][[*keys, "coverage 68%", "coverage 95%"]]
        rows = rows.rename(columns={"coverage 68%": f"{name} 68%", "coverage 95%": f"{name} 95%"})
        out = out.merge(rows, on=keys, how="left")  # unified: symmetric points only
    out["post SD / sqrt CRLB"] = posterior["mean SD / sqrt CRLB"]
    out["1st order SD unusable"] = table[table["method"] == "first order"]["SD unusable"].to_numpy()
    out["post passed"] = posterior["passed"]
    out["z"] = out["z"].map(lambda z: "prior" if np.isnan(z) else f"{z:g}")
    return out


def figure(table: pd.DataFrame, path: Path) -> None:
    """Left: mean SD of z over sqrt(CRLB_z) against z, per N and method (astigmatic); right:
    95% coverage against z, with the nominal 0.95 +- 2 SE."""
    astigmatic = table[table["curve"] == "astigmatic"]
    if astigmatic.empty:
        astigmatic = table
    with saved_figure(path, (11, 4), columns=2) as (left, right):
        markers = dict(zip(METHODS, ("o-", "s--", "^:", "d-."), strict=True))
        for (method, photons), g in astigmatic.groupby(["method", "N"], sort=False):
            label = f"{method}, N = {photons:g}"
            left.plot(g["z"], g["mean SD / sqrt CRLB"], markers[method], label=label)
            right.plot(g["z"], g["coverage 95%"], markers[method], label=label)
        left.axhline(1.0, color="grey", lw=0.8)
        left.set_yscale("log")
        left.set_xlabel("z (nm)")
        left.set_ylabel("mean SD of z / sqrt(CRLB_z)")
        se = astigmatic["SE 95%"].max()
        right.axhspan(0.95 - 2 * se, 0.95 + 2 * se, color="grey", alpha=0.3, label="0.95 +- 2 SE")
        right.set_xlabel("z (nm)")
        right.set_ylabel("95% coverage of the true z")
        right.legend(fontsize=5, ncol=2)


if __name__ == "__main__":
    main()
