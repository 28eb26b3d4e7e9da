"""``Model``: one molecule in a square ROI seen through a camera, with its prior."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from bayespsf import psf
from bayespsf._validate import finite_array, real_array
from bayespsf.cameras import Camera
from bayespsf.errors import BayespsfInputError
from bayespsf.model.camera import camera_from_scene, inference_tier
from bayespsf.model.prior import PriorTerms, sample_prior
from bayespsf.model.screen import roi_problems
from bayespsf.scene import Scene, units

MIN_ROI = 5  # six parameters need the spot and a border of background pixels
LOG_PARAMETERS = [2, 3, 4]  # s_x, s_y, N are sampled in log space


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
        self.camera = inference_tier(camera)
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
        """This model for another ROI side, with the prior's defaults for that geometry.

        Parameters
        ----------
        roi : int
            The new odd ROI side in pixels.
        detected : bool, optional
            Give N and b in detected photoelectrons; default: this model's photon unit.

        Returns
        -------
        Model
            The same camera, pixel size, CIC, saturation, pixel model and quantum efficiency.
        """
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
        """Expected photoelectrons per pixel: spot and background in photoelectrons, plus CIC.

        Parameters
        ----------
        params : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b`` (nm; N and b in ``photon_unit``), checked as by
            ``psf.expected_counts``.

        Returns
        -------
        ndarray, shape (..., roi, roi)
        """
        spot = psf.sampled_gaussian if self.pixel_model == "sampled" else psf.expected_counts
        photons = spot(params, self.roi, self.pixel_size)
        return self._detected(photons)

    def _detected(self, photons):
        """Expected photoelectrons of expected photons in N's unit (the spot is linear in N, b)."""
        if self.photoelectrons_per_photon != 1.0:
            photons = photons * self.photoelectrons_per_photon
        return photons + self.clock_induced_charge

    def expected_and_jacobian(self, params: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Expected photoelectrons and their derivatives by the six parameters
        (``psf.expected_counts_and_jacobian``).

        Parameters
        ----------
        params : array_like, shape (..., 6)
            As ``expected``.

        Returns
        -------
        expected : ndarray, shape (..., roi, roi)
        jacobian : ndarray, shape (..., 6, roi, roi)
        """
        mu, jac = psf.expected_counts_and_jacobian(
            params, self.roi, self.pixel_size, self.pixel_model
        )
        if self.photoelectrons_per_photon != 1.0:
            jac = jac * self.photoelectrons_per_photon
        return self._detected(mu), jac

    def check_counts(self, counts: ArrayLike) -> np.ndarray:
        """ROI counts, validated once for the unchecked evaluations.

        Parameters
        ----------
        counts : array_like, shape (..., roi, roi)
            Counts in ADU.

        Returns
        -------
        ndarray
            ``counts`` as a float array.

        Raises
        ------
        BayespsfInputError
            Naming the first ROI with a problem (``roi_problems``) and the number of others.
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
        """Counts as a float array of this model's ROI shape; values are judged per ROI
        (``roi_problems``).

        Parameters
        ----------
        counts : array_like, shape (..., roi, roi)

        Returns
        -------
        ndarray

        Raises
        ------
        BayespsfInputError
            If ``counts`` is not real or its last two dimensions are not ``(roi, roi)``.
        """
        c = real_array("counts", counts)
        if c.ndim < 2 or c.shape[-2:] != (self.roi, self.roi):
            raise BayespsfInputError(
                f"counts must have shape (..., {self.roi}, {self.roi}) for this model, "
                f"got {c.shape}"
            )
        return c

    def roi_problems(self, counts: ArrayLike) -> list[str | None]:
        """Why each ROI cannot be analysed by this model, or ``None`` where it can: NaN or
        infinite pixels, counts outside the camera's domain or far below its offset, equal
        pixels, saturated pixels or an undeclared saturation (``screen.roi_problems``).

        Parameters
        ----------
        counts : array_like, shape (..., roi, roi)

        Returns
        -------
        list of str or None
            One entry per ROI, in C order of the leading dimensions.
        """
        return roi_problems(self.camera, self.check_shape(counts), self.saturation)

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
        """``log_likelihood`` without checking its inputs (the samplers' hot path).

        Parameters
        ----------
        counts : ndarray, shape (..., roi, roi)
            Already validated (``check_counts``).
        params : ndarray, shape (..., 6)
            Finite and inside the PSF's domain.

        Returns
        -------
        ndarray
            One log-likelihood per ROI, the broadcast batch shape.
        """
        lam = self._detected(
            psf.expected_counts_unchecked(params, self.roi, self.pixel_size, self.pixel_model)
        )
        return self.pixel_log_likelihood(counts, lam).sum(axis=(-2, -1))

    def pixel_log_likelihood(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """Per-pixel log p of counts given expected photoelectrons, unchecked: the law of
        ``log_likelihood_unchecked`` (``bayespsf.inference.fused``'s nodes).

        Parameters
        ----------
        counts : ndarray
            Validated counts in ADU.
        expected : ndarray
            Expected photoelectrons (``expected``), broadcasting with ``counts``.

        Returns
        -------
        ndarray
            log p per pixel, the broadcast shape.
        """
        return self.camera.log_likelihood_unchecked(counts, expected)

    def to_photons(self, counts: ArrayLike) -> np.ndarray:
        """Counts converted to N's unit with the camera's mean conversion: what the paper fits
        by least squares.

        Parameters
        ----------
        counts : array_like
            Counts in ADU.

        Returns
        -------
        ndarray
            ``(counts - offset)`` times photoelectrons per ADU over
            ``photoelectrons_per_photon``.
        """
        per_adu, offset = self.camera.photons_per_adu()
        per_adu = np.asarray(per_adu) / self.photoelectrons_per_photon
        return (np.asarray(counts, dtype=np.float64) - offset) * per_adu

    def photon_variance(self, lam: ArrayLike) -> np.ndarray:
        """Variance of ``to_photons`` of a pixel.

        Parameters
        ----------
        lam : array_like
            Expected photoelectrons of the pixel.

        Returns
        -------
        ndarray
            In N's unit squared.
        """
        per_adu, _ = self.camera.photons_per_adu()
        per_adu = np.asarray(per_adu) / self.photoelectrons_per_photon
        return self.camera.variance(lam) * per_adu**2

    def to_unconstrained(self, params: ArrayLike) -> np.ndarray:
        """Sampling coordinates of parameters: positions and the background stay in their own
        units (proposals outside their prior support are rejected); widths and N are logged.

        Parameters
        ----------
        params : array_like, shape (..., 6)
            ``x0 y0 s_x s_y N b``.

        Returns
        -------
        ndarray, shape (..., 6)
            ``x0, y0, log s_x, log s_y, log N, b``.
        """
        z = np.array(params, dtype=np.float64)
        z[..., LOG_PARAMETERS] = np.log(z[..., LOG_PARAMETERS])
        return z

    def from_unconstrained(self, z: ArrayLike) -> np.ndarray:
        """The parameters of sampling coordinates (the inverse of ``to_unconstrained``).

        Parameters
        ----------
        z : array_like, shape (..., 6)

        Returns
        -------
        ndarray, shape (..., 6)
            ``x0 y0 s_x s_y N b``.
        """
        p = np.array(z, dtype=np.float64)
        p[..., LOG_PARAMETERS] = np.exp(p[..., LOG_PARAMETERS])
        return p

    def log_prior(self, params: ArrayLike) -> np.ndarray:
        """Log prior density up to a constant (``prior.PriorTerms``).

        Parameters
        ----------
        params : array_like, shape (..., 6)

        Returns
        -------
        ndarray
            One value per vector; -inf outside the prior's support and for NaN.
        """
        return self._prior_terms(np.asarray(params, dtype=np.float64))

    def prior_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Ends of each parameter's prior support.

        Returns
        -------
        low, high : ndarray, shape (6,)
            Infinite where unbounded.
        """
        return self._prior_terms.low.copy(), self._prior_terms.high.copy()

    def sample_prior(self, n: int, rng: np.random.Generator | int) -> np.ndarray:
        """Parameter vectors drawn from the prior (simulation-based calibration draws its
        truths so).

        Parameters
        ----------
        n : int
            The number of draws, >= 0.
        rng : numpy.random.Generator or int
            A generator or an integer seed.

        Returns
        -------
        ndarray, shape (n, 6)
        """
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
            raise BayespsfInputError(f"n must be a non-negative integer, got {n!r}")
        return sample_prior(self.prior, int(n), np.random.default_rng(rng))

    def log_posterior(
        self, z: ArrayLike, counts: np.ndarray, which: ArrayLike | None = None
    ) -> np.ndarray:
        """Log posterior in sampling coordinates, up to a constant: log prior + log |Jacobian|
        (the log of s_x, s_y, N) + log-likelihood, the last only where the prior is finite.

        Parameters
        ----------
        z : array_like, shape (..., 6)
            Sampling coordinates (``to_unconstrained``), e.g. one row per walker.
        counts : ndarray
            Validated counts (``check_counts``): one ROI ``(roi, roi)`` for every ``z``, or a
            stack ``(m, roi, roi)`` with ``which``.
        which : array_like of int, optional
            The ROI of each draw, the shape of ``z[..., 0]``, so that draws of many ROIs are
            scored in one call.

        Returns
        -------
        ndarray
            The shape of ``z[..., 0]``; -inf outside the prior's support.
        """
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
