"""The simulator's effects: one small class each, applied in order to a batch of images.

A batch carries the per-image truth (``x0 y0 s_x s_y N b`` and any drawn extras) and the pixel
values at their current *stage*: ``expected`` photons, integer ``photoelectrons``, amplified
``electrons`` or ``adu``. Each effect states the stage it reads and the stage it leaves, whether
it draws random numbers, and does one thing. ``bayespsf.simulate`` builds the list of
effects from exactly what a scene declares. The camera law's effects, from photoelectrons
to ADU, are in ``bayespsf.simulation.camera_effects``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from bayespsf import psf
from bayespsf.psf.defocus import Defocus

STAGES = ("truth", "expected", "photoelectrons", "electrons", "adu")


@dataclass
class Batch:
    """Images being simulated: per-image truth columns and the pixel values at ``stage``.

    ``roi`` is the side of square ROIs, read by the effects that draw the signal; the effects
    after it (background, camera) read only ``image.shape``, so whole movie frames
    ``(k, height, width)`` pass through them too (``bayespsf.simulation.movie``).
    """

    n: int
    roi: int
    truth: dict[str, np.ndarray] = field(default_factory=dict)
    image: np.ndarray | None = None
    stage: str = "truth"


class Effect(ABC):
    """One step of the simulation: ``reads`` and ``leaves`` a stage; ``draws`` if it is random."""

    reads: str = "truth"
    leaves: str = "truth"
    draws: bool = False

    def __call__(self, batch: Batch, rng: np.random.Generator) -> None:
        if batch.stage != self.reads:
            raise RuntimeError(f"{self!r} reads {self.reads!r} images, got {batch.stage!r}")
        self.apply(batch, rng)
        batch.stage = self.leaves

    @abstractmethod
    def apply(self, batch: Batch, rng: np.random.Generator) -> None: ...

    def __repr__(self) -> str:
        fields = ", ".join(
            f"{k}={v!r}"
            for k, v in vars(self).items()
            if not k.startswith("_") and k not in ("reads", "leaves")
        )
        return f"{type(self).__name__}({fields})"


# ------------------------------------------------------------------------------- truth effects


@dataclass(repr=False)
class EmitterTruth(Effect):
    """Fills the truth of every image from the scene (no randomness)."""

    x0: float
    y0: float
    s_x: float
    s_y: float
    photons: float
    background: float

    def apply(self, batch, rng):
        for name, value in (
            ("x0", self.x0),
            ("y0", self.y0),
            ("s_x", self.s_x),
            ("s_y", self.s_y),
            ("N", self.photons),
            ("b", self.background),
        ):
            batch.truth[name] = np.full(batch.n, float(value))


@dataclass(repr=False)
class UniformPosition(Effect):
    """x0, y0 uniform in [-half_width, half_width] (the central pixel, or a box)."""

    half_width: float
    draws = True

    def apply(self, batch, rng):
        xy = rng.uniform(-self.half_width, self.half_width, size=(2, batch.n))
        batch.truth["x0"], batch.truth["y0"] = xy[0], xy[1]


@dataclass(repr=False)
class AxialPosition(Effect):
    """The emitter's axial position ``z`` (nm) of each image: ``fixed`` at ``z0``, ``uniform``
    in [``low``, ``high``] or ``normal`` (mean ``z0``, SD ``sd``): a scene's ``[axial]`` table."""

    law: str
    z0: float = 0.0
    low: float = 0.0
    high: float = 0.0
    sd: float = 0.0

    @property
    def draws(self) -> bool:
        return self.law != "fixed"

    def apply(self, batch, rng):
        if self.law == "fixed":
            batch.truth["z"] = np.full(batch.n, float(self.z0))
        elif self.law == "uniform":
            batch.truth["z"] = rng.uniform(self.low, self.high, size=batch.n)
        else:
            batch.truth["z"] = self.z0 + self.sd * rng.standard_normal(batch.n)


@dataclass(repr=False)
class DefocusWidths(Effect):
    """``s_x``, ``s_y`` of each image from its ``z`` through the defocus curves
    (``bayespsf.psf.defocus``; the emitter's s0x, s0y are their in-focus widths)."""

    defocus: Defocus

    def apply(self, batch, rng):
        batch.truth["s_x"], batch.truth["s_y"] = self.defocus.widths(batch.truth["z"])


@dataclass(repr=False)
class PhotonNumberJitter(Effect):
    """N of each image uniform in N (1 +- relative) (frames kept within +-20%: the paper)."""

    relative: float
    draws = True

    def apply(self, batch, rng):
        batch.truth["N"] = batch.truth["N"] * rng.uniform(
            1.0 - self.relative, 1.0 + self.relative, size=batch.n
        )


@dataclass(repr=False)
class WholePhotonNumber(Effect):
    """Fixed photon statistics: N rounded to a whole number of photons (truth updated)."""

    def apply(self, batch, rng):
        batch.truth["N"] = np.rint(batch.truth["N"])


# ------------------------------------------------------------------------------ photon effects


def _pixel_probabilities(batch: Batch, pixel_size: float) -> np.ndarray:
    t = batch.truth
    params = np.column_stack(
        [t["x0"], t["y0"], t["s_x"], t["s_y"], np.ones(batch.n), np.zeros(batch.n)]
    )
    return psf.expected_counts(params, batch.roi, pixel_size)


@dataclass(repr=False)
class ExpectedSignal(Effect):
    """Expected photons per pixel of the pixel-integrated Gaussian spot (no randomness)."""

    pixel_size: float
    leaves = "expected"

    def apply(self, batch, rng):
        batch.image = batch.truth["N"][:, None, None] * _pixel_probabilities(batch, self.pixel_size)


@dataclass(repr=False)
class PoissonBackgroundMean(Effect):
    """Poisson background folded into the expected image: lam += mean (no draws of its own;
    Poisson(signal) + Poisson(mean) is Poisson(signal + mean))."""

    mean: float
    reads = leaves = "expected"

    def apply(self, batch, rng):
        batch.image = batch.image + self.mean


@dataclass(repr=False)
class PoissonPhotons(Effect):
    """Photoelectrons of each pixel ~ Poisson(expected)."""

    reads, leaves, draws = "expected", "photoelectrons", True

    def apply(self, batch, rng):
        batch.image = rng.poisson(batch.image)


@dataclass(repr=False)
class MultinomialPhotons(Effect):
    """Exactly N photons per image, spread over the pixels (and the world outside the ROI) by
    the pixel-integrated Gaussian: pixel counts are multinomial."""

    pixel_size: float
    leaves, draws = "photoelectrons", True

    def apply(self, batch, rng):
        p = _pixel_probabilities(batch, self.pixel_size).reshape(batch.n, -1)
        outside = np.clip(1.0 - p.sum(axis=1, keepdims=True), 0.0, 1.0)  # round-off only
        counts = rng.multinomial(batch.truth["N"].astype(np.int64), np.hstack([p, outside]))
        batch.image = counts[:, :-1].reshape(batch.n, batch.roi, batch.roi)


@dataclass(repr=False)
class PhotonBinning(Effect):
    """Photon by photon, as in the paper: each photon is drawn from a Gaussian whose widths are
    (s0x + d, s0y + d), d ~ Normal(0, width_jitter) per photon (emission bandwidth), and binned.

    With ``fixed`` each image emits exactly N photons, otherwise Poisson(N).
    """

    pixel_size: float
    width_jitter: float
    fixed: bool
    leaves, draws = "photoelectrons", True

    def apply(self, batch, rng):
        t = batch.truth
        emitted = t["N"].astype(np.int64) if self.fixed else rng.poisson(t["N"])
        t["photons_emitted"] = emitted.astype(float)
        owner = np.repeat(np.arange(batch.n), emitted)
        z = rng.standard_normal((3, owner.size))
        d = self.width_jitter * z[2]
        x = t["x0"][owner] + (t["s_x"][owner] + d) * z[0]
        y = t["y0"][owner] + (t["s_y"][owner] + d) * z[1]
        half = 0.5 * batch.roi
        col = np.floor(x / self.pixel_size + half)
        row = np.floor(y / self.pixel_size + half)
        keep = (col >= 0) & (col < batch.roi) & (row >= 0) & (row < batch.roi)
        flat = (owner[keep] * batch.roi + row[keep].astype(np.int64)) * batch.roi + col[
            keep
        ].astype(np.int64)
        counts = np.bincount(flat, minlength=batch.n * batch.roi * batch.roi)
        batch.image = counts.reshape(batch.n, batch.roi, batch.roi)


AIRY_GAUSSIAN_SD = 0.21  # best-fitting Gaussian SD of the in-focus Airy disk, in lambda / NA


def airy_gaussian_sd(wavelength: float, na: float) -> float:
    """SD of the Gaussian that best approximates the in-focus Airy pattern, 0.21 lambda / NA
    (paraxial; Zhang, Zerubia & Olivo-Marin, Appl. Opt. 46, 1819 (2007))."""
    return AIRY_GAUSSIAN_SD * wavelength / na


@dataclass(repr=False)
class AiryPhotons(Effect):
    """Photon by photon from the in-focus Born-Wolf Airy pattern ``(2 J1(v) / v)^2`` with
    ``v = 2 pi NA r / wavelength``. Radii are drawn by inverting the encircled energy
    ``1 - J0(v)^2 - J1(v)^2`` (tabulated to v = 2000; beyond, its asymptote 1 - 2 / (pi v)).
    Width jitter scales each photon's radius by (s + d) / s, s the Gaussian-equivalent SD."""

    pixel_size: float
    wavelength: float
    na: float
    width_jitter: float
    fixed: bool
    leaves, draws = "photoelectrons", True

    def __post_init__(self):
        v = np.concatenate([np.linspace(0.0, 50.0, 50_001), np.geomspace(50.0, 2000.0, 50_000)[1:]])
        self._v = v
        self._energy = 1.0 - special.j0(v) ** 2 - special.j1(v) ** 2

    def apply(self, batch, rng):
        t = batch.truth
        emitted = t["N"].astype(np.int64) if self.fixed else rng.poisson(t["N"])
        t["photons_emitted"] = emitted.astype(float)
        owner = np.repeat(np.arange(batch.n), emitted)
        u, angle, z = (
            rng.random(owner.size),
            rng.uniform(0, 2 * np.pi, owner.size),
            rng.standard_normal(owner.size),
        )
        top = self._energy[-1]
        v = np.where(
            u <= top,
            np.interp(np.minimum(u, top), self._energy, self._v),
            2.0 / (np.pi * (1.0 - u)),
        )
        s = airy_gaussian_sd(self.wavelength, self.na)
        radius = v * self.wavelength / (2.0 * np.pi * self.na) * (1.0 + self.width_jitter * z / s)
        x = t["x0"][owner] + radius * np.cos(angle)
        y = t["y0"][owner] + radius * np.sin(angle)
        batch.image = _bin_photons(x, y, owner, batch, self.pixel_size)


def _bin_photons(x, y, owner, batch: Batch, pixel_size: float) -> np.ndarray:
    """Counts per pixel of photons at (x, y) belonging to image ``owner`` (others are lost)."""
    half = 0.5 * batch.roi
    col = np.floor(x / pixel_size + half)
    row = np.floor(y / pixel_size + half)
    keep = (col >= 0) & (col < batch.roi) & (row >= 0) & (row < batch.roi)
    flat = (owner[keep] * batch.roi + row[keep].astype(np.int64)) * batch.roi
    flat += col[keep].astype(np.int64)
    counts = np.bincount(flat, minlength=batch.n * batch.roi * batch.roi)
    return counts.reshape(batch.n, batch.roi, batch.roi)


# -------------------------------------------------------------------------- background effects


class BackgroundPhotons(Effect):
    """Base of the background effects that draw whole photons per pixel and add them."""

    reads = leaves = "photoelectrons"
    draws = True

    @property
    @abstractmethod
    def moments(self) -> tuple[float, float]:
        """Exact mean and variance of one pixel's background photons."""

    @abstractmethod
    def draw(self, shape, rng) -> np.ndarray: ...

    def apply(self, batch, rng):
        batch.image = batch.image + self.draw(batch.image.shape, rng)


@dataclass(repr=False)
class PoissonBackground(BackgroundPhotons):
    """Poisson(mean) background photons per pixel."""

    mean: float

    @property
    def moments(self):
        return self.mean, self.mean

    def draw(self, shape, rng):
        return rng.poisson(self.mean, size=shape)


@dataclass(repr=False)
class DiscreteGaussianBackground(BackgroundPhotons):
    """Background photons k = 0, 1, 2, ... with P(k) proportional to exp(-(k - mean)^2 / 2 sd^2):
    a Gaussian on the whole photon counts, truncated at zero (the paper's Fig. 1C shapes: a full
    Gaussian at high mean, a truncated one at low mean). Drawn by inverse CDF on its support."""

    mean: float
    sd: float

    def __post_init__(self):
        top = int(np.ceil(self.mean + 40.0 * self.sd)) + 1
        k = np.arange(top + 1)
        log_w = -0.5 * ((k - self.mean) / self.sd) ** 2
        w = np.exp(log_w - log_w.max())
        self._k = k
        self._p = w / w.sum()
        self._cdf = np.cumsum(self._p)

    @property
    def moments(self):
        mean = float(np.sum(self._k * self._p))
        return mean, float(np.sum((self._k - mean) ** 2 * self._p))

    def draw(self, shape, rng):
        u = rng.random(shape)
        return np.minimum(np.searchsorted(self._cdf, u, side="right"), self._k[-1])


@dataclass(repr=False)
class BinomialBackground(BackgroundPhotons):
    """Binomial(trials, probability) background photons per pixel (under-dispersed)."""

    trials: int
    probability: float

    @property
    def moments(self):
        m = self.trials * self.probability
        return m, m * (1.0 - self.probability)

    def draw(self, shape, rng):
        return rng.binomial(self.trials, self.probability, size=shape)


# --------------------------------------------------------------------------- detection effects


@dataclass(repr=False)
class QuantumEfficiency(Effect):
    """Each photon of every pixel (signal and background alike) becomes a photoelectron with
    probability ``efficiency``: binomial thinning of the whole photon counts."""

    efficiency: float
    reads = leaves = "photoelectrons"
    draws = True

    def apply(self, batch, rng):
        batch.image = rng.binomial(np.asarray(batch.image, dtype=np.int64), self.efficiency)


@dataclass(repr=False)
class DetectedTruth(Effect):
    """The truth's N and b in detected photoelectrons: times the quantum efficiency (the
    scene's photon_unit 'detected'; the counts are unchanged)."""

    efficiency: float
    reads = leaves = "adu"

    def apply(self, batch, rng):
        for name in ("N", "b"):
            batch.truth[name] = batch.truth[name] * self.efficiency
