"""Spatial photon transfer: the camera from the background pixels of one frame or a few, when
the frames are too few for the temporal cumulants (``photon_transfer``) or the molecules
(``gain``).

The frames' background (pixels away from every spot) is tiled into ``block`` x ``block``
blocks. In each block a least-squares plane is removed (an illumination slope would otherwise
add to the variance), and the residuals' power sums give the block's variance and its third and
fourth cumulants without bias: for residuals ``r = A e`` of the plane fit (``A = I - H``,
symmetric and idempotent) and independent pixels of cumulants ``K2, K3, K4``,

    E sum r^2 = K2 tr A,   E sum r^3 = K3 sum A_ik^3,
    E sum r^4 = K4 sum A_ik^4 + 3 K2^2 sum A_ii^2,
    E (sum r^2)^2 = K2^2 ((tr A)^2 + 2 tr A) + K4 sum A_ii^2,

and the block's mean is its pixels' mean. Averaged over blocks, these are the averages of the
blocks' own cumulants, and each cumulant of ``offset + M Y + readout`` (``photon_transfer``'s
module docstring) is linear in the background's photons ``lam``, so the block averages obey
the same relations as one pixel's:

    K1 - offset = lam M,   K2 - sigma^2 = c2 lam M^2,   K3 = c3 lam M^3,   K4 = c4 lam M^4,

the photon-transfer line ``K2 = c2 M (K1 - offset) + sigma^2`` among them. What is solved for
depends on what else is known:

* dark frames give ``offset`` and ``sigma^2``: ``M = (K2 - sigma^2) / (c2 (K1 - offset))``;
* a declared readout gives ``sigma^2``: ``M = (c2 / c3) K3 / (K2 - sigma^2)``, then
  ``lam = K3 / (c3 M^3)`` and ``offset = K1 - lam M``;
* neither: ``M = (c3 / c4) K4 / K3``, the offset as above and ``sigma^2 = K2 - c2 lam M^2``.

The standard errors are the larger of two: a bootstrap over block positions (all frames of a
position go together, so that a pattern fixed to the pixels is resampled whole), and the
spread of the same estimator on blocks drawn from the fitted camera (a parametric bootstrap).
The first holds where the model does not; the second does not shrink with a sample that lacks
the few large counts of an EMCCD's heavy tail (such a sample reads ``M`` low and, by the first
alone, with a small SE). On 400 single simulated EMCCD frames (``validation/short_calibration.py``)
the SE averages 2.15% of ``M`` against a spread of the estimate of 2.22%, and 0.917 of the
frames lie within 1.96 SE, where an error bar equal to the spread itself covers 0.93: the
difference, 6 of 400 frames (about one binomial SE), is the SE's own scatter (7% from frame to
frame, and smaller where a frame reads ``M`` low), not a short error bar. Dark frames' offset
and readout are drawn from their normal errors in each replicate.

It assumes what ``photon_transfer`` assumes: Poisson background photons, independent pixels,
and a background smooth within a block. A pattern fixed to the pixels (an sCMOS camera's
per-pixel offsets) counts as readout noise here; dark frames measure it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayespsf.calibration.photon_transfer import CUMULANT_FACTORS
from bayespsf.errors import BayespsfInputError

BLOCK = 8  # pixels on a block's side
MIN_BLOCKS = 20  # block positions: fewer cannot give a bootstrap error
REPLICATES = 400  # bootstrap replicates over the blocks
PARAMETRIC = 100  # replicates drawn from the fitted camera
PARAMETRIC_BLOCKS = 500  # blocks drawn in each


@dataclass(frozen=True)
class BlockSums:
    """Per block position (rows) and frame (columns): the block's mean and its plane-fit
    residuals' ``sum r^2``, ``sum r^3``, ``sum r^4`` and ``(sum r^2)^2``; ``factors`` the
    plane fit's ``tr A``, ``sum A_ik^3``, ``sum A_ik^4``, ``sum A_ii^2``."""

    mean: np.ndarray
    s2: np.ndarray
    s3: np.ndarray
    s4: np.ndarray
    s2sq: np.ndarray
    factors: tuple[float, float, float, float]
    block: int

    @property
    def positions(self) -> int:
        return self.mean.shape[0]

    @property
    def frames(self) -> int:
        return self.mean.shape[1]


def plane_factors(block: int) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The residual-maker ``A = I - H`` of a plane fit to a ``block`` x ``block`` block, and
    ``tr A``, ``sum A_ik^3``, ``sum A_ik^4``, ``sum A_ii^2``."""
    rows, cols = np.mgrid[0:block, 0:block]
    design = np.column_stack([np.ones(block * block), rows.ravel(), cols.ravel()]).astype(float)
    hat = design @ np.linalg.solve(design.T @ design, design.T)
    a = np.eye(block * block) - hat
    diagonal = np.diag(a)
    return a, (
        float(diagonal.sum()),
        float((a**3).sum()),
        float((a**4).sum()),
        float(diagonal @ diagonal),
    )


def block_sums(frames: np.ndarray, keep: np.ndarray, block: int = BLOCK) -> BlockSums:
    """The sums of every ``block`` x ``block`` tile of ``frames`` (frames, h, w) whose pixels
    are all True in ``keep`` (h, w): the background away from the spots."""
    if not (isinstance(block, int | np.integer) and block >= 3):
        raise BayespsfInputError(f"block must be a whole number of pixels >= 3, got {block!r}")
    frames = np.asarray(frames, dtype=np.float64)
    n, h, w = frames.shape
    tiles_r, tiles_c = h // block, w // block
    cut = frames[:, : tiles_r * block, : tiles_c * block]
    tiles = cut.reshape(n, tiles_r, block, tiles_c, block).transpose(1, 3, 0, 2, 4)
    inside = keep[: tiles_r * block, : tiles_c * block].reshape(tiles_r, block, tiles_c, block)
    whole = inside.all(axis=(1, 3))
    return sums_of(tiles[whole].reshape(-1, n, block * block), block)


def sums_of(values: np.ndarray, block: int) -> BlockSums:
    """The ``BlockSums`` of blocks ``values`` (positions, frames, ``block**2`` pixels)."""
    a, factors = plane_factors(block)
    residual = values @ a  # A is symmetric
    s2 = (residual**2).sum(axis=2)
    return BlockSums(
        mean=values.mean(axis=2),
        s2=s2,
        s3=(residual**3).sum(axis=2),
        s4=(residual**4).sum(axis=2),
        s2sq=s2**2,
        factors=factors,
        block=block,
    )


def pooled_cumulants(sums: BlockSums, weights: np.ndarray | None = None) -> np.ndarray:
    """``K1 .. K4``: the blocks' average cumulants (``weights`` per position: a bootstrap's
    counts; default all once)."""
    w = np.ones(sums.positions) if weights is None else weights
    total = w.sum() * sums.frames

    def average(x):
        return float(w @ x.sum(axis=1) / total)

    trace, cubes, fourths, diagonal = sums.factors
    k2 = average(sums.s2) / trace
    k3 = average(sums.s3) / cubes
    # E s4 = K4 fourths + 3 Q diagonal; E s2sq = Q (trace^2 + 2 trace) + K4 diagonal
    system = np.array([[fourths, 3 * diagonal], [diagonal, trace**2 + 2 * trace]])
    k4, _ = np.linalg.solve(system, [average(sums.s4), average(sums.s2sq)])
    return np.array([average(sums.mean), k2, k3, k4])


@dataclass(frozen=True)
class Known:
    """What is known beside the frames: the offset and readout variance (ADU, ADU^2) with
    their SEs from dark frames, or a declared readout in electrons (``readout_e``, turned into
    ADU by ``readout_per_photon``: True for an sCMOS, whose readout in electrons is per
    photoelectron, so ADU = e- x M; False for an EMCCD, ADU = e- / ``e_per_adu``)."""

    offset: float | None = None
    offset_se: float = 0.0
    readout_sd: float | None = None
    readout_sd_se: float = 0.0
    readout_e: float | None = None
    readout_per_photon: bool = False
    e_per_adu: float = 1.0

    @property
    def source(self) -> str:
        if self.offset is not None:
            return "dark"
        return "declared" if self.readout_e is not None else "cumulants"


def solve(k: np.ndarray, excess: float, known: Known) -> tuple[float, float, float, float]:
    """``(M, offset, readout variance, lam)`` from the pooled cumulants (module docstring)."""
    c2, c3, c4 = CUMULANT_FACTORS[excess]
    k1, k2, k3, k4 = k
    if known.offset is not None:
        variance = known.readout_sd**2
        m = (k2 - variance) / (c2 * (k1 - known.offset))
        return m, known.offset, variance, (k1 - known.offset) / m
    if known.readout_e is None:
        m = c3 * k4 / (c4 * k3)
        lam = k3 / (c3 * m**3)
        return m, k1 - lam * m, k2 - c2 * lam * m * m, lam
    if known.readout_per_photon:
        m = _per_photon_root(k, c2, c3, c4, known.readout_e)
        variance = (known.readout_e * m) ** 2
    else:
        variance = (known.readout_e / known.e_per_adu) ** 2
        m = c2 * k3 / (c3 * (k2 - variance))
    lam = k3 / (c3 * m**3)
    return m, k1 - lam * m, variance, lam


def _per_photon_root(k: np.ndarray, c2: float, c3: float, c4: float, readout_e: float) -> float:
    """``M`` from ``c3 M (K2 - e^2 M^2) = c2 K3`` (a readout of ``e`` electrons per
    photoelectron is ``e M`` ADU). The cubic has two positive roots where the readout is not
    small against the photon noise (both fit ``K2`` and ``K3``: more photons at a smaller
    ``M`` and less readout, or the reverse); the one nearer ``(c3 / c4) K4 / K3`` is taken."""
    _, k2, k3, k4 = k
    roots = np.roots([c3 * readout_e**2, 0.0, -c3 * k2, c2 * k3])
    positive = np.sort(roots[(np.abs(roots.imag) < 1e-9 * np.abs(roots)) & (roots.real > 0)].real)
    if positive.size == 0:  # K3 too large for K2 at this readout: the tangent point
        return float(np.sqrt(k2 / (3 * readout_e**2)))
    return float(positive[np.argmin(np.abs(positive - c3 * k4 / (c4 * k3)))])


def _draw(rng, excess, m, offset, variance, lam, shape, block) -> np.ndarray:
    """Blocks of counts ``offset + M Y + readout`` of the fitted camera (module docstring)."""
    size = (*shape, block * block)
    electrons = rng.poisson(lam, size)
    if excess == 2.0:  # each photoelectron an Exp(1) amount out of the EM register
        amplified = np.zeros(size)
        lit = electrons > 0
        amplified[lit] = rng.gamma(electrons[lit], 1.0)
    else:
        amplified = electrons.astype(np.float64)
    return offset + m * amplified + np.sqrt(variance) * rng.standard_normal(size)


@dataclass(frozen=True)
class SpatialEstimate:
    """The camera from spatial photon transfer (``spatial_photon_transfer``).

    Attributes
    ----------
    adu_per_photon, adu_per_photon_se : float
        ``M`` (ADU per photoelectron) and its bootstrap standard error.
    offset, offset_se : float
        ADU.
    readout_sd, readout_sd_se : float
        ADU (``readout_sd_se`` 0 where it was declared).
    photons : float
        The background's mean photoelectrons per pixel, ``lam``.
    blocks, frames : int
        Block positions and frames used.
    source : {"dark", "declared", "cumulants"}
        What fixed the readout: dark frames, a declared readout, or the fourth cumulant.
    """

    adu_per_photon: float
    adu_per_photon_se: float
    offset: float
    offset_se: float
    readout_sd: float
    readout_sd_se: float
    photons: float
    blocks: int
    frames: int
    source: str


def spatial_photon_transfer(
    sums: BlockSums, excess: float, known: Known, seed: int = 0
) -> SpatialEstimate:
    """The camera from the blocks' pooled cumulants, with bootstrap standard errors over block
    positions (module docstring).

    Raises
    ------
    BayespsfInputError
        Fewer than ``MIN_BLOCKS`` block positions, a background without photon noise, or a
        readout that the frames cannot measure (give it: dark frames or a declared readout).
    """
    if sums.positions < MIN_BLOCKS:
        raise BayespsfInputError(
            f"{sums.positions} background blocks of {sums.block} x {sums.block} pixels away from "
            f"the spots; the calibration from the frames' own pixels needs at least {MIN_BLOCKS} "
            "(give dark frames, --dark, or frames with more background)"
        )
    k = pooled_cumulants(sums)
    if not (k[2] > 0 and (known.source != "cumulants" or k[3] > 0)):
        raise BayespsfInputError(
            "the frames' background has no photon noise to calibrate against (its third or "
            "fourth cumulant is not positive): give dark frames (--dark) or a movie of at least "
            "20 frames of immobile molecules"
        )
    if known.source == "declared" and not known.readout_per_photon:
        declared = known.readout_e / known.e_per_adu
        if not declared**2 < k[1]:
            raise BayespsfInputError(
                f"readout_sd: the declared readout, {known.readout_e:g} e- = {declared:.4g} ADU "
                f"at {known.e_per_adu:g} e- per ADU, is not below the background's whole noise "
                f"(SD {np.sqrt(k[1]):.4g} ADU): check --readout-sd (electrons) and --e-per-adu"
            )
    m, offset, variance, lam = solve(k, excess, known)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(REPLICATES):
        counts = np.bincount(
            rng.integers(0, sums.positions, sums.positions), minlength=sums.positions
        )
        replicate = known
        if known.offset is not None:
            replicate = Known(
                offset=known.offset + known.offset_se * rng.standard_normal(),
                readout_sd=known.readout_sd + known.readout_sd_se * rng.standard_normal(),
            )
        draws.append(solve(pooled_cumulants(sums, counts.astype(float)), excess, replicate))
    # the same estimator on blocks drawn from the fitted camera: its spread does not hang on
    # the few large counts that an EMCCD's heavy tail gives one sample and not another
    model = []
    total = sums.positions * sums.frames
    drawn = min(total, PARAMETRIC_BLOCKS)  # the SE then scales as 1 / sqrt(blocks)
    if m > 0 and lam > 0 and variance >= 0:
        for _ in range(PARAMETRIC):
            counts = _draw(rng, excess, m, offset, variance, lam, (drawn, 1), sums.block)
            replicate = known
            if known.offset is not None:
                replicate = Known(
                    offset=known.offset + known.offset_se * rng.standard_normal(),
                    readout_sd=known.readout_sd + known.readout_sd_se * rng.standard_normal(),
                )
            model.append(solve(pooled_cumulants(sums_of(counts, sums.block)), excess, replicate))
    se_m, se_offset, se_variance, _ = np.array(draws).std(axis=0, ddof=1)
    if model:
        se_m, se_offset, se_variance = np.maximum(
            [se_m, se_offset, se_variance],
            np.array(model).std(axis=0, ddof=1)[:3] * np.sqrt(drawn / total),
        )
    if known.source == "cumulants" and not variance > 2 * se_variance:
        raise BayespsfInputError(
            f"the readout noise cannot be measured from these frames: the variance beyond the "
            f"photon noise reads {variance:.3g} +- {se_variance:.2g} ADU^2. State the camera's "
            "readout noise (--readout-sd in electrons, from its specification) or give dark "
            "frames (--dark)"
        )
    if not (m > 0 and lam > 0):
        raise BayespsfInputError(
            f"the frames' background gives {m:.3g} ADU per photon and {lam:.3g} photons per pixel: "
            "no photon noise above the readout to calibrate against (are the frames of light, "
            "and the dark frames, --dark, or the declared readout, --readout-sd, right?)"
        )
    readout = float(np.sqrt(variance))
    if known.source == "dark":
        readout_se, offset_se = known.readout_sd_se, known.offset_se
    elif known.source == "declared":
        readout_se, offset_se = 0.0, float(se_offset)
    else:
        readout_se, offset_se = float(se_variance / (2 * readout)), float(se_offset)
    return SpatialEstimate(
        adu_per_photon=float(m),
        adu_per_photon_se=float(se_m),
        offset=float(offset),
        offset_se=offset_se,
        readout_sd=readout,
        readout_sd_se=readout_se,
        photons=float(lam),
        blocks=sums.positions,
        frames=sums.frames,
        source=known.source,
    )


__all__ = [
    "BLOCK",
    "BlockSums",
    "Known",
    "SpatialEstimate",
    "block_sums",
    "plane_factors",
    "pooled_cumulants",
    "solve",
    "spatial_photon_transfer",
]
