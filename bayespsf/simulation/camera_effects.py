"""The simulator's camera effects: the camera law's steps, from photoelectrons to ADU.

Clock-induced charge, the EM register (Gamma-distributed or stage by stage), readout noise, the
conversion to ADU and the ADC (rounding, full scale), or an ideal photon-counting camera:
the effects ``bayespsf.simulation.pipeline.camera_effects`` builds from a scene's camera table.
Like every effect (``bayespsf.simulation.effects``: ``Batch``, ``Effect``, the stages) each
does one thing, and they read only the image's shape, so whole movie frames pass through them.

The EM register and readout draws (``gamma_register``, ``add_normal``) belong to the camera
laws (``bayespsf.cameras.draws``), whose own ``sample`` methods use them; the effects import
them from there, so the simulator and the likelihood describe one camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayespsf.cameras.draws import add_normal, gamma_register
from bayespsf.simulation.effects import Effect

# ------------------------------------------------------------------------------ camera effects


@dataclass(repr=False)
class ClockInducedCharge(Effect):
    """Spurious electrons created before the EM register: Poisson(rate) per pixel, amplified
    like photoelectrons."""

    rate: float
    reads = leaves = "photoelectrons"
    draws = True

    def apply(self, batch, rng):
        batch.image = batch.image + rng.poisson(self.rate, size=batch.image.shape)


@dataclass(repr=False)
class PhotonCounting(Effect):
    """An ideal photon-counting camera: counts are the photoelectrons (1 ADU each)."""

    reads, leaves = "photoelectrons", "adu"

    def apply(self, batch, rng):
        batch.image = batch.image.astype(np.float64)


@dataclass(repr=False)
class GammaRegister(Effect):
    """EM register: n photoelectrons become Gamma(n, gain) electrons (0 stays 0)."""

    gain: float
    reads, leaves, draws = "photoelectrons", "electrons", True

    def apply(self, batch, rng):
        batch.image = gamma_register(batch.image, self.gain, rng)


@dataclass(repr=False)
class StagedRegister(Effect):
    """EM register stage by stage: at each of ``stages`` stages every electron makes a second one
    with probability gain^(1/stages) - 1 (a Galton-Watson process; mean gain exactly ``gain``,
    excess noise factor 1 + (1 - p)(gain - 1) / (gain (1 + p)) -> 2)."""

    gain: float
    stages: int
    reads, leaves, draws = "photoelectrons", "electrons", True

    def apply(self, batch, rng):
        p = self.gain ** (1.0 / self.stages) - 1.0
        n = batch.image.astype(np.int64)
        for _ in range(self.stages):
            n = n + rng.binomial(n, p)
        batch.image = n.astype(np.float64)


@dataclass(repr=False)
class ReadoutNoise(Effect):
    """Gaussian readout noise of the given SD, in the units of the current stage."""

    sd: float
    stage: str = "electrons"
    draws = True

    def __post_init__(self):
        self.reads = self.leaves = self.stage

    def apply(self, batch, rng):
        batch.image = add_normal(batch.image, self.sd, rng)


@dataclass(repr=False)
class ElectronsToADU(Effect):
    """ADU = offset + electrons / e_per_adu (no randomness)."""

    offset: float
    e_per_adu: float
    reads, leaves = "electrons", "adu"

    def apply(self, batch, rng):
        batch.image = self.offset + batch.image / self.e_per_adu


@dataclass(repr=False)
class PhotoelectronsToADU(Effect):
    """sCMOS conversion: ADU = offset + gain * photoelectrons (no randomness)."""

    gain: float
    offset: float
    reads, leaves = "photoelectrons", "adu"

    def apply(self, batch, rng):
        batch.image = self.offset + self.gain * batch.image


@dataclass(repr=False)
class Quantize(Effect):
    """The ADC: counts rounded to the nearest whole ADU."""

    reads = leaves = "adu"

    def apply(self, batch, rng):
        batch.image = np.rint(batch.image)


@dataclass(repr=False)
class Saturate(Effect):
    """The ADC's full scale: counts above ``full_scale`` are recorded as ``full_scale``."""

    full_scale: float
    reads = leaves = "adu"

    def apply(self, batch, rng):
        batch.image = np.minimum(batch.image, self.full_scale)
