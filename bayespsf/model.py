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
from numpy.typing import ArrayLike

from bayespsf import psf
from bayespsf._validate import finite_array, real_array, saturation_plateau, suspect_rois
from bayespsf.cameras import EMCCD, SCMOS, Camera, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import Scene, units

DEFAULT_TIER = {"emccd": "table", "scmos": "exact"}
MIN_ROI = 5  # six parameters need the spot and a border of background pixels
OFFSET_SDS = 5.0  # counts this many readout SDs below the offset are not the camera's
OFFSET_FRACTION = 0.1  # ... nor an ROI with more than this fraction of such pixels
LOG_PARAMETERS = [2, 3, 4]  # s_x, s_y, N are sampled in log space


class PriorTerms:
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
            with np.errstate(over="ignore"):  # beyond ~1e154 scales: density 0, log -inf
                total -= 0.5 * (((p[..., q] - self.centre[q]) / self.scale[q]) ** 2).sum(axis=-1)
        return np.where(inside, total, -np.inf)


def _sample_prior_1d(spec: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` independent draws from one parameter's prior (the law of ``PriorTerms``)."""
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


def _inference_tier(camera: Camera) -> Camera:
    """``camera``, or for an EMCCD whose likelihood tier was not chosen, the same camera with
    the inference default (``DEFAULT_TIER``), as a scene gives it."""
    if isinstance(camera, EMCCD) and not camera.tier_chosen:
        return EMCCD(
            camera.gain, camera.readout_sd, camera.offset, camera.e_per_adu, DEFAULT_TIER["emccd"]
        )
    return camera


class Model:
    """One molecule in a square ROI seen through a camera.

    Parameters
    ----------
    roi : int
        Odd ROI side in pixels, >= ``MIN_ROI`` (5).
    pixel_size : float
        Pixel side in nm.
    camera : Camera
        A ``bayespsf.cameras.Camera``; its ``likelihood`` tier is the model's. An EMCCD built
        without choosing a tier gets the ``table`` tier, as scenes give it.
    prior : dict, optional
        The ``[prior]`` table of a scene (kind and parameters per parameter); ``None`` takes
        the scene defaults for this geometry.
    clock_induced_charge : float, optional
        Mean spurious electrons per pixel (EMCCD), added to the expected photoelectrons.
    saturation : float, optional
        The ADC's full scale in ADU (0: none); ROIs with saturated pixels are rejected.
    pixel_model : {"integrated", "sampled"}, optional
        ``"integrated"`` (default): the spot integrated over each pixel, as the camera records
        it. ``"sampled"``: the Gaussian density at pixel centres times the pixel area, the
        paper's Eq. A3.1 and the model of many fitters; it is biased (its width tends to
        ``sqrt(s0**2 + a**2 / 12)``, Eq. tophat) and is offered to measure that bias.
    quantum_efficiency, photon_unit : float, {"incident", "detected"}, optional
        The camera's quantum efficiency (in (0, 1], default 1) and the unit of N and b:
        ``"incident"`` photons (default; the expected photoelectrons are QE times the spot and
        the background) or ``"detected"`` photoelectrons (``bayespsf.scene.units``).

    Raises
    ------
    BayespsfInputError
        If the geometry, camera, prior, quantum efficiency, photon unit or pixel model is bad.
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
        quantum_efficiency: float = 1.0,
        photon_unit: str = "incident",
    ):
        psf.pixel_centres(roi, pixel_size)  # validates the geometry
        if roi < MIN_ROI:
            raise BayespsfInputError(
                f"roi must be >= {MIN_ROI} pixels for inference, got {roi}: the six parameters "
                "need the spot and a border of background pixels (scenes of smaller ROIs can "
                "be simulated, not fitted)"
            )
        self.pixel_model = psf.check_pixel_model(pixel_model)
        if not isinstance(camera, Camera):
            raise BayespsfInputError(f"camera must be a bayespsf camera, got {camera!r}")
        self.roi = int(roi)
        self.pixel_size = float(pixel_size)
        self.camera = _inference_tier(camera)
        geometry = {"roi": self.roi, "pixel_size": self.pixel_size}
        self.prior = Scene.from_dict({"geometry": geometry, "prior": prior or {}}).to_dict()[
            "prior"
        ]
        self.clock_induced_charge = float(clock_induced_charge)
        self.saturation = float(saturation)
        self.quantum_efficiency, self.photon_unit = units.check(quantum_efficiency, photon_unit)
        self.photoelectrons_per_photon = units.photoelectrons_per_photon(
            self.quantum_efficiency, self.photon_unit
        )
        self._prior_terms = PriorTerms(self.prior)

    @classmethod
    def from_scene(
        cls, scene: Scene, likelihood: str | None = None, pixel_model: str = "integrated"
    ) -> Model:
        """The model of a scene: its geometry, camera (tier ``likelihood``), prior, CIC,
        saturation, quantum efficiency and photon unit.

        Parameters
        ----------
        scene : Scene
        likelihood : str, optional
            The camera's tier; default the scene's ``camera.likelihood``, else ``DEFAULT_TIER``.
        pixel_model : {"integrated", "sampled"}, optional
            See ``Model``.

        Returns
        -------
        Model

        Examples
        --------
        >>> from bayespsf import Model, load_scene, simulate
        >>> scene = load_scene("paper-fig3")
        >>> model = Model.from_scene(scene)
        >>> model.roi, model.pixel_size, model.camera.likelihood
        (19, 79.0, 'table')
        >>> counts, truth = simulate(scene, n=2, seed=1)
        >>> model.log_likelihood(counts, truth.to_numpy()).shape
        (2,)
        """
        cam = scene.camera
        return cls(
            scene.geometry["roi"],
            scene.geometry["pixel_size"],
            camera_from_scene(scene, likelihood),
            scene.prior,
            cam.get("clock_induced_charge", 0.0),
            cam.get("saturation", 0.0),
            pixel_model,
            cam["quantum_efficiency"],
            cam["photon_unit"],
        )

    def for_roi(self, roi: int, *, detected: bool = False) -> Model:
        """This model for ``roi`` x ``roi`` ROIs: the same camera, pixel size, CIC, saturation,
        pixel model, quantum efficiency and photon unit (N and b in detected photoelectrons
        when ``detected``), with the prior's defaults for the new geometry."""
        unit = "detected" if detected else self.photon_unit
        return Model(
            roi,
            self.pixel_size,
            self.camera,
            None,
            self.clock_induced_charge,
            self.saturation,
            self.pixel_model,
            self.quantum_efficiency,
            unit,
        )

    @property
    def photon_unit_label(self) -> str:
        """The unit of N and b in words (``bayespsf.scene.units.label``)."""
        return units.label(self.quantum_efficiency, self.photon_unit)

    def expected(self, params: ArrayLike) -> np.ndarray:
        """Expected photoelectrons per pixel ``(..., roi, roi)`` of ``params`` ``(..., 6)``
        (``x0 y0 s_x s_y N b``): the spot and the background times
        ``photoelectrons_per_photon``, plus the CIC. Raises like ``psf.expected_counts``."""
        spot = psf.sampled_gaussian if self.pixel_model == "sampled" else psf.expected_counts
        photons = spot(params, self.roi, self.pixel_size)
        return self._detected(photons)

    def _detected(self, photons):
        """Expected photoelectrons of expected ``photons`` (spot and background, in N's unit).
        The spot is linear in (N, b), so this is the spot of (QE N, QE b) for incident units."""
        if self.photoelectrons_per_photon != 1.0:
            photons = photons * self.photoelectrons_per_photon
        return photons + self.clock_induced_charge

    def expected_and_jacobian(self, params: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Expected photoelectrons ``(..., roi, roi)`` and their derivatives by the six
        parameters ``(..., 6, roi, roi)`` (``psf.expected_counts_and_jacobian``)."""
        mu, jac = psf.expected_counts_and_jacobian(
            params, self.roi, self.pixel_size, self.pixel_model
        )
        if self.photoelectrons_per_photon != 1.0:
            jac = jac * self.photoelectrons_per_photon
        return self._detected(mu), jac

    def check_counts(self, counts: ArrayLike) -> np.ndarray:
        """ROI counts as a float array of shape ``(..., roi, roi)``, validated once.

        Raises ``BayespsfInputError`` for the first ROI with a problem (``roi_problems``).
        """
        c = self.check_shape(counts)
        problems = self.roi_problems(c)
        bad = [(i, why) for i, why in enumerate(problems) if why is not None]
        if bad:
            i, why = bad[0]
            where = f"ROI {i} of {len(problems)}" if c.ndim > 2 else "the ROI"
            more = f" ({len(bad) - 1} more ROI(s) have problems)" if len(bad) > 1 else ""
            raise BayespsfInputError(f"counts: {where}: {why}{more}")
        return c

    def check_shape(self, counts: ArrayLike) -> np.ndarray:
        """Counts as a float array of shape (..., roi, roi); values are judged per ROI."""
        c = real_array("counts", counts)
        if c.ndim < 2 or c.shape[-2:] != (self.roi, self.roi):
            raise BayespsfInputError(
                f"counts must have shape (..., {self.roi}, {self.roi}) for this model, "
                f"got {c.shape}"
            )
        return c

    def roi_problems(self, counts: ArrayLike) -> list[str | None]:
        """Why each ROI of ``counts`` (..., roi, roi) cannot be analysed by this model, or
        ``None`` where it can: one entry per ROI, in C order of the leading dimensions.

        The reasons: NaN or infinite pixels; counts outside the camera's domain (a photon
        camera's are whole numbers >= 0); every pixel equal (an empty, dead or clipped ROI);
        counts far below the camera's offset (more than ``OFFSET_FRACTION`` of the pixels
        over ``OFFSET_SDS`` readout SDs below it, which the camera law gives a probability
        below 1e-6 each: not ADU above the offset, e.g. an offset subtracted twice); pixels at
        or above a declared ``saturation``; and, where no saturation is declared, a plateau of
        equal maximal counts (``saturation_plateau``) that marks an undeclared one.
        """
        c = self.check_shape(counts)
        flat = c.reshape(-1, self.roi * self.roi)
        _, offset = self.camera.photons_per_adu()
        offset = np.broadcast_to(np.asarray(offset, dtype=np.float64), c.shape[-2:]).ravel()
        readout = np.sqrt(self.camera.variance(np.zeros(c.shape[-2:]))).ravel()
        out: list[str | None] = [None] * len(flat)
        for i in np.flatnonzero(self._suspects(flat, offset, readout)):  # the rest pass
            out[i] = self._roi_problem(flat[i], offset, readout)
        return out

    def _suspects(self, flat, offset, readout) -> np.ndarray:
        """ROIs that may have a problem (``_roi_problem`` decides), by whole-stack screens."""
        try:
            self.camera.check_counts(flat.reshape(-1, self.roi, self.roi))
        except BayespsfInputError:
            return np.ones(len(flat), dtype=bool)
        cam = self.camera
        floor = cam.offset if isinstance(cam, EMCCD) and cam.readout_sd == 0 else -np.inf
        return suspect_rois(
            np.ascontiguousarray(flat, dtype=np.float64),
            np.ascontiguousarray(offset - OFFSET_SDS * readout, dtype=np.float64),
            float(floor),
            OFFSET_FRACTION,
            float(self.saturation),
        )

    def _roi_problem(self, roi, offset, readout) -> str | None:
        bad = np.count_nonzero(~np.isfinite(roi))
        if bad:
            return f"{bad} pixels are NaN or infinite"
        try:
            self.camera.check_counts(roi.reshape(self.roi, self.roi))
        except BayespsfInputError as exc:
            return str(exc)
        if np.all(roi == roi[0]):
            return (
                f"every pixel has the same value ({roi[0]:g}): an empty, dead or clipped ROI "
                "carries no spot"
            )
        cam = self.camera
        if isinstance(cam, EMCCD) and cam.readout_sd == 0 and np.any(roi < cam.offset):
            return (
                f"counts below the offset ({cam.offset:g} ADU) are impossible for an EMCCD "
                f"without readout noise; min is {roi.min():.6g} (declare its readout_sd)"
            )
        below = np.mean(roi < offset - OFFSET_SDS * readout)
        if np.any(readout > 0) and below > OFFSET_FRACTION:
            return (
                f"{below:.0%} of the pixels lie more than {OFFSET_SDS:g} readout SDs below the "
                f"camera's offset ({np.median(offset):g} ADU; median count "
                f"{np.median(roi):.6g}): the counts are not in ADU above the offset (was the "
                "offset subtracted already, or is the camera's offset wrong?)"
            )
        if self.saturation > 0:
            saturated = int(np.count_nonzero(roi >= self.saturation))
            if saturated:
                return (
                    f"{saturated} pixels are saturated (>= {self.saturation:g} ADU); their true "
                    "counts are unknown and the model has no censored likelihood: crop or mask "
                    "the ROI, or lower the EM gain"
                )
            return None
        plateau = saturation_plateau(roi)
        if plateau:
            return (
                f"{plateau} pixels share the ROI's maximum of {roi.max():.6g} ADU, a plateau "
                "that marks a saturated ADC or full well, and no saturation is declared: "
                "posteriors of saturated spots are wrong. Declare the camera's saturation level "
                "(`saturation = ...` in the [camera] table, or Model(saturation=...)), so that "
                "saturated ROIs are named exactly and the others analysed"
            )
        return None

    def log_likelihood(self, counts: ArrayLike, params: ArrayLike) -> np.ndarray:
        """Sum over pixels of log p(counts | params), broadcasting batch dimensions.

        Parameters
        ----------
        counts : array_like, shape (..., roi, roi)
            Counts in ADU (checked: ``check_counts``).
        params : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b`` (nm; N and b in ``photon_unit``).

        Returns
        -------
        ndarray
            One log-likelihood per ROI, the broadcast batch shape.

        Raises
        ------
        BayespsfInputError
            If a ROI has a problem (``roi_problems``) or ``params`` is invalid.
        """
        c = self.check_counts(counts)
        lam = self.expected(finite_array("params", params))
        return self.camera.log_likelihood_unchecked(c, lam).sum(axis=(-2, -1))

    def log_likelihood_unchecked(self, counts: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``log_likelihood`` without checking its inputs: ``counts`` already validated
        (``check_counts``) and ``params`` (..., 6) finite and inside the PSF's domain (the
        samplers' hot path)."""
        lam = self._detected(
            psf.expected_counts_unchecked(params, self.roi, self.pixel_size, self.pixel_model)
        )
        return self.pixel_log_likelihood(counts, lam).sum(axis=(-2, -1))

    def pixel_log_likelihood(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """Per-pixel log p of validated ``counts`` given ``expected`` photoelectrons, unchecked:
        the law of ``log_likelihood_unchecked`` (``bayespsf.inference.fused``'s nodes)."""
        return self.camera.log_likelihood_unchecked(counts, expected)

    def to_photons(self, counts: ArrayLike) -> np.ndarray:
        """Counts converted to N's unit with the camera's mean conversion (offset removed,
        times photoelectrons per ADU, over ``photoelectrons_per_photon``): what the paper fits
        by least squares."""
        per_adu, offset = self.camera.photons_per_adu()
        per_adu = np.asarray(per_adu) / self.photoelectrons_per_photon
        return (np.asarray(counts, dtype=np.float64) - offset) * per_adu

    def photon_variance(self, lam: ArrayLike) -> np.ndarray:
        """Variance of ``to_photons`` of a pixel with ``lam`` expected photoelectrons."""
        per_adu, _ = self.camera.photons_per_adu()
        per_adu = np.asarray(per_adu) / self.photoelectrons_per_photon
        return self.camera.variance(lam) * per_adu**2

    # ------------------------------------------------------------------ posterior

    def to_unconstrained(self, params: ArrayLike) -> np.ndarray:
        """Sampling coordinates: ``x0, y0, log s_x, log s_y, log N, b`` (positions and the
        background stay in their own units; proposals outside their prior support are
        rejected)."""
        z = np.array(params, dtype=np.float64)
        z[..., LOG_PARAMETERS] = np.log(z[..., LOG_PARAMETERS])
        return z

    def from_unconstrained(self, z: ArrayLike) -> np.ndarray:
        """The parameters ``x0 y0 s_x s_y N b`` of sampling coordinates ``z`` (..., 6)."""
        p = np.array(z, dtype=np.float64)
        p[..., LOG_PARAMETERS] = np.exp(p[..., LOG_PARAMETERS])
        return p

    def log_prior(self, params: ArrayLike) -> np.ndarray:
        """Log prior density of ``params`` (..., 6) up to a constant; -inf outside its support
        (and for NaN)."""
        return self._prior_terms(np.asarray(params, dtype=np.float64))

    def prior_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper ends of each parameter's prior support (infinite where unbounded)."""
        return self._prior_terms.low.copy(), self._prior_terms.high.copy()

    def sample_prior(self, n: int, rng: np.random.Generator | int) -> np.ndarray:
        """``n`` parameter vectors ``(n, 6)`` drawn from the prior (simulation-based
        calibration draws its truths so); ``rng`` is a Generator or an integer seed."""
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
            raise BayespsfInputError(f"n must be a non-negative integer, got {n!r}")
        rng = np.random.default_rng(rng)
        return np.column_stack(
            [_sample_prior_1d(self.prior[name], int(n), rng) for name in PARAMETER_NAMES]
        )

    def log_posterior(
        self, z: ArrayLike, counts: np.ndarray, which: ArrayLike | None = None
    ) -> np.ndarray:
        """Log posterior in sampling coordinates ``z`` (..., 6), up to a constant: log prior +
        log |Jacobian| (the log of s_x, s_y, N) + log-likelihood. Vectorised over walkers; the
        likelihood is evaluated only where the prior is finite. ``counts`` must already be
        validated (``check_counts``): one ROI for every ``z``, or a stack ``(m, roi, roi)``
        with ``which`` (integers, the shape of ``z[..., 0]``) naming each draw's ROI, so that
        draws of many ROIs are scored in one call."""
        z = np.asarray(z, dtype=np.float64)
        with np.errstate(over="ignore"):  # exp overflow -> inf -> outside the prior's support
            p = self.from_unconstrained(z)
        out = self.log_prior(p) + z[..., LOG_PARAMETERS].sum(axis=-1)
        inside = np.isfinite(out)
        if inside.any():
            # inside the prior's support the parameters are valid: skip the PSF's input checks
            data = counts if which is None else counts[np.asarray(which)[inside]]
            out[inside] += self.log_likelihood_unchecked(data, p[inside])
        out[~np.isfinite(out)] = -np.inf
        return out

    def __repr__(self) -> str:
        extra = ", pixel_model='sampled'" if self.pixel_model == "sampled" else ""
        if self.quantum_efficiency != 1.0:
            extra += (
                f", quantum_efficiency={self.quantum_efficiency!r}, "
                f"photon_unit={self.photon_unit!r}"
            )
        return (
            f"Model(roi={self.roi}, pixel_size={self.pixel_size:g}, camera={self.camera!r}{extra})"
        )


__all__ = ["PARAMETER_NAMES", "Model", "camera_from_scene"]
