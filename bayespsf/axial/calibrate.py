"""Defocus curves from a bead z-stack (issue 16, item 2).

A z-stack images one bright, immobile bead at known stage positions z, several frames per
step. Calibration, in three steps:

1. **Per-step widths.** The frames of each step share the bead's position and widths, so each
   step's widths are the joint posterior over its frames (``bayespsf.analysis.joint``): the
   posterior mean and SD of s_x and s_y per step.
2. **Curves.** Per axis, the curve (``HuangCurve`` or ``PolynomialCurve``) fitted to the steps'
   widths by weighted least squares, each step weighted by its posterior SD; the parameters'
   covariance is the inverse of ``J' W J`` at the fit (the Gauss-Newton approximation, Seber &
   Wild, Nonlinear Regression (1989), sec. 2.1).
3. **Does the curve fit?** The weighted residuals' chi-square against its degrees of freedom;
   where its p-value is below ``MISFIT_P`` the calibration says so (``Calibration.problems``):
   the stack has structure the curve does not describe (residuals beyond their errors), and
   its z will be biased where the curve is wrong.

Stacks come from ``simulate_zstack`` (a scene with ``[axial]``: the bead at each step) or from
a user's movie (``bead_rois``: the movie reader, the detector on its mean projection, and the
ROIs of the brightest bead). ``bayespsf.axial.calibration_file`` saves and loads the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize, stats

from bayespsf import simulate
from bayespsf._checks import finite_array
from bayespsf.axial.defocus import Defocus, HuangCurve, PolynomialCurve
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES

CURVES = {"huang": HuangCurve, "polynomial": PolynomialCurve}
TERMS = ("w0", "c", "d", "A", "B")
MISFIT_P = 1e-3  # a chi-square p-value below this says the curve does not fit the stack
MIN_STEPS = 6  # a five-term curve per axis needs more steps than terms


@dataclass
class Calibration:
    """Fitted defocus curves with their uncertainty and how they were made.

    ``fits``: one row per axis (``x``, ``y``): the terms, their SDs, ``chi2``, ``dof``, ``p``.
    ``covariance``: per axis, the terms' covariance (5 x 5; rows and columns of terms held
    fixed are 0). ``steps``: the per-step widths the curves were fitted to. ``source``: where
    the stack came from (free-form provenance, kept in every file and result).
    """

    curve: str
    defocus: Defocus
    fits: pd.DataFrame
    covariance: dict[str, np.ndarray]
    steps: pd.DataFrame
    source: dict = field(default_factory=dict)

    def record(self) -> dict:
        """What a result that used this calibration keeps of it: the curve, each axis's terms
        and fit, and the source (with the file it was loaded from)."""
        axes = {axis: {k: float(v) for k, v in row[[*TERMS, "chi2", "p"]].items()}
                for axis, row in self.fits.iterrows()}  # fmt: skip
        return {"curve": self.curve, **axes, "source": dict(self.source)}

    @property
    def problems(self) -> list[str]:
        """One sentence per axis whose curve does not fit its stack (chi-square p below
        ``MISFIT_P``)."""
        out = []
        for axis, row in self.fits.iterrows():
            if row["p"] < MISFIT_P:
                out.append(
                    f"the {self.curve} curve does not fit the stack's {axis} widths: "
                    f"chi2 = {row['chi2']:.1f} on {int(row['dof'])} degrees of freedom "
                    f"(p = {row['p']:.1e}); residuals are beyond their errors, so z from this "
                    "curve will be biased where it is wrong"
                )
        return out


def zstack_positions(start: float, step: float, steps: int, frames_per_step: int) -> np.ndarray:
    """The stage z of every frame of a stack: ``steps`` positions ``start + k step``, each
    held for ``frames_per_step`` frames."""
    for name, value in (("steps", steps), ("frames_per_step", frames_per_step)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise BayespsfInputError(f"{name} must be a positive integer, got {value!r}")
    start, step = (float(finite_array(n, v)) for n, v in (("start", start), ("step", step)))
    if step == 0:
        raise BayespsfInputError("step must not be 0")
    return np.repeat(start + step * np.arange(steps), frames_per_step)


def simulate_zstack(scene, z, seed: int):
    """Counts ``(len(z), roi, roi)`` of the scene's emitter at each stage position of ``z``
    (a scene with ``[axial]``; its z law is replaced by each position), and the truth table.
    Frame ``i`` depends on ``seed`` and its step only."""
    if "axial" not in scene.to_dict():
        raise BayespsfInputError("the scene declares no [axial] table: no defocus to image")
    z = finite_array("z", z)
    counts, truths = [], []
    values, first = np.unique(z, return_index=True)
    for k, value in enumerate(values[np.argsort(first)]):
        n = int(np.sum(z == value))
        step_seed = int(np.random.SeedSequence([seed, k]).generate_state(1)[0])
        c, t = simulate(scene.replace(axial={"z": "fixed", "z0": float(value)}), n, step_seed)
        counts.append(c)
        truths.append(t)
    order = np.argsort(np.concatenate([np.flatnonzero(z == v) for v in values[np.argsort(first)]]))
    return np.concatenate(counts)[order], pd.concat(truths, ignore_index=True).iloc[order]


def bead_rois(movie, model, *, s0: float, fit: int | None = None, roi: int = 25):
    """The ROIs ``(frames, fit, fit)`` of a z-stack movie's brightest bead (detected on the
    movie's mean projection, ``bayespsf.movie.detect.detect_movie``, with the template SD
    ``s0`` nm) and its detection row. ``fit`` defaults to the model's ROI side; ``roi`` is
    the cut around the bead (its border must lie inside the frames)."""
    from bayespsf.movie.detect import detect_movie
    from bayespsf.movie.extract import cut_rois, open_movie

    movie = open_movie(movie)
    fit = model.roi if fit is None else fit
    found = detect_movie(movie, psf_sd=s0, pixel_size=model.pixel_size, camera=model, roi=roi)
    found = found[found["status"] == "accepted"]
    if found.empty:
        raise BayespsfInputError(
            f"no bead was detected on the stack's mean projection at least {roi // 2} pixels "
            "from its edges"
        )
    bead = found.sort_values("amplitude").iloc[[-1]].assign(molecule=0)
    stack = cut_rois(movie, bead, roi=roi, fit=fit)
    return stack.central(fit), bead


def step_widths(counts, z, model, *, seed: int = 0, ess: float = 400.0,
                workers: int | None = None) -> pd.DataFrame:  # fmt: skip
    """Per step (frames of equal z): the joint posterior mean and SD of s_x and s_y over its
    frames (``bayespsf.analysis.joint.joint_posteriors``), one row per step in z order."""
    from bayespsf.analysis.joint import joint_posteriors
    from bayespsf.estimators import fit_mle

    z = finite_array("z", z)
    counts = model.check_counts(counts)
    if counts.ndim != 3 or len(counts) != len(z):
        raise BayespsfInputError(f"counts must be (frames, roi, roi) with one z per frame; got "
                                 f"{np.shape(counts)} and {len(z)} positions")  # fmt: skip
    values, step = np.unique(z, return_inverse=True)
    fits = fit_mle(counts, model)
    frames = pd.DataFrame({"molecule": step, "mle_converged": fits["converged"].to_numpy()})
    for p in PARAMETER_NAMES:
        frames[f"{p}_mle"] = fits[p].to_numpy()
    joint = joint_posteriors(counts, frames, model, seed=seed, ess=ess, workers=workers,
                             progress=False)  # fmt: skip
    table = pd.DataFrame({"z": values, "frames": np.bincount(step)})
    for axis in ("s_x", "s_y"):
        for stat in ("mean", "sd"):
            column = f"{axis}_joint_{stat}"
            table[f"{axis}_{stat}" if stat == "sd" else axis] = (
                joint[column].to_numpy() if column in joint else np.nan
            )
    table["method"] = joint["joint_method"].to_numpy()
    return table


def fit_curve(z, width, sd, curve: str = "huang", higher_order: bool = True) -> dict:
    """One axis's curve by weighted least squares (module docstring): the terms, their
    covariance (5 x 5), ``chi2``, ``dof`` and its ``p``-value. ``higher_order`` False holds
    A = B = 0."""
    if curve not in CURVES:
        raise BayespsfInputError(f"curve must be one of {sorted(CURVES)}, got {curve!r}")
    z, width, sd = (finite_array(n, v) for n, v in (("z", z), ("width", width), ("sd", sd)))
    free = 5 if higher_order else 3
    if len(z) < max(MIN_STEPS, free + 1):
        raise BayespsfInputError(
            f"a {curve} curve with {free} terms needs at least {max(MIN_STEPS, free + 1)} steps "
            f"with widths; got {len(z)}"
        )
    if np.any(sd <= 0) or np.any(width <= 0):
        raise BayespsfInputError("every step needs a width > 0 and an SD > 0")
    kind = CURVES[curve]

    def residuals(terms):
        full = np.concatenate([terms, np.zeros(5 - free)])
        try:
            model = kind(*full)
            return (width - model.width(z)) / sd
        except BayespsfInputError:  # outside the curve's domain or a bad term: far off
            return np.full(len(z), 1e6)

    best = None
    for start in _starts(z, width, curve)[:, :free]:
        lower = [0.0, -np.inf, 1.0, -np.inf, -np.inf][:free]
        try:
            result = optimize.least_squares(residuals, start, bounds=(lower, np.inf),
                                            x_scale="jac")  # fmt: skip
        except ValueError:
            continue
        if best is None or result.cost < best.cost:
            best = result
    if best is None:
        raise BayespsfInputError(f"no start of the {curve} curve could be fitted to these widths")
    jac = best.jac
    covariance = np.zeros((5, 5))
    try:
        covariance[:free, :free] = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        covariance[:free, :free] = np.nan
    chi2 = float(2 * best.cost)
    dof = len(z) - free
    terms = np.concatenate([best.x, np.zeros(5 - free)])
    return {"terms": terms, "covariance": covariance, "chi2": chi2, "dof": dof,
            "p": float(stats.chi2.sf(chi2, dof))}  # fmt: skip


def _starts(z, width, curve: str) -> np.ndarray:
    """Starting terms (3, 5): w0 the smallest width, c where it is, d where the width has
    grown by the curve's factor at u = 1 (sqrt 2 for Huang's, 2 for the polynomial), and c
    a quarter of the stack's span to either side."""
    order = np.argsort(z)
    z, width = z[order], width[order]
    w0, c = width.min(), z[np.argmin(width)]
    grown = width >= w0 * (np.sqrt(2.0) if curve == "huang" else 2.0)
    distance = np.abs(z[grown] - c)
    span = float(np.ptp(z)) or 1.0
    d = float(distance.min()) if distance.size else span / 2
    d = max(d, 1.0)
    return np.array([[w0, c + shift, d, 0.0, 0.0] for shift in (0.0, -span / 4, span / 4)])


def calibrate(steps: pd.DataFrame, curve: str = "huang", higher_order: bool = True,
              source: dict | None = None) -> Calibration:  # fmt: skip
    """Curves for both axes from ``step_widths``' table (steps without widths are left out)."""
    missing = [c for c in ("z", "s_x", "s_x_sd", "s_y", "s_y_sd") if c not in steps]
    if missing:
        raise BayespsfInputError(f"steps: no column {', '.join(missing)}")
    usable = np.isfinite(steps[["s_x", "s_x_sd", "s_y", "s_y_sd"]]).all(axis=1)
    used = steps[usable]
    rows, covariance, curves = [], {}, {}
    for axis in ("x", "y"):
        fit = fit_curve(used["z"], used[f"s_{axis}"], used[f"s_{axis}_sd"], curve, higher_order)
        sd = np.sqrt(np.diagonal(fit["covariance"]))
        rows.append({"axis": axis, **dict(zip(TERMS, fit["terms"], strict=True)),
                     **{f"{t}_sd": s for t, s in zip(TERMS, sd, strict=True)},
                     "chi2": fit["chi2"], "dof": fit["dof"], "p": fit["p"],
                     "steps": len(used)})  # fmt: skip
        covariance[axis] = fit["covariance"]
        curves[axis] = CURVES[curve](*fit["terms"])
    fits = pd.DataFrame(rows).set_index("axis")
    source = {"steps_left_out": int((~usable).sum()), **(source or {})}
    return Calibration(curve, Defocus(curves["x"], curves["y"]), fits, covariance,
                       steps.reset_index(drop=True), source)  # fmt: skip


__all__ = ["CURVES", "Calibration", "bead_rois", "calibrate", "fit_curve", "simulate_zstack",
           "step_widths", "zstack_positions"]  # fmt: skip
