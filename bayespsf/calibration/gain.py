"""The camera's ADU per photon from a movie's own immobile molecules: the paper's Eq.
photonConv over many molecules, combined with an error bar.

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), "Photon gain calibration": over the
frames of one immobile molecule, pixel ``i``'s counts have mean ``<N_i*>`` and variance
``sigma_i*^2``, the background pixels ``<b*>`` and ``sigma_b*^2``, and

    M = (sigma_i*^2 - sigma_b*^2) / (2 (<N_i*> - <b*>))        (Eq. photonConv)

is the camera's ADU per photon: the EM register's excess noise makes the variance of an
amplified signal ``2 M^2`` per photon (``excess = 2``; a CCD or sCMOS has ``excess = 1``).
``calibrate_gain`` applies it, as the paper does, to the nine centre pixels of one molecule
(``photon_conv``).

Here, per molecule and over the pixels of its ROI's centre, the variance excess is fitted as

    sigma_i*^2 - sigma_b*^2 = excess M S_i + phi S_i^2,    S_i = <N_i*> - <b*>,

by weighted least squares. The quadratic term is the frame-to-frame fluctuation of the
molecule's photon count (a relative variance ``phi``, common to its pixels): Eq. photonConv
assumes none, and the paper's own molecules fluctuated by up to 20% between frames, which would
raise the variance of a 100-photon pixel by as much as its shot noise does. The weights are ``1
/ Var(sigma_i*^2) = (K - 1) / (2 v_i^2)`` with ``v_i`` the fitted variance (K frames; normal
counts), iterated from equal weights so that they do not depend on the noise of the variances
they weigh. The molecules' estimates are combined by their inverse-variance weighted mean, and
then each molecule is fitted again with the variances of its weights taken at that common ``M``
(and its own ``phi``): weights from a molecule's own ``M`` give a molecule that reads low a
small SE and a large weight, which pulls the combination low by about half its SE. The standard
error is the larger of the one from the molecules' SEs and the one from their scatter about the
mean (Birge's ratio, which holds where the per-molecule errors are misjudged by a common
factor): over ~15 molecules the scatter alone is itself uncertain by ~20%, and a movie whose
molecules happen to agree closely would otherwise be given a small SE. The 95% interval is from
Student's t with ``molecules - 1`` degrees of freedom. A molecule whose estimate lies more than
``OUTLIER_Z`` of its own SEs from the others' (first their weighted median, then the weighted
mean of those kept) is left out and flagged: a molecule that moves inflates its pixels' variance
beyond shot noise by an amount not proportional to ``S_i^2`` (moving molecules of a paper-movie
read 48-270 ADU per photon against 16.7). A fluctuation common to a molecule's pixels is not an
outlier: frames that span its bleaching step add ``p (1 - p) S_i^2`` and fall into the quadratic
term.

The background pixels are the ROI's periphery outside its central ``fit`` x ``fit`` pixels
(the paper's 25 x 25 ROIs and 15 x 15 fits). Frames are read a block at a time: memory holds two
sums per ROI pixel and molecule, whatever the movie's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy import stats

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.movie import Movie, iter_rois
from bayespsf.movie.extract import check_sizes, open_movie

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

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
        Its standard error: the larger of the one from the molecules' SEs and the one from
        their scatter (Birge's ratio).
    interval : tuple of float
        The 95% interval (Student's t, molecules - 1 degrees of freedom): the error bar.
    per_molecule : pandas.DataFrame
        ``molecule``, ``x``, ``y``, ``frames`` (the number used), ``adu_per_photon``,
        ``se``, ``fluctuation`` (the fitted
        relative variance ``phi`` of its photons between frames), ``peak_photons`` and
        ``outlier`` (left out of the combination).
    excess : float
        The excess-noise factor assumed (2: EMCCD; 1: CCD, sCMOS).

    See Also
    --------
    gain_from_molecules : makes one.
    """

    adu_per_photon: float
    se: float
    interval: tuple[float, float]
    per_molecule: pd.DataFrame
    excess: float

    def __str__(self) -> str:
        """One line: the estimate, its SE and interval, the molecules used and left out."""
        low, high = self.interval
        return (
            f"{self.adu_per_photon:.4g} ADU per photon (SE {self.se:.2g}; 95% interval "
            f"{low:.4g} to {high:.4g}) from {int((~self.per_molecule['outlier']).sum())} "
            f"molecules ({int(self.per_molecule['outlier'].sum())} outliers left out), "
            "Eq. photonConv of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) with excess "
            f"{self.excess:g}"
        )


def gain_from_molecules(
    movie: Movie | str | Path,
    molecules: pd.DataFrame,
    frames: pd.DataFrame,
    *,
    roi: int = 25,
    fit: int = 15,
    centre: int = 7,
    excess: float = 2.0,
    block: int = 64,
) -> GainEstimate:
    """ADU per photon from the frames of immobile molecules.

    Parameters
    ----------
    movie : Movie or path
        The movie in counts (ADU), from ``read_movie`` or a path it opens.
    molecules : pandas.DataFrame
        ``molecule``, ``x``, ``y`` (camera pixels, picasso's convention) of immobile
        single molecules, e.g. the selected rows of ``find_molecules``.
    frames : pandas.DataFrame
        ``molecule`` and ``frame``: the frames of each molecule to use, e.g. those before
        its bleaching step (at least ``MIN_FRAMES`` per molecule; others are dropped).
    roi, fit : int, default 25 and 15
        Odd sides in pixels of the cut (its periphery outside ``fit`` x ``fit`` is the
        background) and of its centre; ``fit < roi``.
    centre : int, default 7
        Side of the pixels around the molecule whose variances are fitted (odd, <= fit).
    excess : float, default 2.0
        The excess-noise factor: 2 for an EMCCD, 1 for a CCD or sCMOS.
    block : int, default 64
        Frames read at a time.

    Returns
    -------
    GainEstimate
        ``adu_per_photon`` (ADU per photon; for an EMCCD, the EM gain over the electrons per
        ADU), its ``se`` and 95% ``interval``, and ``per_molecule``: one row per molecule
        used, with ``molecule``, ``x``, ``y``, ``frames``, ``adu_per_photon``, ``se``,
        ``fluctuation`` (relative variance ``phi`` of its photons between frames),
        ``peak_photons`` and ``outlier``.

    Raises
    ------
    BayespsfInputError
        Even or inconsistent sizes (``fit`` must be smaller than ``roi``), an ``excess`` that
        is not > 0, tables without their columns, fewer than 2 molecules with
        ``MIN_FRAMES`` frames, or fewer than 2 molecules that agree.

    See Also
    --------
    calibrate_gain : the paper's Eq. photonConv on one molecule, as the paper states it.
    photon_conv : the equation itself.
    find_molecules : immobile molecules and their frames before bleaching.

    Notes
    -----
    The module docstring gives the method: per molecule, the variance excess of its ROI's
    centre pixels is fitted as ``excess M S_i + phi S_i^2`` by iterated weighted least
    squares (Eq. photonConv of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), with a
    term for the frame-to-frame fluctuation of the photon count); the molecules' estimates
    are combined by their inverse-variance weighted mean (refitted with weights at the common
    ``M``), with an SE that is the larger of the one from their SEs and the one from their
    scatter (Birge's ratio), and a Student's t interval; a molecule more than ``OUTLIER_Z``
    of its SEs from the others is left out and flagged (a moving molecule).

    Examples
    --------
    Four immobile molecules of a simulated movie (the ``paper-movie`` scene's EMCCD: gain 200,
    12 e- per ADU, so M = 16.7 ADU per photon), all 60 frames of each:

    >>> import tempfile
    >>> from pathlib import Path
    >>> import pandas as pd
    >>> import bayespsf
    >>> from bayespsf.calibration import gain_from_molecules
    >>> scene = bayespsf.load_scene("paper-movie").replace(
    ...     movie={"frames": 60, "height": 96, "width": 96, "molecules": 4, "dark_frames": 0,
    ...            "bleach_mean": 1e6, "two_fluorophores": 0.0, "moving": 0.0}
    ... )
    >>> made = bayespsf.simulate_movie(scene, seed=5, out=Path(tempfile.mkdtemp()) / "m")
    >>> frames = pd.read_csv(made.files["truth"])[["molecule", "frame"]]
    >>> gain = gain_from_molecules(made.files["movie"], made.molecules, frames)
    >>> round(gain.adu_per_photon, 1), gain.interval[0] < 200 / 12 < gain.interval[1]
    (17.2, True)
    """
    check_sizes(roi, fit)
    check_sizes(fit, centre, names=("fit", "centre"))
    if fit == roi:
        raise BayespsfInputError(
            f"fit ({fit}) must be smaller than roi ({roi}): the periphery gives the background "
            "(--fit, --roi)"
        )
    if not (np.isfinite(excess) and excess > 0):
        raise BayespsfInputError(
            f"excess must be a number > 0 (2: EMCCD, 1: CCD or sCMOS; --kind), got {excess!r}"
        )
    for name, table, columns in (
        ("molecules", molecules, ("molecule", "x", "y")),
        ("frames", frames, ("molecule", "frame")),
    ):
        if not isinstance(table, pd.DataFrame) or not set(columns) <= set(table.columns):
            raise BayespsfInputError(f"{name} must be a table with columns {list(columns)}")
    movie = open_movie(movie)
    use = frames.groupby("molecule")["frame"].apply(lambda f: set(map(int, f)))
    use = use[use.map(len) >= MIN_FRAMES]
    chosen = molecules[molecules["molecule"].isin(use.index)].reset_index(drop=True)
    if len(chosen) < 2:
        raise BayespsfInputError(
            f"gain_from_molecules needs at least 2 molecules with >= {MIN_FRAMES} frames each; "
            f"got {len(chosen)} (the frames before each molecule's bleaching step: give a longer "
            "movie, or one whose molecules bleach later)"
        )
    sums = _moments(movie, chosen, use, roi, fit, block)
    rows = [_one_molecule(mid, *sums[mid], roi, fit, centre, excess) for mid in chosen["molecule"]]
    first = _combine(_table(rows, chosen), excess)
    # again, each molecule weighted at the molecules' common M (module docstring); an outlier
    # keeps its own weights, which leave it out again
    outlier = first.per_molecule["outlier"].to_numpy()
    rows = [
        row
        if out
        else _one_molecule(mid, *sums[mid], roi, fit, centre, excess, first.adu_per_photon)
        for row, out, mid in zip(rows, outlier, chosen["molecule"], strict=True)
    ]
    return _combine(_table(rows, chosen), excess)


def _table(rows: list[dict], chosen: pd.DataFrame) -> pd.DataFrame:
    per_molecule = pd.DataFrame(rows)
    per_molecule.insert(1, "x", chosen["x"].to_numpy())
    per_molecule.insert(2, "y", chosen["y"].to_numpy())
    return per_molecule


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


def _one_molecule(molecule, k, total, squares, roi, fit, centre, excess, common=None) -> dict:
    """Eq. photonConv with the fluctuation term, by iterated weighted least squares; the
    weights' variances use ``common`` for ``M`` where given (else the molecule's own fit)."""
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
        at = coef if common is None else np.array([common, coef[1]])
        fitted = np.maximum(b_var + design @ at, b_var)
        weights = (k - 1) / (2.0 * fitted**2)
    # the covariance of a weighted least-squares fit with known weights
    cov = np.linalg.inv(design.T @ (design * weights[:, None]))
    m = float(coef[0])
    return {
        "molecule": molecule,
        "frames": int(k),
        "adu_per_photon": m,
        "se": float(np.sqrt(cov[0, 0])),
        "fluctuation": float(coef[1]),
        "peak_photons": float(s.max() / m) if m > 0 else np.nan,
    }


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
        each = ", ".join(f"{m_all[k]:.4g} +- {se_all[k]:.2g}" for k in np.argsort(m_all)[:10]) + (
            " ..." if len(m_all) > 10 else ""
        )
        raise BayespsfInputError(
            f"gain_from_molecules: fewer than 2 molecules agree within {OUTLIER_Z:g} of their "
            f"SEs (ADU per photon of each: {each}): moving or blinking molecules inflate their "
            "pixels' variance; give a movie with more immobile single molecules"
        )
    mean = float(np.sum(w * m) / np.sum(w))
    birge = np.sum(w * (m - mean) ** 2) / (n - 1)  # Birge's ratio squared
    se = float(np.sqrt(max(birge, 1.0) / np.sum(w)))  # never below the molecules' own SEs
    half = float(stats.t.ppf(0.975, n - 1)) * se
    return GainEstimate(mean, se, (mean - half, mean + half), per_molecule, float(excess))


def photon_conv(
    signal: float | np.ndarray, variance_excess: float | np.ndarray, excess: float = 2.0
) -> float | np.ndarray:
    """The paper's Eq. photonConv: ADU per photon from a pixel's mean signal above background,
    ``<N_i*> - <b*>``, and its variance above the background's, ``sigma_i*^2 - sigma_b*^2``.

    The excess-noise factor is 2 for an EM register (the paper's form) and 1 for a CCD or
    sCMOS. ``gain_from_molecules`` fits the same relation with a fluctuation term, to which it
    reduces when the molecule's photon count does not change from frame to frame.

    Parameters
    ----------
    signal : float or ndarray
        Mean counts above the background (ADU), > 0.
    variance_excess : float or ndarray
        Variance of the counts above the background's variance (ADU^2).
    excess : float, default 2.0
        The excess-noise factor.

    Returns
    -------
    float or ndarray
        ADU per photon.

    See Also
    --------
    calibrate_gain : the equation on one molecule's centre pixels.
    gain_from_molecules : with a fluctuation term, over many molecules.
    """
    return variance_excess / (excess * signal)


@dataclass(frozen=True)
class GainCalibration:
    """Result of ``calibrate_gain``: ADU per photon and what it was computed from.

    Attributes
    ----------
    adu_per_photon : float
        The mean of ``pixel_estimates``.
    pixel_estimates : numpy.ndarray
        Eq. photonConv of each pixel used (nine, or the centre pixel alone).
    background_mean : float
        ``<b*>``, ADU.
    background_variance : float
        ``sigma_b*^2``, ADU^2.
    snr : float
        ``I0 / sqrt(I0 + sigma_b^2)`` in photons, from the centre pixel's estimate.
    centre : tuple of int
        Row and column of the centre pixel.

    See Also
    --------
    calibrate_gain : makes one.
    """

    adu_per_photon: float
    pixel_estimates: np.ndarray  # Eq. photonConv of each pixel used
    background_mean: float  # <b*>, ADU
    background_variance: float  # sigma_b*^2, ADU^2
    snr: float  # I0 / sqrt(I0 + sigma_b^2) in photons, from the centre pixel's estimate
    centre: tuple[int, int]  # row, column of the centre pixel


def calibrate_gain(movie: ArrayLike, snr_threshold: float = 3.0) -> GainCalibration:
    """ADU per photon from a movie ``(frames, roi, roi)`` of one immobile molecule, by the
    paper's Eq. photonConv as it states it (no fluctuation term).

    Background pixels are the ROI's border; the centre is the brightest pixel of the
    background-subtracted mean image (kept one pixel from the border). Eq. photonConv is
    averaged over the nine centre pixels, or taken from the centre pixel alone when the
    signal-to-noise ratio ``I0 / sqrt(I0 + sigma_b^2)`` (photons) is at most
    ``snr_threshold``. It assumes Poisson photon statistics without frame-to-frame changes of
    N, and a background that is the same in every pixel.

    Parameters
    ----------
    movie : array_like, shape (frames, rows, columns)
        Counts (ADU) of one immobile molecule, at least 3 frames of at least 5 x 5 pixels.
    snr_threshold : float, default 3.0
        Above this signal-to-noise ratio the nine centre pixels are averaged.

    Returns
    -------
    GainCalibration
        The ADU per photon and what it was computed from.

    Raises
    ------
    BayespsfInputError
        If the movie is too small, not finite, or its centre is not brighter than its border.

    See Also
    --------
    gain_from_molecules : the same equation over many molecules, with an error bar.
    """
    m = finite_array("movie", movie)
    if m.ndim != 3 or m.shape[0] < 3 or min(m.shape[1:]) < 5:
        raise BayespsfInputError(
            f"movie must have shape (frames >= 3, rows >= 5, columns >= 5), got {m.shape}"
        )
    mean = m.mean(axis=0)
    var = m.var(axis=0, ddof=1)
    border = np.ones(mean.shape, bool)
    border[1:-1, 1:-1] = False
    b_mean, b_var = mean[border].mean(), var[border].mean()
    inner = np.where(border, -np.inf, mean)
    row, col = np.unravel_index(np.argmax(inner), mean.shape)
    row, col = int(np.clip(row, 1, mean.shape[0] - 2)), int(np.clip(col, 1, mean.shape[1] - 2))

    def pixel(r, c):
        signal = mean[r, c] - b_mean
        if signal <= 0:
            raise BayespsfInputError("movie: the centre pixel is not brighter than the background")
        return photon_conv(signal, var[r, c] - b_var)

    centre_m = pixel(row, col)
    i0 = (mean[row, col] - b_mean) / centre_m
    snr = i0 / np.sqrt(i0 + b_var / centre_m**2)
    if snr > snr_threshold:
        estimates = np.array([pixel(row + dr, col + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    else:
        estimates = np.array([centre_m])
    return GainCalibration(
        float(estimates.mean()), estimates, float(b_mean), float(b_var), float(snr), (row, col)
    )


__all__ = [
    "GainCalibration",
    "GainEstimate",
    "calibrate_gain",
    "gain_from_molecules",
    "photon_conv",
]
