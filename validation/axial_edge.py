"""Coverage at the edge of |z|: credible intervals and the unified interval on the paper's
symmetric curve near focus, in the Gaussian limit, by quadrature.

On a curve even about focus the image tells only ``tau = z^2``; near focus the widths are
linear in tau (``s^2 = s0^2 (1 + tau / D^2)``), so tau's estimate is Gaussian with an SD
``sigma`` that does not depend on tau, and tau >= 0. In units of ``sigma`` this is the mean
``mu = tau / sigma >= 0`` of a unit Gaussian observed once, ``x ~ N(mu, 1)``: a Gaussian mean
bounded at 0 (Mandelkern, Statist. Sci. 17 (2002)). The coverage of an interval at each
fixed ``mu`` is then an integral over ``x``, computed here by quadrature (no Monte Carlo
error):

- **posterior, z uniform**: the prior of ``bayespsf.axial.posterior.z_posterior``; z's
  posterior density is ``exp(-(z^2/sigma - x)^2 / 2)``, and the interval is its
  highest-density region (``ZPosterior.hdi``);
- **posterior, tau uniform**: the Jeffreys prior near focus (tau's information is constant
  there), with the highest-density region of tau;
- **unified**: Feldman & Cousins' interval (``bayespsf.axial.unified.bounded_mean_interval``),
  which holds its level at every ``mu`` by construction.

The table also places the simulated points of ``validation/axial.py`` on this scale:
``mu = z^2 / sigma``, with ``sigma`` from the widths' Cramér-Rao covariance in focus (the
astigmatic scene's camera, background 10 photons, s0 = 130 nm, D = 400 nm). And it checks the
unified interval where the Gaussian limit is only approximate: on simulated ROIs of that
scene, from their MLE widths and Laplace covariance, 2 000 per point (binomial SE 0.010 at
68%, 0.005 at 95%).

    python validation/axial_edge.py           # 20 means, 5 201 x; 12 simulated points
    python validation/axial_edge.py --quick   # 5 means, 1 301 x; 2 points of 40 ROIs
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import simulate
from bayespsf.axial import bounded_mean_interval, distance_from_focus
from bayespsf.inference import covariance, fit_mle
from bayespsf.model import Model
from bayespsf.theory import fisher_matrix

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study
from axial import defocus_of, scene_at

LEVELS = (0.68, 0.95)
MEANS = (
    0.0,
    0.05,
    0.1,
    0.2,
    0.3,
    0.4,
    0.5,
    0.6,
    0.8,
    1.0,
    1.25,
    1.5,
    2.0,
    2.5,
    3.0,
    4.0,
    5.0,
    6.0,
    8.0,
    10.0,
)
QUICK_MEANS = (0.0, 0.25, 1.0, 3.0, 10.0)
SIMULATED = {1000.0: (0.0, 50.0, 100.0, 200.0), 10_000.0: (0.0, 50.0, 100.0, 200.0)}
UNIFIED_POINTS = [
    (n, z) for n in (1000.0, 10_000.0) for z in (0.0, 25.0, 50.0, 100.0, 200.0, 400.0)
]
UNIFIED_MOLECULES = 2000
QUICK_UNIFIED = ([(1000.0, 0.0), (10_000.0, 100.0)], 40)


def _level_set(log_density: np.ndarray, mass: np.ndarray, prob: float) -> float:
    """The log density at which the highest-density region holds ``prob``: ``log_density``
    and ``mass`` per cell of a grid."""
    order = np.argsort(-log_density)
    held = np.cumsum(mass[order]) / mass.sum()
    return float(log_density[order][np.searchsorted(held, prob)])


def _thresholds(x: np.ndarray, prob: float, prior: str) -> np.ndarray:
    """Per observation ``x``: how far (in ``(t - x)^2 / 2``, t the parameter the region is
    taken in) the highest-density region reaches, so that ``mu`` is inside when
    ``(mu - x)^2 / 2 <= h``; for the z-uniform prior in z (``t = z^2``), else in tau."""
    out = np.empty(len(x))
    for i, xi in enumerate(x):
        top = max(xi, 0.0) + 10.0
        if prior == "z":
            z = np.linspace(0.0, np.sqrt(top), 8001)[1:]  # z / sqrt(sigma)
            log_density = -0.5 * (z * z - xi) ** 2
        else:
            z = np.linspace(0.0, top, 8001)[1:]  # tau / sigma
            log_density = -0.5 * (z - xi) ** 2
        out[i] = -_level_set(log_density, np.exp(log_density - log_density.max()), prob)
    return out


def coverage_table(means, x_points: int) -> pd.DataFrame:
    """Each interval's coverage at each fixed mean: the integral over ``x ~ N(mu, 1)`` of
    whether the interval from ``x`` holds ``mu`` (trapezoid rule on one grid of ``x`` from -8
    to max(means) + 8, whose regions are computed once)."""
    x = np.linspace(-8.0, max(means) + 8.0, x_points)
    rows = []
    for prob in LEVELS:
        reach = {prior: _thresholds(x, prob, prior) for prior in ("z", "tau")}
        lower, upper = bounded_mean_interval(x, prob)
        for mu in means:
            weight = np.exp(-0.5 * (x - mu) ** 2) / np.sqrt(2 * np.pi)
            row = {"mu": mu, "level": prob}
            for prior, h in reach.items():
                inside = 0.5 * (mu - x) ** 2 <= h
                row[f"posterior, {prior} uniform"] = float(np.trapezoid(weight * inside, x))
            inside = (lower <= mu) & (mu <= upper)
            row["unified"] = float(np.trapezoid(weight * inside, x))
            rows.append(row)
    return pd.DataFrame(rows)


def tau_sd(photons: float) -> float:
    """tau's SD in focus (nm^2) from the widths' Cramér-Rao covariance on the symmetric curve
    (module docstring)."""
    scene = scene_at("symmetric", 0.0, photons)
    s0 = scene.emitter["s0x"]
    theta = np.array([0.0, 0.0, s0, s0, photons, scene.background["mean"]])
    widths = np.linalg.inv(fisher_matrix(Model.from_scene(scene), theta))[2:4, 2:4]
    return float(distance_from_focus(defocus_of(scene), s0, s0, widths)["tau_sd"].iloc[0])


def simulated(points, molecules: int) -> pd.DataFrame:
    """The unified interval on simulated ROIs beyond the Gaussian limit: per (N, z), the
    MLE widths and their Laplace covariance of ``molecules`` ROIs of the symmetric scene, the
    coverage of their 68% and 95% intervals, and tau's z-score about the truth (mean, SD)."""
    rows = []
    for seed, (photons, z) in enumerate(points):
        scene = scene_at("symmetric", z, photons)
        counts, _ = simulate(scene, molecules, 500 + seed)
        fits = fit_mle(counts, Model.from_scene(scene))
        widths = np.stack([c[2:4, 2:4] for c in covariance(fits)])
        ok = fits["converged"].to_numpy() & np.all(np.isfinite(widths), axis=(1, 2))
        row = {"N": photons, "z (nm)": z, "ROIs": int(ok.sum()), "fits failed": int((~ok).sum())}
        for prob in LEVELS:
            out = distance_from_focus(
                defocus_of(scene), fits["s_x"][ok], fits["s_y"][ok], widths[ok], prob
            )
            row[f"coverage {prob:.0%}"] = float(np.mean((out["lower"] <= z) & (z <= out["upper"])))
            row[f"SE {prob:.0%}"] = float(np.sqrt(prob * (1 - prob) / ok.sum()))
        score = (out["tau_hat"] - z * z) / out["tau_sd"]
        row["tau z-score mean"], row["tau z-score SD"] = float(score.mean()), float(score.std())
        rows.append(row)
    return pd.DataFrame(rows)


def figure(wide: pd.DataFrame, points: pd.DataFrame, path: Path) -> None:
    """Coverage against mu at 68% (left) and 95% (right), per interval, with the nominal
    level and the simulated points' mu marked."""
    with saved_figure(path, (10, 3.8), columns=2) as axes:
        for ax, level in zip(axes, ("68%", "95%"), strict=True):
            for method, style in (
                ("posterior, z uniform", "o-"),
                ("posterior, tau uniform", "s--"),
                ("unified", "k-"),
            ):
                ax.plot(wide["mu"], wide[f"{method} {level}"], style, ms=3, label=method)
            ax.axhline(float(level[:-1]) / 100, color="grey", lw=0.8)
            for mu in points["mu = z^2 / sigma"]:
                ax.axvline(mu, color="grey", lw=0.5, ls=":")
            ax.set_xscale("symlog", linthresh=0.1)
            ax.set_xlabel("mu = tau / sigma (dotted: the simulated points)")
            ax.set_ylabel(f"coverage of the {level} interval")
        axes[0].legend(fontsize=7)


def main(argv=None):
    args, started, stem = study(__doc__, argv, "axial_edge", posteriors=False)
    means = QUICK_MEANS if args.quick else MEANS
    table = coverage_table(means, 1301 if args.quick else 5201)
    wide = table.pivot(
        index="mu",
        columns="level",
        values=["posterior, z uniform", "posterior, tau uniform", "unified"],
    )
    wide.columns = [f"{method} {level:.0%}" for method, level in wide.columns]
    wide = wide.reset_index()
    points = pd.DataFrame(
        [
            {"N": n, "sigma (nm^2)": sd, "z (nm)": z, "mu = z^2 / sigma": z * z / sd}
            for n in SIMULATED
            for sd in [tau_sd(n)]
            for z in SIMULATED[n]
        ]
    )
    figure(wide, points, args.out / f"{stem}.png")
    unified = simulated(*(QUICK_UNIFIED if args.quick else (UNIFIED_POINTS, UNIFIED_MOLECULES)))
    fmt = {"index": False, "floatfmt": ".3g"}
    body = (
        f"{wide.to_markdown(**fmt)}\n\nThe simulated points of `validation/axial.py` on this "
        f"scale:\n\n{points.to_markdown(**fmt)}\n\nThe unified interval on simulated ROIs "
        f"(the symmetric scene; MLE widths and their Laplace covariance):\n\n"
        f"{unified.to_markdown(**fmt)}"
    )
    text = (
        f"# Coverage at the edge of |z| (Gaussian limit, quadrature)\n\n{body}\n\n"
        f"Figure: [{stem}.png]({stem}.png)."
    )
    summary = f"{body}\n\n![coverage against mu](results/{stem}.png)"
    return finish(args, "axial_edge", wide, text, started, summary)


if __name__ == "__main__":
    main()
