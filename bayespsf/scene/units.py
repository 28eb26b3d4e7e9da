"""The unit of N and b: photons incident on the camera or photoelectrons it detected.

A camera detects each incident photon with probability ``quantum_efficiency`` (binomial thinning,
so a Poisson spot of N incident photons gives Poisson(QE N) photoelectrons). The camera law
sees photoelectrons; N and b are reported in ``photon_unit``: ``"incident"`` photons (N =
photoelectrons / QE, picasso's convention when its ``qe`` is set) or ``"detected"``
photoelectrons (what the paper's Eq. photonConv gives, and what the Cramér-Rao bound and the
SNR depend on). With QE 1, the default, the two are the same.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from bayespsf.errors import BayespsfInputError

UNITS = ("incident", "detected")


def check(quantum_efficiency, photon_unit) -> tuple[float, str]:
    """``quantum_efficiency`` in (0, 1] and ``photon_unit`` one of ``UNITS``, else an error
    naming the field."""
    q = quantum_efficiency
    number = not isinstance(q, bool | np.bool_) and isinstance(q, numbers.Real)
    if not (number and math.isfinite(q) and 0 < q <= 1):
        raise BayespsfInputError(f"quantum_efficiency must be a number in (0, 1], got {q!r}")
    if photon_unit not in UNITS:
        raise BayespsfInputError(
            f"photon_unit must be one of {', '.join(map(repr, UNITS))}, got {photon_unit!r}"
        )
    return float(q), photon_unit


def photoelectrons_per_photon(quantum_efficiency: float, photon_unit: str) -> float:
    """Expected photoelectrons per unit of N and b: the QE for incident photons, 1 for detected
    photoelectrons."""
    return float(quantum_efficiency) if photon_unit == "incident" else 1.0


def label(quantum_efficiency: float, photon_unit: str) -> str:
    """The unit of N and b in words, as every table states it (its ``photon_unit`` column)."""
    if photoelectrons_per_photon(quantum_efficiency, photon_unit) == 1.0:
        return "photoelectrons"
    return f"incident photons (quantum efficiency {quantum_efficiency:g})"
