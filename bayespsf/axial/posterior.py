"""The posterior of an emitter's axial position: a model of ``(x0, y0, z, N, b)`` whose widths
are the calibration's ``(s_x(z), s_y(z))``.

Likelihood: the camera law of ``Model`` at the six parameters ``(x0, y0, s_x(z), s_y(z), N, b)``
(``bayespsf.axial.bounds.to_widths``). Prior: the model's own for x0, y0, N and b, and z uniform
on ``z_range``.

Sampler: importance sampling from a proposal built on a grid of z, so that every mode of z is
found by construction, never by a chain's chance:

1. at each z of a grid over ``z_range`` (``COARSE_STEP``), the maximum of the likelihood in
   ``(x0, y0, N, b)`` with the widths held at the curve's (``bayespsf.inference.solver.maximise``,
   all grid points as one stack), and its Laplace approximation;
2. the Laplace approximation of z's marginal posterior at each grid point,
   ``log p(z) ~ log L + log prior + log N + (1/2) log det C`` (Tierney & Kadane, JASA 81
   (1986)), with ``C`` the conditional covariance of ``(x0, y0, log N, b)``;
3. the same again on a grid ``FINE_STEP`` apart wherever the coarse marginal holds more than
   ``exp(-KEEP)`` of its peak;
4. proposals: z uniform within a fine cell chosen by its marginal mass (or, 5% of them,
   uniform over the whole range), the rest from the conditional Gaussian of the cell nearest
   z mixed with a wider one (a defensive mixture, Hesterberg, Technometrics 37 (1995));
   Pareto-smoothed importance weights against the exact posterior
   (``bayespsf.inference.importance``), with their k-hat as the check (Vehtari et al.,
   arXiv:1507.02646).

Where the curves are even about a plane (the paper's symmetric defocus: z and -z give the
same image), both mirror modes are on the grid with their exact weight, so the posterior
reports both; ``info["above_plane"]`` is the posterior probability of the upper one.

The calibration's own uncertainty can be marginalised (``calibration_uncertainty``): each
draw then also carries curve terms drawn from their Gaussian (``DefocusCalibration.covariance``),
in the proposal and in the target alike, so the weights are unchanged in form and the z
draws are those of the posterior integrated over the curves. The proposal's z is moved, given
the drawn terms, by the first-order shift that keeps the widths at the grid's mode (a
translation: its density is unchanged), so that it follows the curves of each draw.

Sampling coordinates: ``v = (x0, y0, z, log N, b)`` (nm, nm, nm, log photons, photons).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from bayespsf._validate import as_generator
from bayespsf.axial.bounds import THETA_NAMES
from bayespsf.axial.match import check_calibration
from bayespsf.axial.push import check_z_range, symmetry_plane
from bayespsf.axial.result import ZPosterior
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import start_values
from bayespsf.inference.importance import KHAT_MAX, psis, systematic_resample
from bayespsf.inference.solver import maximise, observed_information
from bayespsf.model import Model, PriorTerms
from bayespsf.psf import CURVES, TERMS, Defocus, DefocusCalibration, widths_of_terms

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

COARSE_STEP = 10.0  # nm between the first grid's z
FINE_STEP = 1.0  # nm between the refined grid's z
KEEP = 25.0  # refine where the coarse log marginal is within this of its peak
WIDE_FRACTION, WIDE_SCALE = 0.3, 2.0  # the defensive mixture's wide component (below)
UNIFORM_FRACTION = 0.05  # proposals with z uniform over the whole range
MAX_DRAWS_PER_ESS = 50  # scored draws at most per effective draw asked
BATCH = 4096  # draws scored per likelihood pass
HELD_WIDTHS = np.array([False, False, True, True, False, False])
CONDITIONAL = [0, 1, 4, 5]  # x0, y0, N, b among the six parameters
FLAT_WIDTH_PRIOR = {"kind": "uniform", "low": 0.0, "high": np.inf}


class _Problem:
    """One ROI's exact log posterior in ``v`` and the conditional fits on a grid of z; with
    a ``calibration``, also at curve terms drawn from its uncertainty (``draw_terms``)."""

    def __init__(self, counts, model: Model, defocus: Defocus, z_range, calibration=None):
        self.counts, self.model, self.defocus = counts, model, defocus
        self.calibration = calibration
        self.low, self.high = z_range
        defocus.widths(np.linspace(self.low, self.high, 1001))  # names a z outside its domain
        self.prior = PriorTerms({**model.prior, "s_x": FLAT_WIDTH_PRIOR, "s_y": FLAT_WIDTH_PRIOR})
        self.start = start_values(model.to_photons(counts[None]), model)[0]

    def draw_terms(self, n: int, rng) -> np.ndarray:
        """``n`` draws (2, n, 5) of both curves' terms from the calibration's Gaussian."""
        out = []
        for axis in ("x", "y"):
            mean = self.calibration.fits.loc[axis, list(TERMS)].to_numpy(float)
            values, vectors = np.linalg.eigh(self.calibration.covariance[axis])
            root = vectors * np.sqrt(np.clip(values, 0.0, None))  # held terms: no spread
            out.append(mean + rng.standard_normal((n, 5)) @ root.T)
        return np.stack(out)

    def shift(self, terms: np.ndarray, z: float) -> np.ndarray:
        """How far z moves (n,) when the curves are drawn ``terms`` (2, n, 5) instead of the
        fitted ones, to first order at ``z``: the least-squares z-shift that restores the
        widths, ``-g'(w_drawn - w) / g'g`` with ``g`` the slopes (0 where g vanishes). The
        proposal's z is moved by it, so that it follows the curves the target uses."""
        kind = CURVES[self.calibration.curve]
        g = np.array(self.defocus.slopes(z), dtype=np.float64).ravel()
        if g @ g < 1e-12:  # in focus on a symmetric curve: no first-order shift
            return np.zeros(terms.shape[1])
        w = np.array(self.defocus.widths(z), dtype=np.float64).ravel()
        change = np.stack([widths_of_terms(kind, terms[a], z) - w[a] for a in (0, 1)])
        return -np.nan_to_num(g @ change) / (g @ g)

    def params(self, v: np.ndarray, terms: np.ndarray | None = None) -> np.ndarray:
        if terms is None:
            s_x, s_y = self.defocus.widths(v[:, 2])
        else:
            kind = CURVES[self.calibration.curve]
            s_x, s_y = (widths_of_terms(kind, t, v[:, 2]) for t in terms)
        with np.errstate(over="ignore"):
            n = np.exp(v[:, 3])
        return np.column_stack([v[:, 0], v[:, 1], s_x, s_y, n, v[:, 4]])

    def log_posterior(self, v: np.ndarray, terms: np.ndarray | None = None) -> np.ndarray:
        """Up to a constant; with ``terms`` (2, n, 5), at each draw's own curves (their
        Gaussian is the proposal's too, so it cancels from the importance weights)."""
        out = np.full(len(v), -np.inf)
        inside = (v[:, 2] >= self.low) & (v[:, 2] <= self.high) & np.all(np.isfinite(v), axis=1)
        if not inside.any():
            return out
        p = self.params(v[inside], None if terms is None else terms[:, inside])
        log_prior = self.prior(p) + v[inside, 3]  # + log N: the density of log N
        ok = np.isfinite(log_prior)
        values = np.full(len(p), -np.inf)
        if ok.any():
            values[ok] = log_prior[ok] + self.model.log_likelihood_unchecked(self.counts, p[ok])
        out[inside] = values
        return out

    def conditional_fits(self, z: np.ndarray, starts: np.ndarray | None = None):
        """At each z: the conditional maximum of ``(x0, y0, N, b)``, its covariance in
        ``(x0, y0, log N, b)`` and the Laplace log marginal of z (module docstring)."""
        p0 = np.tile(self.start, (len(z), 1)) if starts is None else starts.copy()
        p0[:, 2], p0[:, 3] = self.defocus.widths(z)
        stack = np.broadcast_to(self.counts, (len(z), *self.counts.shape))
        fit, log_l, converged, _ = maximise(self.model, stack, p0, HELD_WIDTHS)
        info = observed_information(self.model, stack, fit)[:, CONDITIONAL][:, :, CONDITIONAL]
        info[:, 2, :] *= fit[:, 4, None]  # d N / d log N = N
        info[:, :, 2] *= fit[:, 4, None]
        sign, log_det_info = np.linalg.slogdet(info)
        good = converged & np.isfinite(log_l) & (sign > 0)
        log_marginal = np.full(len(z), -np.inf)
        covariance = np.full_like(info, np.nan)
        if good.any():
            log_prior = self.prior(fit[good]) + np.log(fit[good, 4])
            log_marginal[good] = log_l[good] + log_prior - 0.5 * log_det_info[good]
            covariance[good] = np.linalg.inv(info[good])
        return fit, covariance, log_marginal


class _GridProposal:
    """z uniform within a cell picked by its marginal mass, or (a share ``UNIFORM_FRACTION``)
    uniform over the whole z range; ``(x0, y0, log N, b)`` from the conditional Gaussian of
    the cell nearest that z, mixed with ``WIDE_FRACTION`` of it ``WIDE_SCALE`` wider. The
    uniform share bounds the weights where z's Laplace marginal has lighter tails than its
    posterior. At 300 photons (astigmatic scene, z = -600 nm, 40 ROIs), a wide share of 10%
    at 1.5 x left 5 posteriors with k-hat > 0.7; 30% at 2 x, none (and none of 30 at z = 600,
    with k-hat at most 0.47), at the same share of effective draws (0.73)."""

    def __init__(self, lower, upper, log_mass, centre, covariance, z_range):
        self.lower, self.upper = lower, upper
        self.points = 0.5 * (lower + upper)
        self.low, self.high = z_range
        self.mass = np.exp(log_mass - log_mass.max())
        self.mass /= self.mass.sum()
        self.cumulative = np.cumsum(self.mass)
        self.centre = centre  # (cells, 4) in (x0, y0, log N, b)
        self.cholesky = np.linalg.cholesky(covariance)
        self.log_det = 2 * np.log(np.diagonal(self.cholesky, axis1=1, axis2=2)).sum(axis=1)

    def _nearest(self, z: np.ndarray) -> np.ndarray:
        """The index of the cell centre nearest each z."""
        if len(self.points) == 1:
            return np.zeros(len(z), dtype=np.int64)
        right = np.clip(np.searchsorted(self.points, z), 1, len(self.points) - 1)
        left = right - 1
        return np.where(z - self.points[left] <= self.points[right] - z, left, right)

    def draw(self, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
        cell = np.minimum(np.searchsorted(self.cumulative, rng.random(n)), len(self.mass) - 1)
        z = self.lower[cell] + (self.upper[cell] - self.lower[cell]) * rng.random(n)
        anywhere = rng.random(n) < UNIFORM_FRACTION
        z[anywhere] = rng.uniform(self.low, self.high, int(anywhere.sum()))
        cell = self._nearest(z)  # the cell that holds z, where one does
        inside = (z >= self.lower[cell]) & (z <= self.upper[cell])
        width = self.upper[cell] - self.lower[cell]
        with np.errstate(divide="ignore"):
            log_z = np.logaddexp(
                np.log1p(-UNIFORM_FRACTION)
                + np.log(np.where(inside, self.mass[cell], 0.0))
                - np.log(width),
                np.log(UNIFORM_FRACTION) - np.log(self.high - self.low),
            )
        e = rng.standard_normal((n, 4))
        e[rng.random(n) < WIDE_FRACTION] *= WIDE_SCALE
        r2 = np.sum(e * e, axis=1)
        rest = self.centre[cell] + np.einsum("nij,nj->ni", self.cholesky[cell], e)
        log_kernel = np.logaddexp(
            np.log1p(-WIDE_FRACTION) - 0.5 * r2,
            np.log(WIDE_FRACTION) - 4 * np.log(WIDE_SCALE) - 0.5 * r2 / WIDE_SCALE**2,
        )
        log_q = log_z - 0.5 * self.log_det[cell] + log_kernel
        v = np.column_stack([rest[:, 0], rest[:, 1], z, rest[:, 2], rest[:, 3]])
        return v, log_q


def _grid(problem: _Problem):
    """The coarse grid, then the fine one where the coarse marginal matters (module
    docstring): ``(z, fits, covariance, log marginal)`` of the fine grid."""
    low, high = problem.low, problem.high
    coarse = np.linspace(low, high, int(np.ceil((high - low) / COARSE_STEP)) + 1)
    fit, _, log_m = problem.conditional_fits(coarse)
    if not np.isfinite(log_m).any():
        raise BayespsfInputError(
            "no z in z_range gives a converged fit of this ROI: the Laplace marginal of z "
            "could not be formed (is there a spot?)"
        )
    step = coarse[1] - coarse[0]
    kept = np.flatnonzero(log_m >= log_m.max() - KEEP)
    points = np.unique(
        np.concatenate(
            [np.arange(z - step / 2, z + step / 2, FINE_STEP) + FINE_STEP / 2 for z in coarse[kept]]
        )
    )
    points = points[(points >= low) & (points <= high)]
    nearest = np.clip(np.searchsorted(coarse, points) - 1, 0, len(coarse) - 1)
    nearer = np.abs(coarse[np.minimum(nearest + 1, len(coarse) - 1)] - points) < np.abs(
        coarse[nearest] - points
    )
    starts = fit[np.where(nearer, np.minimum(nearest + 1, len(coarse) - 1), nearest)]
    fine_fit, covariance, fine_log_m = problem.conditional_fits(points, starts)
    good = np.isfinite(fine_log_m)
    return points[good], fine_fit[good], covariance[good], fine_log_m[good], (coarse, log_m)


def z_posterior(
    counts: ArrayLike,
    model: Model,
    defocus: Defocus | DefocusCalibration,
    *,
    z_range: tuple[float, float] = (-800.0, 800.0),
    seed: int | np.random.Generator = 0,
    ess: float = 400.0,
    calibration_uncertainty: bool = False,
) -> ZPosterior:
    """The posterior of ``(x0, y0, z, N, b)`` of one ROI, z from the widths' curves.

    Parameters
    ----------
    counts : array_like, shape (roi, roi)
        One ROI in ADU, as ``Model`` reads it.
    model : Model
        Camera, geometry and the prior of x0, y0, N and b (its width priors are not used).
    defocus : Defocus or DefocusCalibration
        The curves ``(s_x(z), s_y(z))``; a ``DefocusCalibration`` (``bayespsf.psf.defocus``) is
        also recorded in ``info["calibration"]``.
    z_range : (float, float), default (-800.0, 800.0)
        Support ``(low, high)`` of z's uniform prior (nm).
    seed : int or numpy.random.Generator, default 0
        The draws' random numbers.
    ess : float, default 400.0
        Effective sample size of the importance weights to reach (draws returned), in
        [10, 1e6].
    calibration_uncertainty : bool, default False
        With a ``DefocusCalibration``: marginalise its curves' uncertainty (each draw at curve
        terms drawn from the terms' Gaussian, ``DefocusCalibration.covariance``), so that z's
        posterior widens by what the stack left unknown. False: the fitted curves as exact.

    Returns
    -------
    ZPosterior
        ``draws``: ``ceil(ess)`` equally weighted rows of ``x0``, ``y0``, ``z`` (nm), ``N``
        (photons), ``b`` (photons per pixel). ``info``: ``method`` ("importance"), ``khat``,
        ``ess`` achieved, ``draws_scored``, ``converged`` (k-hat <= 0.7 and the ESS reached),
        ``why`` where not, ``grid_points``, ``z_range``, ``plane`` and ``above_plane`` where
        the curves are symmetric, and ``calibration`` and ``calibration_uncertainty`` with a
        ``DefocusCalibration``. ``grid``: z's coarse Laplace log marginal.

    Raises
    ------
    BayespsfInputError
        ``counts`` that are not one ROI of the model's shape, a ``defocus`` of another type,
        an ``ess`` outside [10, 1e6], a bad ``z_range`` or one outside the curves' domain,
        ``calibration_uncertainty`` without a ``DefocusCalibration``, a
        ``DefocusCalibration`` made at another pixel size or camera kind than the model's
        (``check_calibration``), or no z in ``z_range`` with a converged fit of the ROI.

    See Also
    --------
    z_posteriors : the same for a stack of ROIs, in parallel.
    z_draws : z from the widths' posterior, pushed through the curves.
    crlb_z : the Cramér-Rao bound of z.
    calibrate : the curves from a bead z-stack.

    Notes
    -----
    The module docstring states the likelihood (the camera law at the curves' widths), the
    prior (the model's for x0, y0, N and b; z uniform on ``z_range``) and the sampler:
    importance sampling from a proposal built on a grid of z (Laplace marginals of z on a
    coarse and a fine grid, a defensive mixture), with Pareto-smoothed weights whose k-hat is
    the check. Every mode of z is on the grid by construction; where the curves are even
    about a plane both mirror modes are reported with their exact weight.

    References
    ----------
    .. [1] L. Tierney and J. B. Kadane, J. Am. Stat. Assoc. 81, 82 (1986).
    .. [2] T. Hesterberg, Technometrics 37, 185 (1995).
    .. [3] A. Vehtari et al., "Pareto smoothed importance sampling", arXiv:1507.02646.

    Examples
    --------
    One simulated ROI of the ``astigmatic`` scene at z = 300 nm (2 000 photons):

    >>> from bayespsf import Model, load_scene, simulate
    >>> from bayespsf.axial import z_posterior
    >>> from bayespsf.psf import Defocus
    >>> scene = load_scene("astigmatic")
    >>> axial = {k: v for k, v in scene.axial.items() if k not in ("z_low", "z_high")}
    >>> counts, truth = simulate(scene.replace(axial={**axial, "z": "fixed", "z0": 300.0}), 1, 0)
    >>> defocus = Defocus.from_table(scene.axial, 130.0, 130.0)
    >>> post = z_posterior(counts[0], Model.from_scene(scene), defocus, seed=1)
    >>> post.info["method"], post.info["converged"]
    ('importance', True)
    >>> post.covers(300.0)  # the 95% highest-density region holds the true z
    True
    """
    c = model.check_counts(counts)
    if c.ndim != 2:
        raise BayespsfInputError(f"counts must be one ROI of shape ({model.roi}, {model.roi})")
    calibration = defocus if isinstance(defocus, DefocusCalibration) else None
    defocus = defocus.defocus if calibration is not None else defocus
    if not isinstance(defocus, Defocus):
        raise BayespsfInputError(
            f"defocus must be a Defocus or a DefocusCalibration, got {type(defocus).__name__}"
        )
    if calibration is not None:
        check_calibration(calibration, model)  # made at the model's pixel size and camera
    if not (isinstance(ess, int | float) and np.isfinite(ess) and 10 <= ess <= 1e6):
        raise BayespsfInputError(f"ess must be a number in [10, 1e6], got {ess!r}")
    rng = as_generator(seed)
    if calibration_uncertainty and calibration is None:
        raise BayespsfInputError(
            "calibration_uncertainty needs a DefocusCalibration, not a Defocus"
        )
    problem = _Problem(
        c, model, defocus, check_z_range(z_range), calibration if calibration_uncertainty else None
    )
    points, fit, covariance, log_m, (coarse, coarse_log_m) = _grid(problem)
    edges = np.concatenate([[problem.low], 0.5 * (points[1:] + points[:-1]), [problem.high]])
    lower = np.maximum(edges[:-1], points - FINE_STEP / 2)
    upper = np.minimum(edges[1:], points + FINE_STEP / 2)
    centre = np.column_stack([fit[:, 0], fit[:, 1], np.log(fit[:, 4]), fit[:, 5]])
    proposal = _GridProposal(
        lower, upper, log_m + np.log(upper - lower), centre, covariance, (problem.low, problem.high)
    )
    drawn, drawn_terms, log_ratio = [], [], []
    mode = float(points[np.argmax(log_m)])
    batch, max_draws = int(np.ceil(ess / 0.7)), int(MAX_DRAWS_PER_ESS * ess)
    scored = 0
    while True:
        v, log_q = proposal.draw(batch, rng)
        terms = None if problem.calibration is None else problem.draw_terms(batch, rng)
        if terms is not None:  # a translation given the terms: log_q is unchanged
            v[:, 2] += problem.shift(terms, mode)
        drawn.append(v)
        drawn_terms.append(terms)
        log_ratio.append(problem.log_posterior(v, terms) - log_q)
        scored += batch
        weights, khat = psis(np.concatenate(log_ratio))
        achieved = 1.0 / np.sum(weights**2)
        if achieved >= ess or khat > KHAT_MAX or scored >= max_draws:
            break
        batch = int(
            np.clip(
                1.2 * (ess - achieved) * scored / max(achieved, 1.0),
                100,
                min(BATCH * 16, max_draws - scored),
            )
        )
    v = np.concatenate(drawn)
    keep = systematic_resample(weights, int(np.ceil(ess)), rng)
    terms = None if problem.calibration is None else np.concatenate(drawn_terms, axis=1)
    params = problem.params(v[keep], None if terms is None else terms[:, keep])
    draws = pd.DataFrame(
        np.column_stack([params[:, 0], params[:, 1], v[keep, 2], params[:, 4], params[:, 5]]),
        columns=list(THETA_NAMES),
    )
    converged = bool(khat <= KHAT_MAX and achieved >= ess)
    info = {
        "method": "importance",
        "khat": float(khat),
        "ess": float(achieved),
        "draws_scored": len(v),
        "converged": converged,
        "grid_points": len(points),
        "z_range": [problem.low, problem.high],
    }
    if not converged:
        info["why"] = (
            f"k-hat {khat:.2f} > {KHAT_MAX}"
            if khat > KHAT_MAX
            else f"ESS {achieved:.0f} < {ess:g} after {len(v)} draws"
        )
    if calibration is not None:
        info["calibration"] = calibration.record()
        info["calibration_uncertainty"] = bool(calibration_uncertainty)
    plane = symmetry_plane(defocus)
    if plane is not None:
        info["plane"] = plane
        info["above_plane"] = float(np.sum(weights[v[:, 2] > plane]))
    grid = pd.DataFrame({"z": coarse, "log_marginal": coarse_log_m})
    return ZPosterior(draws, info, grid)


__all__ = ["ZPosterior", "z_posterior"]
