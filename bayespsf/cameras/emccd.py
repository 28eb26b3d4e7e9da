"""Electron-multiplying CCD: Poisson photoelectrons, Gamma-distributed EM gain, Gaussian readout.

Per pixel (Basden, Haniff & Mackay, MNRAS 345 (2003); Hirsch et al., PLoS ONE 8 (2013)):

* photoelectrons ``n ~ Poisson(lam)``, ``lam`` the expected photons (the QE and any
  clock-induced charge belong to the scene, which hands the camera the final ``lam``);
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
"""

from __future__ import annotations

import numpy as np

from bayespsf._checks import nonnegative_array, scalar_in_range
from bayespsf.cameras import _emccd_fisher, _emccd_law, _emccd_table
from bayespsf.cameras.base import Camera
from bayespsf.cameras.photon import poisson_log_pmf
from bayespsf.effects import add_normal, gamma_register
from bayespsf.errors import BayespsfInputError

TIERS = ("exact", "table", "high-gain", "gaussian", "poisson")
MAX_EXPECTED = 1e10  # photons per pixel: the readout quadrature is validated up to here
FISHER_METHODS = ("exact", "excess-noise")


class EMCCD(Camera):
    """An EMCCD camera.

    Parameters
    ----------
    gain : float
        Mean EM gain G (electrons out per photoelectron), >= 1.
    readout_sd : float
        Readout noise SD in electrons, >= 0.
    offset : float
        Bias added to every pixel, in ADU.
    e_per_adu : float
        Electrons per ADU (the A/D conversion factor), > 0.
    likelihood : str
        One of ``TIERS``; see the module docstring.
    """

    fisher_methods = FISHER_METHODS

    def __init__(
        self,
        gain: float,
        readout_sd: float = 0.0,
        offset: float = 0.0,
        e_per_adu: float = 1.0,
        likelihood: str = "exact",
    ):
        self.gain = scalar_in_range("gain", gain, 1.0)
        self.readout_sd = scalar_in_range("readout_sd", readout_sd, 0.0)
        self.offset = scalar_in_range("offset", offset, -np.inf)
        self.e_per_adu = scalar_in_range("e_per_adu", e_per_adu, 0.0, low_inclusive=False)
        if likelihood not in TIERS:
            raise BayespsfInputError(f"likelihood must be one of {TIERS}, got {likelihood!r}")
        self.likelihood = likelihood

    @property
    def readout_in_gain_units(self) -> float:
        """``r = readout_sd / gain``: the one number (with lam) the law in gain units needs."""
        return self.readout_sd / self.gain

    def gain_units(self, counts):
        """Counts in ADU as electrons over gain, ``t = (counts - offset) e_per_adu / gain``."""
        return (np.asarray(counts, dtype=np.float64) - self.offset) * (self.e_per_adu / self.gain)

    def _log_likelihood(self, counts, expected):
        t = self.gain_units(counts)
        log_jacobian = np.log(self.e_per_adu / self.gain)
        r = self.readout_in_gain_units
        tier = self.likelihood
        if tier in ("exact", "table") and r > 0 and expected.max(initial=0.0) > MAX_EXPECTED:
            raise BayespsfInputError(
                f"expected must be <= {MAX_EXPECTED:g} photons per pixel for the EMCCD law with "
                f"readout (got {expected.max():.3g}); no camera pixel holds that many"
            )
        if tier == "exact" and r > 0:
            return _emccd_law.log_exact(t, expected, r) + log_jacobian
        if tier == "table" and r > 0:
            return _emccd_table.log_table(t, expected, r) + log_jacobian
        if tier in ("exact", "table", "high-gain"):
            return self._log_high_gain(t, expected, r, log_jacobian)
        if tier == "gaussian":
            return _gaussian_log_pdf(t, expected, r) + log_jacobian
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

    def _score(self, counts, expected):
        """Closed form for the exact tier (quadrature with readout, Bessel ratio without);
        other tiers by differences of their own log-likelihood."""
        r = self.readout_in_gain_units
        if self.likelihood != "exact" or np.any(expected == 0):
            return super()._score(counts, expected)
        t = self.gain_units(counts)
        if r > 0:
            return _emccd_law.log_and_score_exact(t, expected, r)[1]
        return _emccd_law.score_high_gain(t, expected)

    def _variance(self, expected):
        """``(2 lam G^2 + readout_sd^2) / e_per_adu^2`` (ADU^2)."""
        return (2.0 * expected * self.gain**2 + self.readout_sd**2) / self.e_per_adu**2

    def photons_per_adu(self):
        return self.e_per_adu / self.gain, self.offset

    def fisher_information(self, expected, method: str = "exact") -> np.ndarray:
        """Per-pixel Fisher information about the expected photons.

        ``method="exact"``: ``E[(d log p / d lam)^2]`` of the true law, by quadrature,
        tabulated once per ``readout_sd / gain`` (a few seconds; ~1e-6 relative). Without
        readout it falls from ``1 / lam`` (low signal: each photon is seen) to ``1 / (2 lam)``
        (high signal); readout lowers it most at low signal.
        ``method="excess-noise"``: the shortcut ``1 / (2 lam + (readout_sd / gain)^2)``, i.e.
        Poisson information divided by the excess-noise factor F^2 = 2 (the weights of the
        paper's Eq. pesum).
        """
        lam = nonnegative_array("expected", expected)
        if method not in FISHER_METHODS:
            raise BayespsfInputError(f"method must be one of {FISHER_METHODS}, got {method!r}")
        if method == "exact":
            return _emccd_fisher.fisher_information(lam, self.readout_in_gain_units)
        with np.errstate(divide="ignore"):
            return 1.0 / (2.0 * lam + self.readout_in_gain_units**2)

    def _fisher_information(self, expected):
        return _emccd_fisher.fisher_information(expected, self.readout_in_gain_units)

    def to_dict(self):
        return {
            "kind": "emccd",
            "gain": self.gain,
            "readout_sd": self.readout_sd,
            "offset": self.offset,
            "e_per_adu": self.e_per_adu,
            "likelihood": self.likelihood,
        }

    def __repr__(self):
        return (
            f"EMCCD(gain={self.gain:g}, readout_sd={self.readout_sd:g}, offset={self.offset:g}, "
            f"e_per_adu={self.e_per_adu:g}, likelihood={self.likelihood!r})"
        )


def _gaussian_log_pdf(t, lam, r):
    """Normal(lam, 2 lam + r^2) in gain units; the degenerate ``lam = r = 0`` is the atom at 0."""
    var = 2.0 * lam + r * r
    degenerate = var == 0
    v = np.where(degenerate, 1.0, var)
    log_pdf = -0.5 * (t - lam) ** 2 / v - 0.5 * np.log(2.0 * np.pi * v)
    return np.where(degenerate, np.where(t == 0, 0.0, -np.inf), log_pdf)
