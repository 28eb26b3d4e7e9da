"""Random draws shared by the camera laws' ``sample`` methods and the simulator's effects.

They live with the cameras (the layer below the simulator) so that a camera law owns its own
draws and ``bayespsf.simulation.effects`` reuses them: one EM register and one readout for both.
"""

from __future__ import annotations

import numpy as np


def gamma_register(photoelectrons: np.ndarray, gain: float, rng: np.random.Generator):
    """EM register as the Gamma(n, gain) law (n = 0 stays exactly 0).

    Basden, Haniff & Mackay, MNRAS 345 (2003): ``n`` photoelectrons leave the register as
    Gamma(n, gain) electrons.
    """
    return rng.gamma(photoelectrons, gain)


def add_normal(values: np.ndarray, sd: float, rng: np.random.Generator) -> np.ndarray:
    """``values + Normal(0, sd)`` element-wise (readout noise)."""
    return values + rng.normal(0.0, sd, size=np.shape(values))
