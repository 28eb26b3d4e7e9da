"""The camera's ADU per photon from a movie's own immobile molecules: the paper's Eq.
photonConv over many molecules, combined with an error bar (issue 13, item 2).

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), "Photon gain calibration": over the
frames of one immobile molecule, pixel ``i``'s counts have mean ``<N_i*>`` and variance
``sigma_i*^2``, the background pixels ``<b*>`` and ``sigma_b*^2``, and

    M = (sigma_i*^2 - sigma_b*^2) / (2 (<N_i*> - <b*>))        (Eq. photonConv)

is the camera's ADU per photon: the EM register's excess noise makes the variance of an
amplified signal ``2 M^2`` per photon (``excess = 2``; a CCD or sCMOS has ``excess = 1``).
``bayespsf.calibration.calibrate_gain`` applies it to the nine centre pixels of one molecule.

Here, per molecule and over the pixels of its ROI's centre, the variance excess is fitted as

    sigma_i*^2 - sigma_b*^2 = excess M S_i + phi S_i^2,    S_i = <N_i*> - <b*>,

by weighted least squares. The quadratic term is the frame-to-frame fluctuation of the
molecule's photon count (a relative variance ``phi``, common to its pixels): Eq. photonConv
assumes none, and the paper's own molecules fluctuated by up to 20% between frames, which would
raise the variance of a 100-photon pixel by as much as its shot noise does. The weights are
``1 / Var(sigma_i*^2) = (K - 1) / (2 v_i^2)`` with ``v_i`` the fitted variance (K frames;
normal counts), iterated from equal weights so that they do not depend on the noise of the
variances they weigh. The molecules' estimates are combined by their inverse-variance weighted
mean; its standard error is taken from the scatter of the molecules about it (Birge's ratio:
it holds even where the per-molecule errors are misjudged), and the 95% interval from Student's
t with ``molecules - 1`` degrees of freedom. A molecule whose estimate lies more than
``OUTLIER_Z`` of its own SEs from the others' (first their weighted median, then the weighted
mean of those kept) is left out and flagged: a molecule that moves inflates its pixels'
variance beyond shot noise by an amount not proportional to ``S_i^2`` (moving molecules of a
paper-movie read 48-270 ADU per photon against 16.7). A fluctuation common to a molecule's
pixels is not an outlier: frames that span its bleaching step add ``p (1 - p) S_i^2`` and fall
into the quadratic term.

The background pixels are the ROI's periphery outside its central ``fit`` x ``fit`` pixels
(the paper's 25 x 25 ROIs and 15 x 15 fits). Frames are read a block at a time: memory holds two
sums per ROI pixel and molecule, whatever the movie's length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from bayespsf.errors import BayespsfInputError
from bayespsf.movie.extract import check_sizes, iter_rois, open_movie

MIN_FRAMES = 10  # per molecule: a variance over fewer frames is too noisy to weigh
OUTLIER_Z = 5.0  # molecules this many of their SEs from the others are left out (and flagged)


@dataclass(frozen=True)
class GainEstimate:
    """The camera's ADU per photon from many molecules (``gain_from_molecules``).

    Attributes
    ----------
    adu_per_photon : float
        ``M``: for an EMCCD, the EM gain over the electrons per ADU (gain / e_per_adu).
    se : float
        Its standard error (from the molecules' scatter).
    interval : tuple of float
        The 95% interval (Student's t, molecules - 1 degrees of freedom): the error bar.
    per_molecule : pandas.DataFrame
        ``molecule``, ``x``, ``y``, ``frames`` (the number used), ``adu_per_photon``,
        ``se``, ``fluctuation`` (the fitted
        relative variance ``phi`` of its photons between frames), ``peak_photons`` and
        ``outlier`` (left out of the combination).
    excess : float
        The excess-noise factor assumed (2: EMCCD; 1: CCD, sCMOS).
    """

    adu_per_photon: float
    se: float
    interval: tuple[float, float]
    per_molecule: pd.DataFrame
    excess: float

    def __str__(self) -> str:
        low, high = self.interval
        return (
            f"{self.adu_per_photon:.4g} ADU per photon (SE {self.se:.2g}; 95% interval "
            f"{low:.4g} to {high:.4g}) from {int((~self.per_molecule['outlier']).sum())} "
            f"molecules ({int(self.per_molecule['outlier'].sum())} outliers left out), "
            "Eq. photonConv of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) with excess "
            f"{self.excess:g}"
        )


def gain_from_molecules(
    movie, molecules, frames, *, roi: int = 25, fit: int = 15, centre: int = 7,
    excess: float = 2.0, block: int = 64,
) -> GainEstimate:  # fmt: skip
    """ADU per photon from the frames of immobile molecules (module docstring).

    Parameters
    ----------
    movie : Movie or path
    molecules : pandas.DataFrame
        ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention) of immobile
        single molecules, e.g. the selected rows of ``find_molecules``.
    frames : pandas.DataFrame
        ``molecule`` and ``frame``: the frames of each molecule to use, e.g. those before
        its bleaching step (at least ``MIN_FRAMES`` per molecule; others are dropped).
    roi, fit : int
        The cut (its periphery outside ``fit`` x ``fit`` is the background) and its centre.
    centre : int
        Side of the pixels around the molecule whose variances are fitted (odd, <= fit).
    excess : float
        The excess-noise factor: 2 for an EMCCD, 1 for a CCD or sCMOS.
    block : int
        Frames read at a time.
    """
    check_sizes(roi, fit)
    check_sizes(fit, centre)
    if fit == roi:
        raise BayespsfInputError(f"fit ({fit}) must be smaller than roi ({roi}): the "
                                 "periphery gives the background")  # fmt: skip
    if not (np.isfinite(excess) and excess > 0):
        raise BayespsfInputError(f"excess must be a number > 0 (2: EMCCD), got {excess!r}")
    for name, table, columns in (("molecules", molecules, ("molecule", "x", "y")),
                                 ("frames", frames, ("molecule", "frame"))):  # fmt: skip
        if not isinstance(table, pd.DataFrame) or not set(columns) <= set(table.columns):
            raise BayespsfInputError(f"{name} must be a table with columns {list(columns)}")
    movie = open_movie(movie)
    use = frames.groupby("molecule")["frame"].apply(lambda f: set(map(int, f)))
    use = use[use.map(len) >= MIN_FRAMES]
    chosen = molecules[molecules["molecule"].isin(use.index)].reset_index(drop=True)
    if len(chosen) < 2:
        raise BayespsfInputError(
            f"gain_from_molecules needs at least 2 molecules with >= {MIN_FRAMES} frames each; "
            f"got {len(chosen)}"
        )
    sums = _moments(movie, chosen, use, roi, fit, block)
    rows = [_one_molecule(mid, *sums[mid], roi, fit, centre, excess) for mid in chosen["molecule"]]
    per_molecule = pd.DataFrame(rows)
    per_molecule.insert(1, "x", chosen["x"].to_numpy())
    per_molecule.insert(2, "y", chosen["y"].to_numpy())
    return _combine(per_molecule, excess)


def _moments(movie, molecules, use, roi, fit, block) -> dict:
    """Per molecule: frames used, and the sums of counts and of squared counts per pixel."""
    sums = {mid: [0, np.zeros((roi, roi)), np.zeros((roi, roi))] for mid in molecules["molecule"]}
    for stack in iter_rois(movie, molecules, roi=roi, fit=fit, block=block):
        ids, frames = stack.table["molecule"].to_numpy(), stack.table["frame"].to_numpy()
        for mid in pd.unique(ids):
            rows = (ids == mid) & np.isin(frames, list(use[mid]))
            rois = stack.counts[rows].astype(np.float64)
            entry = sums[mid]
            entry[0] += len(rois)
            entry[1] += rois.sum(axis=0)
            entry[2] += np.square(rois).sum(axis=0)
    return sums


def _one_molecule(molecule, k, total, squares, roi, fit, centre, excess) -> dict:
    """Eq. photonConv with the fluctuation term, by iterated weighted least squares."""
    mean = total / k
    var = (squares - k * mean**2) / (k - 1)
    ring = np.ones((roi, roi), bool)
    lo = (roi - fit) // 2
    ring[lo : lo + fit, lo : lo + fit] = False
    c = (roi - centre) // 2
    b_mean, b_var = mean[ring].mean(), var[ring].mean()
    s = (mean[c : c + centre, c : c + centre] - b_mean).ravel()
    excess_var = (var[c : c + centre, c : c + centre] - b_var).ravel()
    design = np.column_stack([excess * s, s * s])
    weights = np.ones_like(s)
    for _ in range(3):
        w = np.sqrt(weights)
        coef, *_ = np.linalg.lstsq(design * w[:, None], excess_var * w, rcond=None)
        fitted = np.maximum(b_var + design @ coef, b_var)
        weights = (k - 1) / (2.0 * fitted**2)
    # the covariance of a weighted least-squares fit with known weights
    cov = np.linalg.inv(design.T @ (design * weights[:, None]))
    m = float(coef[0])
    return {"molecule": molecule, "frames": int(k), "adu_per_photon": m,
            "se": float(np.sqrt(cov[0, 0])), "fluctuation": float(coef[1]),
            "peak_photons": float(s.max() / m) if m > 0 else np.nan}  # fmt: skip


def _combine(per_molecule: pd.DataFrame, excess: float) -> GainEstimate:
    m_all = per_molecule["adu_per_photon"].to_numpy()
    se_all = per_molecule["se"].to_numpy()
    order = np.argsort(m_all)
    cumulative = np.cumsum(1.0 / se_all[order] ** 2)
    centre = m_all[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])]  # weighted median
    for _ in range(3):
        outlier = np.abs(m_all - centre) > OUTLIER_Z * se_all
        kept = ~outlier
        centre = np.sum(m_all[kept] / se_all[kept] ** 2) / np.sum(1.0 / se_all[kept] ** 2)
    per_molecule = per_molecule.assign(outlier=outlier)
    m, w = m_all[~outlier], 1.0 / se_all[~outlier] ** 2
    n = len(m)
    if n < 2:
        raise BayespsfInputError("gain_from_molecules: fewer than 2 molecules agree")
    mean = float(np.sum(w * m) / np.sum(w))
    scatter = np.sum(w * (m - mean) ** 2) / (n - 1)  # Birge's ratio squared
    se = float(np.sqrt(scatter / np.sum(w)))
    half = float(stats.t.ppf(0.975, n - 1)) * se
    return GainEstimate(mean, se, (mean - half, mean + half), per_molecule, float(excess))


__all__ = ["GainEstimate", "gain_from_molecules"]
