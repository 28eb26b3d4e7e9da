"""Why a chain did not converge: a diagnosis in words for ``sample_posterior``'s result.

A chain whose integrated autocorrelation time keeps growing in proportion to its length will
not converge by running longer (Sokal 1997: tau is only estimable from a chain many tau long).
``stalled`` recognises that; ``explain`` names the likely cause from what is known without
more sampling: the maximum-likelihood fit and its Laplace SDs against the prior.
"""

from __future__ import annotations

import numpy as np

from bayespsf.psf import PARAMETER_NAMES

STALL_MIN_STEPS = 4000  # judge growth only on chains this long (short chains underestimate tau)
STALL_GROWTH = 0.5  # tau growing at least as length**0.5 over a quadrupling: stalled
STILL_STEPS = 1000  # walkers that have not moved in some coordinate after this many steps


def stalled(
    history: list[tuple[int, float]], steps: int, tau_max: float, stuck: int, walkers: int
) -> str | None:
    """A reason to stop, or ``None``: ``history`` holds ``(steps, max tau)`` of earlier checks.

    Stalled: no walker moves in some coordinate after ``STILL_STEPS`` steps; or, on a chain of
    at least ``STALL_MIN_STEPS`` steps, the largest tau grew at least as ``steps**STALL_GROWTH``
    since the chain was a quarter as long (a converging chain's tau estimate levels off; one
    that tracks the chain's length says the sampler has not seen the posterior's extent).
    """
    if steps >= STILL_STEPS and (stuck == walkers or not np.isfinite(tau_max)):
        return f"after {steps} steps no walker moves in some parameter"
    if steps < STALL_MIN_STEPS or not np.isfinite(tau_max):
        return None
    earlier = [(n, t) for n, t in history if n <= steps / 4 and np.isfinite(t) and t > 0]
    if not earlier:
        return None
    n0, t0 = earlier[-1]
    growth = np.log(tau_max / t0) / np.log(steps / n0)
    if growth >= STALL_GROWTH:
        return (
            f"tau grew with the chain ({t0:.0f} steps at {n0} steps, {tau_max:.0f} at {steps}): "
            "a chain whose autocorrelation time tracks its length does not converge by running "
            "longer"
        )
    return None


def explain(fit, model) -> str:
    """The likely cause of a chain that did not converge, from the maximum-likelihood ``fit``
    (a row of ``fit_mle``) and the model's prior; '' when none stands out."""
    if not bool(fit["converged"]):
        return (
            f"the maximum-likelihood fit failed ({fit['message']}): the ROI may hold no spot, "
            "more than one, or counts the camera law cannot explain"
        )
    reasons = []
    for name in PARAMETER_NAMES:
        spec, value = model.prior[name], float(fit[name])
        outside = _outside(spec, value)
        if outside:
            reasons.append(f"the maximum-likelihood {name} = {value:.4g} {outside}")
    if reasons:
        return "the prior excludes the data: " + "; ".join(reasons)
    loose = [
        f"{name} = {float(fit[name]):.4g} +- {float(fit[f'sd_{name}']):.3g}"
        for name in ("s_x", "s_y", "N")
        if float(fit[f"sd_{name}"]) > 0.5 * float(fit[name])
    ]
    if loose:
        return (
            "the posterior is not identified by this ROI (Laplace SDs at the maximum "
            f"likelihood: {', '.join(loose)}); use a larger ROI, or an informative prior"
        )
    return ""


def _outside(spec: dict, value: float) -> str:
    kind = spec["kind"]
    if kind in ("uniform", "log-uniform") and not spec["low"] <= value <= spec["high"]:
        return f"lies outside its {kind} prior [{spec['low']:g}, {spec['high']:g}]"
    if kind == "normal" and abs(value - spec["mean"]) > 5 * spec["sd"]:
        return f"lies more than 5 SD from its normal prior ({spec['mean']:g} +- {spec['sd']:g})"
    if kind == "half-normal" and value > 5 * spec["scale"]:
        return f"lies beyond 5 scales of its half-normal prior (scale {spec['scale']:g})"
    return ""


def no_density(counts: np.ndarray, model, params: np.ndarray) -> str:
    """Why a ROI's likelihood is zero at ``params``, naming the pixels its tier gives no
    density; ``""`` where every pixel has one.

    Parameters
    ----------
    counts : ndarray, shape (roi, roi)
        The ROI in ADU (validated).
    model : Model
        The model fitted.
    params : ndarray, shape (6,)
        ``x0 y0 s_x s_y N b``, finite.

    Returns
    -------
    str
        The pixels (row, column, ADU; the first five) and the fix, or ``""``.
    """
    per_pixel = model.camera.log_likelihood_unchecked(counts, model.expected(params))
    bad = np.argwhere(~np.isfinite(per_pixel))
    if not bad.size:
        return ""
    where = ", ".join(f"({r}, {c}) = {counts[r, c]:.6g} ADU" for r, c in bad[:5])
    tier = getattr(model.camera, "likelihood", "")
    fix = (
        "check the camera's offset, gain and readout"
        if tier == "exact"
        else "use a tier with full support (e.g. 'exact')"
    )
    return (
        f"the {tier!r} likelihood gives zero density to {len(bad)} pixel(s) of this ROI at "
        f"every parameter value tried (row, column: {where}); they lie outside the law's "
        f"support: {fix}"
    )
