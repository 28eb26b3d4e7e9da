"""The inference model: geometry, camera law (one likelihood tier) and prior of one molecule.

Built from the same scene as the simulator (``Model.from_scene``), or from geometry and a
camera for real data. It maps parameters ``x0 y0 s_x s_y N b`` (``PARAMETER_NAMES``) to
expected photons per pixel and scores counts under the camera law, vectorised over leading
batch dimensions (walkers, molecules).

What the model leaves out of the simulator's effects, by design: ADC rounding (the continuous
density is used for whole-ADU counts) and saturation (a ROI with a saturated pixel is rejected
with an error: its likelihood would need censoring). Clock-induced charge is added to the
expected photoelectrons, which is exact for the Poisson-Gamma law.
"""

from __future__ import annotations

import numpy as np

from bayespsf import psf
from bayespsf._checks import finite_array
from bayespsf.cameras import EMCCD, SCMOS, Camera, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import Scene

DEFAULT_TIER = {"emccd": "table", "scmos": "exact"}
LOG_PARAMETERS = [2, 3, 4]  # s_x, s_y, N are sampled in log space


class _PriorTerms:
    """The prior table as arrays, so that the log prior of many walkers is a few array passes.

    Up to a constant: uniform 0, log-uniform ``-log x``, normal ``-(x - mean)^2 / (2 sd^2)``,
    half-normal ``-x^2 / (2 scale^2)``; ``-inf`` outside the support.
    """

    def __init__(self, prior: dict):
        specs = [prior[name] for name in PARAMETER_NAMES]
        kinds = np.array([spec["kind"] for spec in specs])
        self.low, self.high = np.full(6, -np.inf), np.full(6, np.inf)
        self.centre, self.scale = np.zeros(6), np.ones(6)
        for k, spec in enumerate(specs):
            if spec["kind"] in ("uniform", "log-uniform"):
                self.low[k], self.high[k] = spec["low"], spec["high"]
            elif spec["kind"] == "normal":
                self.centre[k], self.scale[k] = spec["mean"], spec["sd"]
            else:
                self.low[k], self.scale[k] = 0.0, spec["scale"]
        self.log_uniform = np.flatnonzero(kinds == "log-uniform")
        self.quadratic = np.flatnonzero((kinds == "normal") | (kinds == "half-normal"))

    def __call__(self, p: np.ndarray) -> np.ndarray:
        inside = np.all((p >= self.low) & (p <= self.high), axis=-1)
        total = np.zeros(p.shape[:-1])
        if self.log_uniform.size:
            safe = np.where(inside[..., None], p[..., self.log_uniform], 1.0)
            total -= np.log(safe).sum(axis=-1)
        if self.quadratic.size:
            q = self.quadratic
            total -= 0.5 * (((p[..., q] - self.centre[q]) / self.scale[q]) ** 2).sum(axis=-1)
        return np.where(inside, total, -np.inf)


def _sample_prior_1d(spec: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` independent draws from one parameter's prior (the law of ``_PriorTerms``)."""
    kind = spec["kind"]
    if kind == "uniform":
        return rng.uniform(spec["low"], spec["high"], n)
    if kind == "log-uniform":
        return np.exp(rng.uniform(np.log(spec["low"]), np.log(spec["high"]), n))
    if kind == "normal":
        return rng.normal(spec["mean"], spec["sd"], n)
    return np.abs(rng.normal(0.0, spec["scale"], n))  # half-normal


def camera_from_scene(scene: Scene, likelihood: str | None = None) -> Camera:
    """The camera law a scene declares, with the likelihood tier ``likelihood`` (or the scene's
    ``camera.likelihood``, or the default: ``table`` for EMCCD, ``exact`` for sCMOS)."""
    cam = scene.camera
    kind = cam["kind"]
    tier = likelihood or cam.get("likelihood") or DEFAULT_TIER.get(kind)
    if kind == "photon":
        if tier not in (None, "exact", "poisson"):
            raise BayespsfInputError(f"likelihood {tier!r} does not apply to a photon camera")
        return Photon()
    if kind == "emccd":
        return EMCCD(cam["gain"], cam["readout_sd"], cam["offset"], cam["e_per_adu"], tier)
    return SCMOS(cam["gain"], cam["offset"], cam["variance"], likelihood=tier)


class Model:
    """One molecule in a square ROI seen through a camera.

    Parameters
    ----------
    roi, pixel_size
        Odd ROI side in pixels; pixel size in nm.
    camera
        A ``bayespsf.cameras.Camera`` (its ``likelihood`` tier is the model's).
    prior
        The ``[prior]`` table of a scene (kind and parameters per parameter); ``None`` takes
        the scene defaults for this geometry.
    clock_induced_charge
        Mean spurious electrons per pixel (EMCCD), added to the expected photoelectrons.
    saturation
        The ADC's full scale in ADU (0: none); ROIs with saturated pixels are rejected.
    pixel_model
        ``"integrated"`` (default): the spot integrated over each pixel, as the camera records
        it. ``"sampled"``: the Gaussian density at pixel centres times the pixel area, the
        paper's Eq. A3.1 and the model of many fitters; it is biased (its width tends to
        ``sqrt(s0**2 + a**2 / 12)``, Eq. tophat) and is offered to measure that bias.
    """

    def __init__(
        self,
        roi: int,
        pixel_size: float,
        camera: Camera,
        prior: dict | None = None,
        clock_induced_charge: float = 0.0,
        saturation: float = 0.0,
        pixel_model: str = "integrated",
    ):
        psf.pixel_centres(roi, pixel_size)  # validates the geometry
        self.pixel_model = psf._check_pixel_model(pixel_model)
        if not isinstance(camera, Camera):
            raise BayespsfInputError(f"camera must be a bayespsf camera, got {camera!r}")
        self.roi = int(roi)
        self.pixel_size = float(pixel_size)
        self.camera = camera
        geometry = {"roi": self.roi, "pixel_size": self.pixel_size}
        self.prior = Scene.from_dict({"geometry": geometry, "prior": prior or {}}).to_dict()[
            "prior"
        ]
        self.clock_induced_charge = float(clock_induced_charge)
        self.saturation = float(saturation)
        self._prior_terms = _PriorTerms(self.prior)

    @classmethod
    def from_scene(
        cls, scene: Scene, likelihood: str | None = None, pixel_model: str = "integrated"
    ) -> Model:
        """The model of a scene: its geometry, camera (tier ``likelihood``), prior and CIC."""
        cam = scene.camera
        return cls(
            scene.geometry["roi"],
            scene.geometry["pixel_size"],
            camera_from_scene(scene, likelihood),
            scene.prior,
            cam.get("clock_induced_charge", 0.0),
            cam.get("saturation", 0.0),
            pixel_model,
        )

    def expected(self, params) -> np.ndarray:
        """Expected photoelectrons per pixel ``(..., roi, roi)`` (PSF, background and CIC)."""
        spot = psf.sampled_gaussian if self.pixel_model == "sampled" else psf.expected_counts
        return spot(params, self.roi, self.pixel_size) + self.clock_induced_charge

    def expected_and_jacobian(self, params):
        """Expected photoelectrons and their derivatives ``(..., 6, roi, roi)``."""
        mu, jac = psf.expected_counts_and_jacobian(
            params, self.roi, self.pixel_size, self.pixel_model
        )
        return mu + self.clock_induced_charge, jac

    def check_counts(self, counts) -> np.ndarray:
        """ROI counts as a float array of shape ``(..., roi, roi)``, validated once."""
        c = finite_array("counts", counts)
        if c.ndim < 2 or c.shape[-2:] != (self.roi, self.roi):
            raise BayespsfInputError(
                f"counts must have shape (..., {self.roi}, {self.roi}) for this model, "
                f"got {c.shape}"
            )
        self.camera._check_counts(c)
        flat = c.reshape(-1, self.roi * self.roi)
        constant = np.all(flat == flat[:, :1], axis=1)
        if np.any(constant):
            raise BayespsfInputError(
                f"counts: {int(constant.sum())} ROI(s) have the same value in every pixel "
                f"(e.g. all {flat[np.argmax(constant), 0]:g}): an empty, dead or clipped ROI "
                "carries no spot"
            )
        cam = self.camera
        if isinstance(cam, EMCCD) and cam.readout_sd == 0 and np.any(c < cam.offset):
            raise BayespsfInputError(
                f"counts below the offset ({cam.offset:g} ADU) are impossible for an EMCCD "
                f"without readout noise; min is {c.min():.6g} (declare its readout_sd)"
            )
        if self.saturation > 0 and np.any(c >= self.saturation):
            raise BayespsfInputError(
                f"counts: {int(np.count_nonzero(c >= self.saturation))} pixels are saturated "
                f"(>= {self.saturation:g} ADU); their true counts are unknown and the model has "
                "no censored likelihood: crop or mask the ROI, or lower the EM gain"
            )
        return c

    def log_likelihood(self, counts, params) -> np.ndarray:
        """Sum over pixels of log p(counts | params), broadcasting batch dimensions."""
        c = self.check_counts(counts)
        lam = self.expected(finite_array("params", params))
        return self.camera._log_likelihood(c, lam).sum(axis=(-2, -1))

    def to_photons(self, counts) -> np.ndarray:
        """Counts converted to photons with the camera's mean conversion (offset removed,
        times photons per ADU): what the paper fits by least squares."""
        per_adu, offset = self.camera.photons_per_adu()
        return (np.asarray(counts, dtype=np.float64) - offset) * per_adu

    def photon_variance(self, lam) -> np.ndarray:
        """Variance of ``to_photons`` of a pixel with ``lam`` expected photoelectrons."""
        per_adu, _ = self.camera.photons_per_adu()
        return self.camera.variance(lam) * np.asarray(per_adu) ** 2

    # ------------------------------------------------------------------ posterior (issue 5)

    def to_unconstrained(self, params) -> np.ndarray:
        """Sampling coordinates: ``x0, y0, log s_x, log s_y, log N, b`` (positions and the
        background stay in their own units; proposals outside their prior support are
        rejected)."""
        z = np.array(params, dtype=np.float64)
        z[..., LOG_PARAMETERS] = np.log(z[..., LOG_PARAMETERS])
        return z

    def from_unconstrained(self, z) -> np.ndarray:
        p = np.array(z, dtype=np.float64)
        p[..., LOG_PARAMETERS] = np.exp(p[..., LOG_PARAMETERS])
        return p

    def log_prior(self, params) -> np.ndarray:
        """Log prior density of ``params`` (..., 6) up to a constant; -inf outside its support
        (and for NaN)."""
        return self._prior_terms(np.asarray(params, dtype=np.float64))

    def prior_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper ends of each parameter's prior support (infinite where unbounded)."""
        return self._prior_terms.low.copy(), self._prior_terms.high.copy()

    def sample_prior(self, n: int, rng) -> np.ndarray:
        """``n`` parameter vectors ``(n, 6)`` drawn from the prior (simulation-based
        calibration draws its truths so); ``rng`` is a Generator or an integer seed."""
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
            raise BayespsfInputError(f"n must be a non-negative integer, got {n!r}")
        rng = np.random.default_rng(rng)
        return np.column_stack(
            [_sample_prior_1d(self.prior[name], int(n), rng) for name in PARAMETER_NAMES]
        )

    def log_posterior(self, z, counts) -> np.ndarray:
        """Log posterior in sampling coordinates ``z`` (..., 6), up to a constant: log prior +
        log |Jacobian| (the log of s_x, s_y, N) + log-likelihood. Vectorised over walkers; the
        likelihood is evaluated only where the prior is finite. ``counts`` must already be
        validated (``check_counts``)."""
        z = np.asarray(z, dtype=np.float64)
        with np.errstate(over="ignore"):  # exp overflow -> inf -> outside the prior's support
            p = self.from_unconstrained(z)
        out = self.log_prior(p) + z[..., LOG_PARAMETERS].sum(axis=-1)
        inside = np.isfinite(out)
        if inside.any():
            # inside the prior's support the parameters are valid: skip the PSF's input checks
            lam = (
                psf.expected_counts_unchecked(
                    p[inside], self.roi, self.pixel_size, self.pixel_model
                )
                + self.clock_induced_charge
            )
            out[inside] += self.camera._log_likelihood(counts, lam).sum(axis=(-2, -1))
        out[~np.isfinite(out)] = -np.inf
        return out

    def __repr__(self) -> str:
        sampled = ", pixel_model='sampled'" if self.pixel_model == "sampled" else ""
        return (
            f"Model(roi={self.roi}, pixel_size={self.pixel_size:g}, camera={self.camera!r}"
            f"{sampled})"
        )


__all__ = ["PARAMETER_NAMES", "Model", "camera_from_scene"]
