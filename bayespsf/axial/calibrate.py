"""Defocus curves from a bead z-stack.

A z-stack images one bright, immobile bead at known stage positions z, several frames per
step. Calibration, in three steps:

1. **Per-step widths.** The frames of each step share the bead's position and widths, so each
   step's widths are the joint posterior over its frames (``bayespsf.inference.joint``): the
   posterior mean and SD of s_x and s_y per step.
2. **Curves.** Per axis, the curve (``HuangCurve`` or ``PolynomialCurve``) fitted to the steps'
   widths by weighted least squares, each step weighted by its posterior SD; the parameters'
   covariance is the inverse of ``J' W J`` at the fit (the Gauss-Newton approximation, Seber &
   Wild, Nonlinear Regression (1989), sec. 2.1).
3. **Does the curve fit?** The weighted residuals' chi-square against its degrees of freedom;
   where its p-value is below ``MISFIT_P`` the calibration says so
   (``DefocusCalibration.problems``): the stack has structure the curve does not describe
   (residuals beyond their errors), and its z will be biased where the curve is wrong.

Stacks come from ``bayespsf.simulation.simulate_zstack`` (a scene with ``[axial]``: the bead
at each step) or from a user's movie (``bead_rois``: the movie reader, the detector on its
mean projection, and the ROIs of one bead: the brightest, unless another is of comparable
brightness, when the caller picks). The result's ``source`` records the pixel size and the
camera's kind of the model the widths were measured with (``step_widths``), which
``z_posterior`` checks against the model it is used with. ``bayespsf.io.z_calibration`` saves
and loads the result.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy import optimize, stats

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import CURVES, PARAMETER_NAMES, TERMS, Defocus, DefocusCalibration

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from bayespsf.model import Model
    from bayespsf.movie import Movie

MIN_STEPS = 6  # a five-term curve per axis needs more steps than terms
COMPARABLE = 0.5  # a second bead with this share of the brightest's photons: ask which
PICK_DISTANCE = 3.0  # pixels from a requested (x, y) to the bead it names


def bead_rois(
    movie: Movie | str | Path,
    model: Model,
    *,
    s0: float,
    fit: int | None = None,
    roi: int = 25,
    bead: tuple[float, float] | str | None = None,
) -> tuple[np.ndarray, pd.DataFrame]:
    """The ROIs of one bead of a z-stack movie, and its detection row.

    Parameters
    ----------
    movie : Movie or path
        The z-stack in counts (ADU), one frame per stage position and frame.
    model : Model
        The camera (ADU to photons) and pixel size.
    s0 : float
        The detector's template SD, nm.
    fit : int, optional
        Odd side in pixels of the ROIs returned; default the model's ROI side.
    roi : int, default 25
        Odd side in pixels of the cut around the bead (its border must lie inside the frames).
    bead : (float, float), "brightest" or None, optional
        Which bead: ``(x, y)`` in camera pixels (picasso's convention, as the error that lists
        the beads gives them), the accepted bead within ``PICK_DISTANCE`` pixels of it;
        ``"brightest"``, the brightest; None (default), the brightest where it is the only
        bead or no other reaches ``COMPARABLE`` of its photons, else an error that lists them.

    Returns
    -------
    counts : numpy.ndarray, shape (frames, fit, fit)
        The bead's central ROIs in every frame, in the movie's data type (ADU).
    bead : pandas.DataFrame
        Its row of ``detect_movie``'s table (``molecule`` set to 0), with ``beads`` (how many
        beads detection accepted) and ``rank`` (this one's by photons, 1 the brightest).

    Raises
    ------
    BayespsfInputError
        No bead accepted on the mean projection at least ``roi // 2`` pixels from the edges,
        several beads of comparable brightness and no ``bead`` to pick one, a ``bead`` that
        is no accepted bead's position, or any error of ``detect_movie`` or ``cut_rois``.

    See Also
    --------
    step_widths : the per-step widths of these ROIs.
    bayespsf.movie.detect_movie : detection on the mean projection.
    """
    from bayespsf.movie import cut_rois, detect_movie
    from bayespsf.movie.extract import open_movie

    movie = open_movie(movie)
    fit = model.roi if fit is None else fit
    found = detect_movie(movie, psf_sd=s0, pixel_size=model.pixel_size, camera=model, roi=roi)
    found = found[found["status"] == "accepted"]
    if found.empty:
        raise BayespsfInputError(
            f"no bead was detected on the stack's mean projection at least {roi // 2} pixels "
            f"from its edges: check the bead's SD (--psf-sd, {s0:g} nm given), the camera file "
            "(--camera: its offset and gain turn counts into photons) and the pixel size "
            f"({model.pixel_size:g} nm: --pixel-size, else the camera file's [geometry] "
            "pixel_size, else the stack's metadata), or cut less "
            f"around the bead (--roi, {roi} pixels) if it lies near an edge"
        )
    found = found.sort_values("amplitude", ascending=False).reset_index(drop=True)
    found = found.assign(beads=len(found), rank=np.arange(1, len(found) + 1))
    row = _pick_bead(found, bead)
    chosen = found.iloc[[row]].assign(molecule=0)
    stack = cut_rois(movie, chosen, roi=roi, fit=fit)
    return stack.central(fit), chosen


def _pick_bead(found: pd.DataFrame, bead) -> int:
    """The row of ``found`` (accepted beads, brightest first) that ``bead`` names."""
    listed = "; ".join(
        f"x {r.x:.1f}, y {r.y:.1f}: {r.amplitude:.3g} photons" for r in found.head(8).itertuples()
    ) + ("; ..." if len(found) > 8 else "")
    if bead is None:
        if len(found) > 1 and found["amplitude"].iloc[1] >= COMPARABLE * found["amplitude"].iloc[0]:
            raise BayespsfInputError(
                f"{len(found)} beads on the stack's mean projection, and more than one of "
                f"comparable brightness (within {1 / COMPARABLE:g}x of the brightest: {listed}); "
                "which one calibrates is the caller's choice: crop the stack to one bead, or "
                "pick one from Python (bead_rois(..., bead=(x, y)) or bead='brightest')"
            )
        return 0
    if isinstance(bead, str):
        if bead != "brightest":
            raise BayespsfInputError(f"bead must be (x, y), 'brightest' or None, got {bead!r}")
        return 0
    try:
        x, y = (float(v) for v in bead)
    except (TypeError, ValueError):
        raise BayespsfInputError(
            f"bead must be (x, y) in camera pixels, 'brightest' or None, got {bead!r}"
        ) from None
    distance = np.hypot(found["x"].to_numpy() - x, found["y"].to_numpy() - y)
    nearest = int(np.argmin(distance))
    if not distance[nearest] <= PICK_DISTANCE:
        raise BayespsfInputError(
            f"bead ({x:g}, {y:g}): no accepted bead within {PICK_DISTANCE:g} pixels of it; the "
            f"stack's beads (x, y in camera pixels): {listed}"
        )
    return nearest


def step_widths(
    counts: ArrayLike,
    z: ArrayLike,
    model: Model,
    *,
    seed: int = 0,
    ess: float = 400.0,
    workers: int | None = None,
) -> pd.DataFrame:
    """Per step (frames of equal z): the joint posterior mean and SD of s_x and s_y.

    Parameters
    ----------
    counts : array_like, shape (frames, roi, roi)
        The bead's ROIs in ADU (``bead_rois``, or ``simulate_zstack``).
    z : array_like, shape (frames,)
        The stage position of each frame, nm; frames of equal z are one step.
    model : Model
        Camera, geometry and prior of the ROIs.
    seed : int, default 0
        Seed of the joint posteriors (``molecule_seed(seed, step)``).
    ess : float, default 400.0
        Effective sample size of each step's joint posterior.
    workers : int, optional
        Local processes (default as ``joint_posteriors``).

    Returns
    -------
    pandas.DataFrame
        One row per step in z order: ``z`` (nm), ``frames``, ``s_x``, ``s_x_sd``, ``s_y``,
        ``s_y_sd`` (the joint posterior's mean and SD over the step's frames, nm; NaN where
        it has none) and ``method`` (the joint posterior's); its ``attrs`` hold the model's
        ``pixel_size`` (nm) and ``camera_kind``, which ``calibrate`` records in its source.

    Raises
    ------
    BayespsfInputError
        ``counts`` that are not a stack of the model's ROIs with one ``z`` per frame.

    See Also
    --------
    calibrate : the curves from this table.
    bayespsf.parallel.joint_posteriors : the joint posterior over a step's frames.
    """
    from bayespsf.inference import fit_mle
    from bayespsf.parallel import joint_posteriors

    z = finite_array("z", z)
    counts = model.check_counts(counts)
    if counts.ndim != 3 or len(counts) != len(z):
        raise BayespsfInputError(
            f"counts must be (frames, roi, roi) with one z per frame; got "
            f"{np.shape(counts)} and {len(z)} positions"
        )
    values, step = np.unique(z, return_inverse=True)
    fits = fit_mle(counts, model)
    frames = pd.DataFrame({"molecule": step, "mle_converged": fits["converged"].to_numpy()})
    for p in PARAMETER_NAMES:
        frames[f"{p}_mle"] = fits[p].to_numpy()
    joint = joint_posteriors(
        counts, frames, model, seed=seed, ess=ess, workers=workers, progress=False
    )
    table = pd.DataFrame({"z": values, "frames": np.bincount(step)})
    for axis in ("s_x", "s_y"):
        for stat in ("mean", "sd"):
            column = f"{axis}_joint_{stat}"
            table[f"{axis}_{stat}" if stat == "sd" else axis] = (
                joint[column].to_numpy() if column in joint else np.nan
            )
    table["method"] = joint["joint_method"].to_numpy()
    table.attrs.update(
        pixel_size=float(model.pixel_size), camera_kind=str(model.camera.to_dict()["kind"])
    )
    return table


def fit_curve(
    z: ArrayLike,
    width: ArrayLike,
    sd: ArrayLike,
    curve: str = "huang",
    higher_order: bool = True,
) -> dict:
    """One axis's curve fitted to the steps' widths by weighted least squares.

    Parameters
    ----------
    z : array_like, shape (steps,)
        Stage positions, nm.
    width : array_like, shape (steps,)
        The widths at each z, nm (> 0).
    sd : array_like, shape (steps,)
        Their SDs, nm (> 0): each step's weight is ``1 / sd^2``.
    curve : {"huang", "polynomial"}, default "huang"
        The curve's kind (``CURVES``).
    higher_order : bool, default True
        Fit the terms ``A`` and ``B``; False holds A = B = 0.

    Returns
    -------
    dict
        ``terms`` (5,: ``w0 c d A B``), their ``covariance`` (5 x 5; rows and columns of held
        terms 0), ``chi2``, ``dof`` and its ``p``-value.

    Raises
    ------
    BayespsfInputError
        An unknown curve, fewer steps than ``MIN_STEPS`` (or the free terms plus one), a
        width or SD that is not > 0, or no start that could be fitted.

    See Also
    --------
    calibrate : both axes, as a ``DefocusCalibration``.

    Notes
    -----
    The terms' covariance is the inverse of ``J' W J`` at the fit (the Gauss-Newton
    approximation, Seber & Wild, Nonlinear Regression (1989), sec. 2.1); the fit starts from
    three guesses (``w0`` the smallest width, ``c`` where it is and a quarter of the stack's
    span to either side) and keeps the best.
    """
    if curve not in CURVES:
        raise BayespsfInputError(f"curve must be one of {sorted(CURVES)} (--curve), got {curve!r}")
    z, width, sd = (finite_array(n, v) for n, v in (("z", z), ("width", width), ("sd", sd)))
    free = 5 if higher_order else 3
    if len(z) < max(MIN_STEPS, free + 1):
        raise BayespsfInputError(
            f"a {curve} curve with {free} terms needs at least {max(MIN_STEPS, free + 1)} steps "
            f"with widths; got {len(z)} (a stack of more steps: the stack's frames over "
            "--frames-per-step"
            + ("; or three terms per axis: --no-higher-order)" if higher_order else ")")
        )
    if np.any(sd <= 0) or np.any(width <= 0):
        raise BayespsfInputError("width, sd: every step needs a width > 0 and an SD > 0")
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
            result = optimize.least_squares(residuals, start, bounds=(lower, np.inf), x_scale="jac")
        except ValueError:
            continue
        if best is None or result.cost < best.cost:
            best = result
    if best is None:
        raise BayespsfInputError(
            f"no start of the {curve} curve could be fitted to these widths (try the other "
            "curve, --curve, or three terms per axis, --no-higher-order)"
        )
    jac = best.jac
    covariance = np.zeros((5, 5))
    try:
        covariance[:free, :free] = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        covariance[:free, :free] = np.nan
    chi2 = float(2 * best.cost)
    dof = len(z) - free
    terms = np.concatenate([best.x, np.zeros(5 - free)])
    return {
        "terms": terms,
        "covariance": covariance,
        "chi2": chi2,
        "dof": dof,
        "p": float(stats.chi2.sf(chi2, dof)),
    }


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


def _steps_without_widths(steps: pd.DataFrame, usable, needed: int) -> str:
    """Why too few steps have widths to fit a curve to."""
    methods = steps.loc[~usable, "method"] if "method" in steps else pd.Series(dtype=object)
    counts = ", ".join(f"{m} {n}" for m, n in methods.value_counts().items())
    frames = steps.loc[~usable, "frames"] if "frames" in steps else pd.Series(dtype=float)
    few = bool(len(frames)) and bool((frames < 2).all())
    return (
        f"{int((~usable).sum())} of {len(steps)} steps have no widths"
        + (f" (their joint posterior's method: {counts})" if counts else "")
        + f", so {int(usable.sum())} are left to fit, fewer than the {needed} a curve needs: "
        + (
            "a step's widths are the joint posterior over its frames, which needs at least 2 "
            "usable frames per step (take the stack with 2 or more frames per step, "
            "--frames-per-step)"
            if few
            else "the bead's fits failed at those steps (is the bead in every frame, and the "
            "camera file, --camera, the stack's?)"
        )
    )


def calibrate(
    steps: pd.DataFrame, curve: str = "huang", higher_order: bool = True, source: dict | None = None
) -> DefocusCalibration:
    """Defocus curves for both axes from the per-step widths of a bead z-stack.

    Parameters
    ----------
    steps : pandas.DataFrame
        ``step_widths``' table: ``z``, ``s_x``, ``s_x_sd``, ``s_y``, ``s_y_sd`` (nm), one row
        per step; steps without finite widths are left out.
    curve : {"huang", "polynomial"}, default "huang"
        The curve's kind (``CURVES``).
    higher_order : bool, default True
        Fit the terms ``A`` and ``B``; False holds A = B = 0.
    source : dict, optional
        Where the stack came from, kept in the result (beside ``steps_left_out``, and the
        ``pixel_size`` and ``camera_kind`` of ``steps.attrs`` where ``step_widths`` put them;
        keys given here take precedence).

    Returns
    -------
    DefocusCalibration
        The curves (``defocus``), ``fits`` (index ``x``, ``y``; columns ``w0 c d A B``, their
        ``_sd``, ``chi2``, ``dof``, ``p``, ``steps``), the terms' ``covariance`` per axis,
        the ``steps`` and the ``source``; ``problems`` names an axis whose curve does not fit.

    Raises
    ------
    BayespsfInputError
        A table without the columns, or any error of ``fit_curve``.

    See Also
    --------
    step_widths : the table from a stack's ROIs.
    fit_curve : one axis.
    z_posterior : z of an emitter from the curves.
    bayespsf.io.write_z_calibration : the calibration as a file.

    Notes
    -----
    The three steps of the module docstring: per-step widths (joint posteriors), curves by
    weighted least squares with the Gauss-Newton covariance, and the chi-square check of the
    fit (a p-value below ``MISFIT_P`` is reported in ``DefocusCalibration.problems``).

    Examples
    --------
    Widths of an astigmatic curve at 25 steps, each with an error of 2 nm:

    >>> import numpy as np
    >>> import pandas as pd
    >>> from bayespsf.axial import calibrate
    >>> from bayespsf.psf import Defocus
    >>> truth = Defocus.astigmatic(w0=120.0, separation=400.0, depth=400.0)
    >>> z = np.linspace(-600.0, 600.0, 25)
    >>> s_x, s_y = truth.widths(z)
    >>> rng = np.random.default_rng(0)
    >>> steps = pd.DataFrame({
    ...     "z": z, "s_x": s_x + rng.normal(0, 2.0, z.size), "s_x_sd": 2.0,
    ...     "s_y": s_y + rng.normal(0, 2.0, z.size), "s_y_sd": 2.0,
    ... })
    >>> result = calibrate(steps, "huang", higher_order=False)
    >>> result.fits[["w0", "c", "d"]].round(0)  # doctest: +NORMALIZE_WHITESPACE
             w0      c      d
    axis
    x     119.0 -196.0  392.0
    y     121.0  193.0  403.0
    >>> result.problems
    []
    """
    missing = [c for c in ("z", "s_x", "s_x_sd", "s_y", "s_y_sd") if c not in steps]
    if missing:
        raise BayespsfInputError(f"steps: no column {', '.join(missing)}")
    usable = np.isfinite(steps[["s_x", "s_x_sd", "s_y", "s_y_sd"]]).all(axis=1)
    used = steps[usable]
    needed = max(MIN_STEPS, (5 if higher_order else 3) + 1)
    if len(used) < needed and not usable.all():
        raise BayespsfInputError(_steps_without_widths(steps, usable, needed))
    rows, covariance, curves = [], {}, {}
    for axis in ("x", "y"):
        fit = fit_curve(used["z"], used[f"s_{axis}"], used[f"s_{axis}_sd"], curve, higher_order)
        sd = np.sqrt(np.diagonal(fit["covariance"]))
        rows.append(
            {
                "axis": axis,
                **dict(zip(TERMS, fit["terms"], strict=True)),
                **{f"{t}_sd": s for t, s in zip(TERMS, sd, strict=True)},
                "chi2": fit["chi2"],
                "dof": fit["dof"],
                "p": fit["p"],
                "steps": len(used),
            }
        )
        covariance[axis] = fit["covariance"]
        curves[axis] = CURVES[curve](*fit["terms"])
    fits = pd.DataFrame(rows).set_index("axis")
    recorded = {k: steps.attrs[k] for k in ("pixel_size", "camera_kind") if k in steps.attrs}
    source = {"steps_left_out": int((~usable).sum()), **recorded, **(source or {})}
    return DefocusCalibration(
        curve,
        Defocus(curves["x"], curves["y"]),
        fits,
        covariance,
        steps.reset_index(drop=True),
        source,
    )


__all__ = ["bead_rois", "calibrate", "fit_curve", "step_widths"]
