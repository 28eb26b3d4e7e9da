"""The inference model in JAX: ``bayespsf.model.Model`` for array backends on any device.

``JaxModel.from_model(model)`` captures a ``Model``'s geometry, pixel model, camera law, quantum
efficiency, clock-induced charge and prior as a JAX pytree (arrays as leaves, the configuration
as static fields), whose methods are pure ``jax.numpy``: jit-able, vmap-able over leading batch
dimensions and differentiable by the parameters ``p = x0 y0 s_x s_y N b`` (``jax.grad``,
``jax.jacfwd``, ``jax.hessian``). They are the NumPy model's formulas, term for term:

* ``expected``: ``psf.expected_counts_unchecked`` (pixel-integrated, with the log-space
  upper-tail differences that keep full relative precision far from the spot, or sampled),
  times ``photoelectrons_per_photon``, plus the clock-induced charge;
* ``pixel_log_likelihood``: the camera's ``log_likelihood`` (``jax_laws``);
* ``log_prior``: ``bayespsf.model.PriorTerms``;
* ``fisher``: the camera's per-pixel Fisher information.

The backend computes in float64: ``from_model`` calls ``enable_x64``, which turns on JAX's
64-bit mode (a process-wide JAX setting); importing this module does not.

Supported laws (``SUPPORTED``): the ``Photon`` camera, and the ``EMCCD`` tiers ``table`` (for
``readout_sd / gain`` in the table's range, 0.01 to 2), ``high-gain``, ``gaussian`` and
``poisson``, and every tier without readout (where ``exact`` and ``table`` are the closed form).
Refused with ``BayespsfInputError`` naming the fix: the sCMOS camera, the EMCCD ``exact`` tier
with readout (its quadrature) and the ``table`` tier with a readout/gain ratio outside the
table (where the NumPy tier is that quadrature).

The one place where this model differs from NumPy's: the ``table`` tier off its grids, where
the NumPy tier integrates the exact law by quadrature, too costly on a GPU. There this model
uses the ``high-gain`` closed form with readout: the zero-electron atom convolved with the
readout exactly, the amplified part readout-free. Measured against the quadrature
(``tests/inference/test_jax_model.py``; readout/gain r = 0.25, in brackets r = 2, the table's
largest):

* counts more than ``ETA_MAX`` from the law's bulk (log p < -65): up to 1.1% of |log p|
  (6.8%), e.g. 1.9 at log p = -235;
* counts more than ``NEAR`` readout SDs below the offset (log p < -70): up to 1.8% (12%);
* ``lam < LAM_MIN`` beyond the small-lam expansion's reach (log p < -1000): 3e-5 of |log p|
  (2e-3);
* lam above the grid (``LAM_MAX``, 1e5 photoelectrons in a pixel): 1.2e-5 (7.5e-4) in log p
  in the law's bulk, 2.4e-7 of |log p| in its tails.

Everywhere else this model is the NumPy formulas to rounding: log p within ~1e-15 relative,
expected counts within 1e-12 relative down to 1e-290 (far tails included).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import special

from bayespsf.cameras import EMCCD, SCMOS, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import jax_laws as laws
from bayespsf.model import PriorTerms
from bayespsf.psf import PIXEL_MODELS, pixel_centres

SUPPORTED = {
    "photon": "Photon camera (Poisson counts)",
    "readout-free": "EMCCD without readout noise, tiers exact, table, high-gain (closed form)",
    "table": "EMCCD with readout, likelihood='table' (readout_sd / gain from 0.01 to 2)",
    "high-gain": "EMCCD with readout, likelihood='high-gain'",
    "gaussian": "EMCCD, likelihood='gaussian'",
    "poisson": "EMCCD, likelihood='poisson'",
}
_SQRT2 = np.sqrt(2.0)
TABLES_KEPT = 4  # cameras' tables kept on the device (``on_device``)
_ON_DEVICE: dict[int, tuple[np.ndarray, jax.Array]] = {}


def enable_x64() -> None:
    """Turn on JAX's 64-bit mode (idempotent): the backend computes in float64.

    Returns
    -------
    None
    """
    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)


def on_device(host: np.ndarray) -> jax.Array:
    """A camera's table (a NumPy array the camera keeps for the process, the same object at
    every call) on JAX's device, copied there once: the EMCCD table is 37 MiB, which each
    ``from_model`` copied again (21 ms on a 2-core CPU, three times per ``sample_many``).
    The last ``TABLES_KEPT`` tables stay; ``backends.release_programs`` lets them go.

    Parameters
    ----------
    host : ndarray
        The table, as the camera's ``law_arrays`` gives it.

    Returns
    -------
    jax.Array
        Its float64 copy on the device.
    """
    kept = _ON_DEVICE.get(id(host))  # each entry holds its ``host``: the id is not reused
    if kept is None:
        while len(_ON_DEVICE) >= TABLES_KEPT:
            _ON_DEVICE.pop(next(iter(_ON_DEVICE)))
        kept = _ON_DEVICE[id(host)] = (host, jnp.asarray(host, dtype=jnp.float64))
    return kept[1]


def release_tables() -> None:
    """Let go of the tables ``on_device`` keeps.

    Returns
    -------
    None
    """
    _ON_DEVICE.clear()


def _refusal(what: str, fix: str) -> BayespsfInputError:
    return BayespsfInputError(f"backend='jax' does not support {what}; {fix}")


@dataclass(frozen=True, eq=False)
class JaxModel:
    """A ``Model`` as a JAX pytree; build it with ``from_model``.

    Static fields (part of the compiled program: a new value recompiles): ``roi``,
    ``pixel_size``, ``pixel_model``, ``law`` (a key of ``SUPPORTED``), and the law's numbers.
    Array fields (leaves): the prior's bounds, centres and scales, the EMCCD table's
    coefficients and the Fisher spline's knots and coefficients (``None`` where unused).

    Attributes
    ----------
    roi : int
        ROI side in pixels.
    pixel_size : float
        Pixel side in nm.
    pixel_model : {"integrated", "sampled"}
        The model's pixel model.
    law : str
        The camera law, a key of ``SUPPORTED``.
    photoelectrons_per_photon, clock_induced_charge : float
        As the model's.
    offset, scale, r, log_jacobian : float
        EMCCD: the offset (ADU), ``e_per_adu / gain``, ``readout_sd / gain`` and
        ``log(e_per_adu / gain)``; unused for the photon camera.
    grid : TableGrid or None
        The table's grids (``table`` law).
    fisher_range : tuple of float or None
        First and last knot of the Fisher spline (log10 lam), EMCCD.
    log_uniform, quadratic : tuple of int
        Parameters with a log-uniform prior, and with a normal or half-normal one.
    prior_low, prior_high, prior_centre, prior_scale : jax.Array
        ``PriorTerms``' arrays, shape (6,).
    table, fisher_knots, fisher_coefficients : jax.Array or None
        The table's coefficients (cells, 16), the Fisher spline's knots (k,) and
        coefficients (4, k - 1).
    """

    roi: int
    pixel_size: float
    pixel_model: str
    law: str
    photoelectrons_per_photon: float
    clock_induced_charge: float
    offset: float
    scale: float
    r: float
    log_jacobian: float
    grid: laws.TableGrid | None
    fisher_range: tuple[float, float] | None
    log_uniform: tuple[int, ...]
    quadratic: tuple[int, ...]
    prior_low: jax.Array
    prior_high: jax.Array
    prior_centre: jax.Array
    prior_scale: jax.Array
    table: jax.Array | None
    fisher_knots: jax.Array | None
    fisher_coefficients: jax.Array | None

    @classmethod
    def from_model(cls, model) -> JaxModel:
        """The JAX model of ``model`` (turns on JAX's 64-bit mode).

        Parameters
        ----------
        model : bayespsf.Model
            The inference model.

        Returns
        -------
        JaxModel

        Raises
        ------
        BayespsfInputError
            For a camera law or pixel model this backend does not support (the message names
            it and the fix).
        """
        enable_x64()
        if model.pixel_model not in PIXEL_MODELS:
            raise _refusal(
                f"pixel_model={model.pixel_model!r}",
                f"use one of {', '.join(PIXEL_MODELS)}",
            )
        camera = model.camera
        numbers = dict(offset=0.0, scale=1.0, r=0.0, log_jacobian=0.0)
        grid = fisher_range = table = knots = coefficients = None
        if isinstance(camera, Photon):
            law = "photon"
        elif isinstance(camera, EMCCD):
            arrays = camera.law_arrays()
            law, r = arrays["tier"], arrays["r"]
            if r == 0 and law not in ("poisson", "gaussian"):
                law = "readout-free"
            elif law == "exact":
                raise _refusal(
                    "the EMCCD 'exact' likelihood tier with readout noise (its quadrature)",
                    "use likelihood='table' (within 4e-5 of exact) or backend='numpy'",
                )
            elif law == "table" and arrays["table"] is None:
                low, high = arrays["table_range"]
                raise _refusal(
                    f"the EMCCD 'table' tier at readout_sd / gain = {r:.3g}, outside the "
                    f"table's {low:g} to {high:g} (there the tier is the exact quadrature)",
                    "use likelihood='high-gain' or backend='numpy'",
                )
            numbers = dict(
                offset=arrays["offset"],
                scale=arrays["e_per_adu"] / arrays["gain"],
                r=r,
                log_jacobian=arrays["log_jacobian"],
            )
            if law == "table":
                grid = laws.TableGrid.from_arrays(arrays["table"])
                table = on_device(arrays["table"]["coefficients"])
            knots_np = np.asarray(arrays["fisher"]["knots"], dtype=np.float64)
            fisher_range = (float(knots_np[0]), float(knots_np[-1]))
            knots = on_device(arrays["fisher"]["knots"])
            coefficients = on_device(arrays["fisher"]["coefficients"])
        elif isinstance(camera, SCMOS):
            raise _refusal("the sCMOS camera law yet", "use backend='numpy' (the default)")
        else:
            raise _refusal(f"the camera {camera!r}", "use backend='numpy' (the default)")
        prior = PriorTerms(model.prior)
        return cls(
            roi=int(model.roi),
            pixel_size=float(model.pixel_size),
            pixel_model=model.pixel_model,
            law=law,
            photoelectrons_per_photon=float(model.photoelectrons_per_photon),
            clock_induced_charge=float(model.clock_induced_charge),
            **{k: float(v) for k, v in numbers.items()},
            grid=grid,
            fisher_range=fisher_range,
            log_uniform=tuple(int(k) for k in prior.log_uniform),
            quadratic=tuple(int(k) for k in prior.quadratic),
            prior_low=jnp.asarray(prior.low, dtype=jnp.float64),
            prior_high=jnp.asarray(prior.high, dtype=jnp.float64),
            prior_centre=jnp.asarray(prior.centre, dtype=jnp.float64),
            prior_scale=jnp.asarray(prior.scale, dtype=jnp.float64),
            table=table,
            fisher_knots=knots,
            fisher_coefficients=coefficients,
        )

    # ------------------------------------------------------------------ the spot

    def _axis(self, centre, width):
        """Fraction of the spot's photons in each pixel along one axis, (..., roi)."""
        a = self.pixel_size
        if self.pixel_model == "sampled":
            w = width[..., None]
            z = (jnp.asarray(pixel_centres(self.roi, a)) - centre[..., None]) / w
            return (a * laws.INV_SQRT_2PI) * jnp.exp(-0.5 * z * z) / w
        edges = jnp.asarray((np.arange(self.roi + 1) - self.roi / 2.0) * a)
        z = (edges - centre[..., None]) / width[..., None]
        lo, hi = z[..., :-1], z[..., 1:]
        straddle = (lo < 0) & (hi > 0)
        # a pixel wholly on one side: a difference of upper tails in log space, mirrored so
        # that 0 <= near <= far (straddling pixels get stand-ins, masked below)
        right = lo >= 0
        near = jnp.where(straddle, 0.0, jnp.where(right, lo, -hi))
        far = jnp.where(straddle, 1.0, jnp.where(right, hi, -lo))
        log_tail_near = laws.log_ndtr(-near)
        log_tail_far = laws.log_ndtr(-far)
        one_sided = jnp.exp(log_tail_near) * -jnp.expm1(log_tail_far - log_tail_near)
        central = 0.5 * (special.erf(hi / _SQRT2) - special.erf(lo / _SQRT2))
        return jnp.where(straddle, central, one_sided)

    def expected(self, p):
        """Expected photoelectrons per pixel (``Model.expected``).

        Parameters
        ----------
        p : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b`` (nm, nm, nm, nm, photons, photons per pixel); widths > 0.

        Returns
        -------
        jax.Array, shape (..., roi, roi)
            The spot plus the background, times ``photoelectrons_per_photon``, plus the
            clock-induced charge; rows are y, columns x.
        """
        px, py, n, b = self.spot(p)
        return n[..., None, None] * py[..., :, None] * px[..., None, :] + b[..., None, None]

    def spot(self, p):
        """The factors of ``expected``: ``expected = n py[i] px[j] + b``.

        Parameters
        ----------
        p : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b``; widths > 0.

        Returns
        -------
        px, py : jax.Array, shape (..., roi)
            Fraction of the spot's photons in each column (x) and row (y).
        n, b : jax.Array, shape (...)
            The spot's and the background's photoelectrons (times
            ``photoelectrons_per_photon``; ``b`` plus the clock-induced charge).
        """
        p = jnp.asarray(p, dtype=jnp.float64)
        px = self._axis(p[..., 0], p[..., 2])
        py = self._axis(p[..., 1], p[..., 3])
        n, b = p[..., 4], p[..., 5]
        if self.photoelectrons_per_photon != 1.0:
            n = n * self.photoelectrons_per_photon
            b = b * self.photoelectrons_per_photon
        return px, py, n, b + self.clock_induced_charge

    # ------------------------------------------------------------------ the camera

    def pixel_log_likelihood(self, counts, lam):
        """Element-wise log p(counts | lam) under the camera law (``camera.log_likelihood``).

        Parameters
        ----------
        counts : array_like
            Counts in ADU (photons for the photon camera).
        lam : array_like
            Expected photoelectrons per pixel, >= 0; broadcasts against ``counts``.

        Returns
        -------
        jax.Array
            Log density per ADU (log mass at the offset of a readout-free EMCCD), ``-inf``
            outside the law's support; the broadcast shape.
        """
        counts = jnp.asarray(counts, dtype=jnp.float64)
        lam = jnp.asarray(lam, dtype=jnp.float64)
        if self.law == "photon":
            return laws.poisson_log_pmf(counts, lam)
        x = counts - self.offset
        t = x * self.scale
        if self.law == "readout-free":
            return laws.log_readout_free(t, x, lam, self.log_jacobian)
        if self.law == "poisson":
            log_p = laws.log_poisson_tier(t, x, lam)
        elif self.law == "gaussian":
            log_p = laws.log_gaussian(t, x, lam, self.r)
        elif self.law == "high-gain":
            log_p = laws.log_high_gain_readout(t, x, lam, self.r)
        else:
            log_p = laws.log_table(t, x, lam, self.r, self.table, self.grid)
        return log_p + self.log_jacobian

    def log_likelihood(self, counts, p):
        """Sum over pixels of log p(counts | p) (``Model.log_likelihood``, unchecked).

        Parameters
        ----------
        counts : array_like, shape (..., roi, roi)
            Counts in ADU; leading dimensions broadcast against those of ``p``.
        p : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b``.

        Returns
        -------
        jax.Array
            One log-likelihood per ROI, the broadcast batch shape.
        """
        lam = self.expected(p)
        return jnp.sum(self.pixel_log_likelihood(counts, lam), axis=(-2, -1))

    def fisher(self, lam):
        """Per-pixel Fisher information about lam (``camera.fisher_information``, exact law).

        Parameters
        ----------
        lam : array_like
            Expected photoelectrons per pixel: >= 1e-6 for the EMCCD (the spline's grid
            starts there; below it the result is NaN), > 0 for the photon camera.

        Returns
        -------
        jax.Array
            Information per photoelectron^2, the shape of ``lam``; ``inf`` at ``lam == 0``.
        """
        lam = jnp.asarray(lam, dtype=jnp.float64)
        if self.law == "photon":
            return 1.0 / lam
        lo, hi = self.fisher_range
        return laws.fisher_spline(lam, self.r, self.fisher_knots, self.fisher_coefficients, lo, hi)

    def step_information(self, lam):
        """Per-pixel information that steers the fit's steps
        (``camera.step_information_unchecked``): ``fisher``, but for the EMCCD's ``poisson`` tier,
        which scores the counts as Poisson photons, that law's own ``1 / lam`` (the camera's is half
        of it).

        Parameters
        ----------
        lam : array_like
            Expected photoelectrons per pixel, as for ``fisher``.

        Returns
        -------
        jax.Array
            Information per photoelectron^2, the shape of ``lam``.
        """
        if self.law == "poisson":
            return 1.0 / jnp.asarray(lam, dtype=jnp.float64)
        return self.fisher(lam)

    # ------------------------------------------------------------------ the prior

    def log_prior(self, p):
        """Log prior density up to a constant (``Model.log_prior``).

        Parameters
        ----------
        p : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b``.

        Returns
        -------
        jax.Array, shape (...)
            ``-inf`` outside the prior's support and for NaN.
        """
        p = jnp.asarray(p, dtype=jnp.float64)
        inside = jnp.all((p >= self.prior_low) & (p <= self.prior_high), axis=-1)
        total = jnp.zeros(p.shape[:-1])
        if self.log_uniform:
            k = np.asarray(self.log_uniform)
            safe = jnp.where(inside[..., None], p[..., k], 1.0)
            total = total - jnp.log(safe).sum(axis=-1)
        if self.quadratic:
            q = np.asarray(self.quadratic)
            z = (p[..., q] - self.prior_centre[q]) / self.prior_scale[q]
            total = total - 0.5 * (z**2).sum(axis=-1)
        return jnp.where(inside, total, -jnp.inf)


jax.tree_util.register_dataclass(
    JaxModel,
    data_fields=[
        "prior_low",
        "prior_high",
        "prior_centre",
        "prior_scale",
        "table",
        "fisher_knots",
        "fisher_coefficients",
    ],
    meta_fields=[
        "roi",
        "pixel_size",
        "pixel_model",
        "law",
        "photoelectrons_per_photon",
        "clock_induced_charge",
        "offset",
        "scale",
        "r",
        "log_jacobian",
        "grid",
        "fisher_range",
        "log_uniform",
        "quadratic",
    ],
)


__all__ = ["SUPPORTED", "TABLES_KEPT", "JaxModel", "enable_x64", "on_device", "release_tables"]
