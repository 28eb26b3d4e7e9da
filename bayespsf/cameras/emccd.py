"""Electron-multiplying CCD: Poisson photoelectrons, Gamma-distributed EM gain, Gaussian readout.

Per pixel (Basden, Haniff & Mackay, MNRAS 345 (2003); Hirsch et al., PLoS ONE 8 (2013)):

* photoelectrons ``n ~ Poisson(lam)``, ``lam`` the expected photoelectrons (the quantum
  efficiency and any clock-induced charge belong to the model, ``bayespsf.model.Model``, which
  hands the camera the final ``lam``);
* the EM register turns ``n >= 1`` into ``Gamma(n, gain)`` electrons; ``n = 0`` stays 0;
* readout adds ``Normal(0, readout_sd)`` electrons;
* counts in ADU are ``offset + electrons / e_per_adu``.

Likelihood tiers (``likelihood=``), each a trade of accuracy for time (see benchmarks/README.md):

``"exact"``
    The readout convolution by adaptive Gauss-Legendre quadrature, ~1e-12 in log p against
    mpmath: the reference. Without readout it is the closed form below, exactly.
``"table"``
    The exact law precomputed once per ``readout_sd / gain`` on a grid of log lam and a
    sqrt-like count coordinate and interpolated bicubically (``._emccd_table``); exact
    quadrature outside the grid. Without readout it is the closed form, like ``"exact"``.
``"high-gain"``
    The closed form ``exp(-lam - x/G) sqrt(lam / (x G)) I1(2 sqrt(lam x / G)) / G`` for the
    amplified electrons, with readout ignored for them; the zero-electron atom is convolved with
    the readout Gaussian exactly, so counts at or below the offset keep a finite likelihood.
``"gaussian"``
    The paper's chi-square model (Eq. photonuncerts of DeSantis, DeCenzo, Li & Wang,
    Opt. Express 18 (2010)): Normal with the law's exact mean ``lam G`` and variance
    ``2 lam G^2 + readout_sd^2`` (electrons), i.e. ``2 lam + sigma_b^2`` in photons.
``"poisson"``
    The EM register ignored: ``counts`` converted to photons ``(counts - offset) e_per_adu / G``
    and scored with the Poisson pmf (continued to real values with ``gammaln``); no support
    below zero photons (``-inf``).

The atom without readout: with ``readout_sd = 0`` the law puts probability ``exp(-lam)`` on
``counts == offset`` exactly. ``log_likelihood`` is then a log density with respect to Lebesgue
measure plus a unit point mass at the offset: at the offset it returns ``-lam`` (the log mass),
elsewhere the log density in ADU; below the offset ``-inf``.

Numerical domain: ``gain >= 1``; ``readout_sd = 0`` or ``RATIO_MIN <= readout_sd / gain <=
RATIO_MAX``; ``expected`` in ``[0, MAX_EXPECTED]``; ``|counts - offset| e_per_adu / gain <=
MAX_GAIN_UNITS``. There every tier's ``log_likelihood`` is finite, or ``-inf`` exactly outside
the tier's support, and no operation warns; outside it ``BayespsfInputError`` names the limit.
docs/cameras.md ("Numerical domain") lists the supports, the score's limits and where the
``exact`` tier takes the readout-free closed form; tests/cameras/test_camera_domain.py checks
all of it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from bayespsf._validate import nonnegative_array, scalar_in_range
from bayespsf.cameras import _emccd_fisher, _emccd_law, _emccd_table
from bayespsf.cameras.base import Camera
from bayespsf.cameras.draws import add_normal, gamma_register
from bayespsf.cameras.photon import poisson_log_pmf, poisson_score
from bayespsf.errors import BayespsfInputError

TIERS = ("exact", "table", "high-gain", "gaussian", "poisson")
MAX_EXPECTED = 1e10  # photons per pixel: the readout quadrature is validated up to here
RATIO_MIN, RATIO_MAX = _emccd_law.RATIO_MIN, _emccd_law.RATIO_MAX  # readout_sd / gain, if > 0
MAX_GAIN_UNITS = _emccd_law.T_MAX  # |counts - offset| * e_per_adu / gain
FISHER_METHODS = ("exact", "excess-noise")


class EMCCD(Camera):
    """An EMCCD camera.

    Parameters
    ----------
    gain : float
        Mean EM gain G (electrons out per photoelectron), >= 1.
    readout_sd : float
        Readout noise SD in electrons: 0, or between ``RATIO_MIN`` and ``RATIO_MAX`` times
        ``gain`` (see the module docstring for the whole numerical domain).
    offset : float
        Bias added to every pixel, in ADU.
    e_per_adu : float
        Electrons per ADU (the A/D conversion factor), > 0.
    likelihood : str, optional
        One of ``TIERS``; see the module docstring. Not given: ``exact`` for this camera's own
        calls (the reference), and ``table`` once the camera is used for inference
        (``bayespsf.Model`` takes the table tier for a camera whose tier was not chosen, as a
        scene does), so that inference has one default tier however the camera was made.
        ``tier_chosen`` says whether it was given.

    Attributes
    ----------
    gain, readout_sd, offset, e_per_adu : float
        The constructor's arguments, as floats.
    likelihood : str
        The tier (``"exact"`` when none was given).
    tier_chosen : bool
        Whether ``likelihood`` was given.

    Raises
    ------
    BayespsfInputError
        If a parameter is outside the numerical domain of the module docstring, or
        ``likelihood`` is not one of ``TIERS``.

    See Also
    --------
    SCMOS : a camera without EM gain, with per-pixel maps.
    Photon : ideal photon counting.

    Notes
    -----
    Per pixel: photoelectrons ``n ~ Poisson(lam)``; the EM register turns ``n >= 1`` into
    ``Gamma(n, gain)`` electrons (``n = 0`` stays 0); readout adds ``Normal(0, readout_sd)``
    electrons; counts are ``offset + electrons / e_per_adu`` ADU (Basden, Haniff & Mackay,
    MNRAS 345 (2003); Hirsch et al., PLoS ONE 8 (2013)). The tiers, their accuracy and the
    numerical domain are described in the module docstring and docs/cameras.md.

    Examples
    --------
    >>> from bayespsf.cameras import EMCCD
    >>> camera = EMCCD(gain=100.0, readout_sd=10.0, offset=100.0)
    >>> camera.log_likelihood([100.0, 300.0, 1100.0], expected=5.0).round(3)
    array([-7.69 , -6.729, -8.08 ])
    >>> camera.fisher_information([1.0, 10.0], method="excess-noise").round(4)
    array([0.4975, 0.05  ])
    """

    fisher_methods = FISHER_METHODS

    def __init__(
        self,
        gain: float,
        readout_sd: float = 0.0,
        offset: float = 0.0,
        e_per_adu: float = 1.0,
        likelihood: str | None = None,
    ):
        self.gain = scalar_in_range("gain", gain, 1.0)
        self.readout_sd = scalar_in_range("readout_sd", readout_sd, 0.0)
        ratio = self.readout_sd / self.gain
        if ratio != 0 and not RATIO_MIN <= ratio <= RATIO_MAX:
            raise BayespsfInputError(
                f"readout_sd must be 0 or in [{RATIO_MIN:g}, {RATIO_MAX:g}] x gain (readout_sd / "
                f"gain = {ratio:.3g}): the EMCCD law is computed and tested there; use "
                "readout_sd=0 for a readout-free camera"
            )
        self.offset = scalar_in_range("offset", offset, -np.inf)
        self.e_per_adu = scalar_in_range("e_per_adu", e_per_adu, 0.0, low_inclusive=False)
        self.tier_chosen = likelihood is not None
        likelihood = "exact" if likelihood is None else likelihood
        if likelihood not in TIERS:
            raise BayespsfInputError(f"likelihood must be one of {TIERS}, got {likelihood!r}")
        self.likelihood = likelihood

    @property
    def readout_in_gain_units(self) -> float:
        """``r = readout_sd / gain``: the one number (with lam) the law in gain units needs."""
        return self.readout_sd / self.gain

    @property
    def _log_jacobian(self) -> float:
        """``log(e_per_adu / gain)``: a density in gain units to one in ADU."""
        return float(np.log(self.e_per_adu / self.gain))

    def law_arrays(self) -> dict:
        """The law's constants and tables as plain numbers and arrays, for array backends.

        Returns
        -------
        dict
            ``tier`` (``likelihood``); ``gain``, ``readout_sd``, ``offset``, ``e_per_adu``;
            ``r`` (``readout_in_gain_units``); ``log_jacobian``, ``log(e_per_adu / gain)``
            (a density in gain units to one per ADU); ``table_range``, the ``r`` the
            ``table`` tier interpolates in (``R_MIN``, ``R_MAX`` of ``_emccd_table``);
            ``table``: for the ``table`` tier with ``r`` in that range, the interpolation
            table (coefficients, grid starts, sizes and steps, and the grids' limits; keys
            listed in ``_emccd_table.table_arrays``), else ``None``; ``fisher``: the spline of
            ``log(lam I(lam))`` behind ``fisher_information`` (``knots`` in log10 lam and
            ``coefficients`` (4, knots - 1), highest power first).

        Notes
        -----
        The tables are built on the machine's first use of this ``r`` (seconds), then read
        from the on-disk cache.
        """
        r, (low, high) = self.readout_in_gain_units, (_emccd_table.R_MIN, _emccd_table.R_MAX)
        table = self.likelihood == "table" and low <= r <= high
        return dict(
            tier=self.likelihood, gain=self.gain, readout_sd=self.readout_sd,
            offset=self.offset, e_per_adu=self.e_per_adu, r=r, log_jacobian=self._log_jacobian,
            table_range=(low, high), table=_emccd_table.table_arrays(r) if table else None,
            fisher=_emccd_fisher.spline_arrays(r),
        )  # fmt: skip

    def gain_units(self, counts: ArrayLike) -> np.ndarray:
        """Counts in ADU as electrons over gain, ``t = (counts - offset) e_per_adu / gain``.

        Parameters
        ----------
        counts : array_like
            Counts in ADU.

        Returns
        -------
        ndarray
            ``t``, the shape of ``counts``.

        Notes
        -----
        Without readout, where ``t == 0`` is the atom and ``t < 0`` outside the support, a
        nonzero ``counts - offset`` whose scaled value underflows keeps its sign as the
        smallest subnormal. With readout the law is continuous at 0, and the two array passes
        this costs (~4% of a table-tier likelihood call) are skipped.
        """
        x = np.asarray(counts, dtype=np.float64) - self.offset
        t = x * (self.e_per_adu / self.gain)
        if self.readout_sd > 0:
            return t
        underflow = (t == 0) & (x != 0)
        if np.any(underflow):
            tiny = np.copysign(np.finfo(np.float64).smallest_subnormal, x)
            t = np.where(underflow, tiny, t)
        return t

    def log_likelihood(self, counts: ArrayLike, expected: ArrayLike) -> np.ndarray:
        """Element-wise log p(counts | expected) under this camera's likelihood tier.

        Parameters
        ----------
        counts : array_like
            Counts in ADU, finite, within ``offset +/- MAX_GAIN_UNITS * gain / e_per_adu``.
        expected : array_like
            Expected photoelectrons per pixel, in ``[0, MAX_EXPECTED]`` for the ``exact`` and
            ``table`` tiers with readout.

        Returns
        -------
        ndarray
            Log density per ADU (at the offset without readout: the log mass of the atom), the
            broadcast shape of the arguments; ``-inf`` outside the tier's support.

        Raises
        ------
        BayespsfInputError
            If an argument is outside the numerical domain (the message names it).

        See Also
        --------
        Camera.log_likelihood : the checks every camera makes.

        Examples
        --------
        >>> from bayespsf.cameras import EMCCD
        >>> EMCCD(gain=100.0, likelihood="high-gain").log_likelihood([0.0, 500.0], 5.0).round(3)
        array([-5.   , -6.715])
        """
        self._check_expected(expected)
        return super().log_likelihood(counts, expected)

    def score(self, counts: ArrayLike, expected: ArrayLike) -> np.ndarray:
        """Element-wise ``d log p(counts | expected) / d expected`` under this tier.

        Parameters
        ----------
        counts : array_like
            Counts in ADU (the domain of ``log_likelihood``).
        expected : array_like
            Expected photoelectrons per pixel (the domain of ``log_likelihood``).

        Returns
        -------
        ndarray
            The derivative per photoelectron, the broadcast shape of the arguments; ``+inf``
            at ``expected == 0`` where the count is impossible without photons.

        Raises
        ------
        BayespsfInputError
            If an argument is outside the numerical domain.
        """
        self._check_expected(expected)
        return super().score(counts, expected)

    def _check_expected(self, expected):
        """``expected <= MAX_EXPECTED`` for the tiers with the readout quadrature (checked in
        the public methods: the score's differences may step just above it)."""
        lam = nonnegative_array("expected", expected)
        r = self.readout_in_gain_units
        if self.likelihood in ("exact", "table") and r > 0 and lam.max(initial=0.0) > MAX_EXPECTED:
            raise BayespsfInputError(
                f"expected must be <= {MAX_EXPECTED:g} photons per pixel for the EMCCD law with "
                f"readout (got {lam.max():.3g}); no camera pixel holds that many"
            )

    def check_counts(self, counts):
        c = np.asarray(counts, dtype=np.float64)  # t rises with the counts: its ends bound |t|
        t = np.abs(self.gain_units([c.min(initial=self.offset), c.max(initial=self.offset)])).max()
        if t > MAX_GAIN_UNITS:
            half_width = MAX_GAIN_UNITS * self.gain / self.e_per_adu
            raise BayespsfInputError(
                f"counts must be within offset +/- {half_width:.3g} ADU for this camera "
                f"(|counts - offset| e_per_adu / gain <= {MAX_GAIN_UNITS:g}); got "
                f"{t * self.gain / self.e_per_adu:.3g} ADU from the offset"
            )

    def log_likelihood_unchecked(self, counts, expected):
        t = self.gain_units(counts)
        log_jacobian = self._log_jacobian
        r = self.readout_in_gain_units
        tier = self.likelihood
        if tier == "exact" and r > 0:
            return _emccd_law.log_exact(t, expected, r) + log_jacobian
        if tier == "table" and r > 0:
            return _emccd_table.log_table(t, expected, r) + log_jacobian
        if tier in ("exact", "table", "high-gain"):
            return self._log_high_gain(t, expected, r, log_jacobian)
        if tier == "gaussian":
            return _emccd_law.gaussian_log_pdf(t, expected, r) + log_jacobian
        return np.where(t >= 0, poisson_log_pmf(np.maximum(t, 0.0), expected), -np.inf) + (
            log_jacobian
        )

    @staticmethod
    def _log_high_gain(t, lam, r, log_jacobian):
        amplified = _emccd_law.log_high_gain(t, lam)
        if r == 0:
            # the atom at t == 0 is a probability mass: no Jacobian there
            return np.where(t == 0, amplified, amplified + log_jacobian)
        continuous = np.where(t == 0, -np.inf, amplified)
        atom = -lam + _emccd_law.log_normal_pdf(t, r)
        return np.logaddexp(atom, continuous) + log_jacobian

    def _sample(self, expected, rng):
        electrons = gamma_register(rng.poisson(expected), self.gain, rng)
        if self.readout_sd > 0:
            electrons = add_normal(electrons, self.readout_sd, rng)
        return self.offset + electrons / self.e_per_adu

    def score_unchecked(self, counts, expected):
        """``d log p / d lam`` in closed form for each tier but ``high-gain`` with readout:
        the exact tier by quadrature with readout (``log_and_score_exact``), the Bessel ratio
        without; the ``table`` tier as the exact derivative of its interpolant
        (``_emccd_table.score_table``) where it interpolates; ``gaussian`` and ``poisson`` from
        their formulas. Elsewhere (``high-gain`` with readout, the ``table`` tier off its grids),
        and at ``lam == 0`` with readout, by differences of the tier's own log-likelihood.
        Without readout at ``lam == 0`` the one-sided derivative is ``+inf`` above the
        offset.

        Parameters
        ----------
        counts, expected : ndarray
            As ``Camera.log_likelihood_unchecked``.

        Returns
        -------
        ndarray
            ``d log p / d lam`` per photon, the arguments' shape.
        """
        r = self.readout_in_gain_units
        tier = self.likelihood
        if tier == "table" and r != 0:
            return self.log_likelihood_and_score_unchecked(counts, expected)[1]
        t = self.gain_units(counts)
        if tier == "poisson":
            return poisson_score(t, expected)
        if tier == "gaussian":
            return _emccd_law.gaussian_score(t, expected, r)
        if r == 0:
            return _emccd_law.readout_free_score(t, expected)
        if tier != "exact":
            return super().score_unchecked(counts, expected)
        t, lam = np.broadcast_arrays(t, expected)
        out = np.empty(t.shape)
        positive = lam > 0
        out[positive] = _emccd_law.log_and_score_exact(t[positive], lam[positive], r)[1]
        if not positive.all():
            zero = ~positive
            out[zero] = super().score_unchecked(np.asarray(counts, float)[zero], lam[zero])
        return out

    def log_likelihood_and_score_unchecked(self, counts, expected):
        """The ``table`` tier with readout: log p and its derivative from one compiled pass over
        the table (``_emccd_table.log_and_score_table``), the score by differences of the
        tier's log-likelihood where it does not interpolate. Other tiers: the two methods.

        Parameters
        ----------
        counts, expected : ndarray
            As ``Camera.log_likelihood_unchecked``.

        Returns
        -------
        log_p, score : ndarray
            Each of the arguments' shape.
        """
        if self.likelihood != "table" or self.readout_in_gain_units == 0:
            return super().log_likelihood_and_score_unchecked(counts, expected)
        t = self.gain_units(counts)
        log_p, score = _emccd_table.log_and_score_table(t, expected, self.readout_in_gain_units)
        missing = np.isnan(score)
        if missing.any():
            c, lam = np.broadcast_arrays(np.asarray(counts, float), expected)
            score[missing] = super().score_unchecked(c[missing], lam[missing])
        return log_p + self._log_jacobian, score

    def score_and_curvature_unchecked(self, counts, expected):
        """The ``table`` tier with readout: both from the interpolant in one compiled pass where
        ``lam >= 1``; below (the base class's differences over 1e-4 photons, a secant where the
        tangent is unbounded) and off the table, the base class's.

        Parameters
        ----------
        counts, expected : ndarray
            As ``Camera.log_likelihood_unchecked``.

        Returns
        -------
        score, curvature : ndarray
            ``d log p / d lam`` and ``d^2 log p / d lam^2``, each of the arguments' shape.
        """
        r = self.readout_in_gain_units
        if self.likelihood != "table" or r == 0:
            return super().score_and_curvature_unchecked(counts, expected)
        c, lam = np.broadcast_arrays(np.asarray(counts, float), np.asarray(expected, float))
        t = self.gain_units(c)
        _, score, curvature = _emccd_table.log_and_score_table(t, lam, r, curvature=True)
        missing = np.isnan(curvature) | (lam < 1.0)
        if missing.any():
            score[missing], curvature[missing] = super().score_and_curvature_unchecked(
                c[missing], lam[missing]
            )
        return score, curvature

    def _variance(self, expected):
        """``(2 lam G^2 + readout_sd^2) / e_per_adu^2`` (ADU^2)."""
        return (2.0 * expected * self.gain**2 + self.readout_sd**2) / self.e_per_adu**2

    def photons_per_adu(self):
        return self.e_per_adu / self.gain, self.offset

    def fisher_information(self, expected: ArrayLike, method: str = "exact") -> np.ndarray:
        """Per-pixel Fisher information about the expected photons.

        Parameters
        ----------
        expected : array_like
            Expected photoelectrons per pixel ``lam``, finite and >= 0.
        method : {"exact", "excess-noise"}, optional
            ``"exact"``: ``E[(d log p / d lam)^2]`` of the true law, by quadrature, tabulated
            once per ``readout_sd / gain`` (a few seconds; within 5e-6 relative).
            ``"excess-noise"``: the shortcut ``1 / (2 lam + (readout_sd / gain)^2)``.

        Returns
        -------
        ndarray
            Information per photoelectron^2, the shape of ``expected``.

        Raises
        ------
        BayespsfInputError
            If ``expected`` is not finite or negative, or ``method`` is unknown.

        Notes
        -----
        Without readout the exact information falls from ``1 / lam`` (low signal: each photon
        is seen) to ``1 / (2 lam)`` (high signal); readout lowers it most at low signal. The
        shortcut is the Poisson information divided by the excess-noise factor F^2 = 2 (the
        weights of the paper's Eq. pesum).
        """
        lam = nonnegative_array("expected", expected)
        if method not in FISHER_METHODS:
            raise BayespsfInputError(f"method must be one of {FISHER_METHODS}, got {method!r}")
        if method == "exact":
            return _emccd_fisher.fisher_information(lam, self.readout_in_gain_units)
        with np.errstate(divide="ignore"):
            return 1.0 / (2.0 * lam + self.readout_in_gain_units**2)

    def fisher_information_unchecked(self, expected):
        return _emccd_fisher.fisher_information(expected, self.readout_in_gain_units)

    def step_information_unchecked(self, expected):
        # the poisson tier's own: steered by the camera's, half of it, steps overshoot twofold
        poisson = self.likelihood == "poisson"
        return 1.0 / expected if poisson else self.fisher_information_unchecked(expected)

    def to_dict(self):
        names = ("gain", "readout_sd", "offset", "e_per_adu", "likelihood")
        return {"kind": "emccd", **{name: getattr(self, name) for name in names}}

    def __repr__(self):
        return (
            f"EMCCD(gain={self.gain:g}, readout_sd={self.readout_sd:g}, offset={self.offset:g}, "
            f"e_per_adu={self.e_per_adu:g}, likelihood={self.likelihood!r})"
        )
