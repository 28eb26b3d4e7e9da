"""The camera from a short movie (1 to ``MIN_FRAMES - 1`` frames) or one frame: spatial photon
transfer over the background away from the spots (``bayespsf.calibration.spatial``).

The spots are found on the frames' mean projection by ``bayespsf.movie.detect`` without a
camera (its noise estimated from the image) at a strict false-positive rate
(``FALSE_POSITIVES`` per projection), and every pixel within ``SPOT_SDS`` spot SDs of a
candidate is left out. The mask so depends on the spots, not on the background's noise: a
noise excess taken for a spot would take the tail of the counts with it and read ``M`` low,
and on 80 single simulated EMCCD frames a mask from the molecules' true positions moves ``M``
by at most 0.4 of its SE and covers the truth as often (71 of 80 within 1.96 SE). The offset
and readout come from dark frames where given; else the readout is declared (``readout_sd``,
electrons) or, where the photon noise does not hide it, measured with the offset from the
background's third and fourth cumulants. The result is approximate (a few per cent on an
EMCCD frame of 256 x 256 pixels, more for an sCMOS without dark frames) and says so in its
text and in the camera file's comments, with what would make it better.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bayespsf.calibration.dark import DarkCalibration, dark_calibration
from bayespsf.calibration.spatial import (
    BLOCK,
    Known,
    SpatialEstimate,
    block_sums,
    spatial_photon_transfer,
)
from bayespsf.io.camera_file import camera_file_text
from bayespsf.movie import detect
from bayespsf.movie.extract import open_movie

SPOT_SDS = 5.0  # pixels within this many spot SDs of a candidate are left out
FALSE_POSITIVES = 0.01  # the detector's expected false candidates per projection: a false one
# is a local excess of noise, whose removal would take the tail of the counts with it
ADVICE = (
    "approximate: spatial photon transfer of the background of a short movie; dark frames "
    "(--dark: offset and readout measured) or a movie of at least 20 frames of immobile "
    "molecules (the ADU per photon by Eq. photonConv) make it better"
)
ADVICE_DARK = (
    "approximate: spatial photon transfer of the background of a short movie; a movie of at "
    "least 20 frames of immobile molecules (the ADU per photon by Eq. photonConv) makes it better"
)


def camera_entries(
    kind: str,
    adu_per_photon: float,
    offset: float,
    readout_adu: float,
    e_per_adu: float,
    quantum_efficiency: float | None,
) -> dict:
    """The ``[camera]`` table of a calibration: an EMCCD's ``gain = M e_per_adu`` and
    ``readout_sd`` in electrons, an sCMOS's ``gain = M`` and readout ``variance`` in ADU^2."""
    if kind == "emccd":
        table = {
            "kind": "emccd",
            "gain": adu_per_photon * e_per_adu,
            "readout_sd": readout_adu * e_per_adu,
            "offset": offset,
            "e_per_adu": e_per_adu,
        }
    else:
        table = {
            "kind": "scmos",
            "gain": adu_per_photon,
            "offset": offset,
            "variance": readout_adu**2,
        }
    if quantum_efficiency is not None:
        table["quantum_efficiency"] = quantum_efficiency
    return table


@dataclass(frozen=True)
class ShortCalibration:
    """What ``calibrate_short`` measured; ``toml`` writes the camera file.

    Attributes
    ----------
    kind : {"emccd", "scmos"}
        The camera's kind.
    estimate : SpatialEstimate
        ADU per photon, offset and readout (ADU) with their standard errors.
    dark : DarkCalibration or None
        The dark frames' offset and readout, where given.
    e_per_adu : float
        Electrons per ADU stated in the file (EMCCD).
    pixel_size : float or None
        Pixel size (nm) stated in the file's ``[geometry]``.
    quantum_efficiency : float or None
        The camera's quantum efficiency as declared.
    spots : int
        Candidate spots whose surroundings were left out.
    """

    kind: str
    estimate: SpatialEstimate
    dark: DarkCalibration | None
    e_per_adu: float
    pixel_size: float | None
    quantum_efficiency: float | None
    spots: int

    def camera_table(self) -> dict:
        """The ``[camera]`` table (the scenes' keys) this calibration gives."""
        e = self.estimate
        return camera_entries(
            self.kind,
            e.adu_per_photon,
            e.offset,
            e.readout_sd,
            self.e_per_adu,
            self.quantum_efficiency,
        )

    def lines(self) -> list[str]:
        """The estimates with their errors, what they came from, and the advice."""
        e = self.estimate
        low, high = (
            e.adu_per_photon - 1.96 * e.adu_per_photon_se,
            e.adu_per_photon + 1.96 * e.adu_per_photon_se,
        )
        readout = {
            "dark": f"offset and readout from the dark frames ({self.dark.describe()})"
            if self.dark is not None
            else "",
            "declared": "readout as declared (--readout-sd), offset from the background's third "
            "cumulant",
            "cumulants": "offset and readout from the background's third and fourth cumulants",
        }[e.source]
        return [
            f"ADU per photon {e.adu_per_photon:.6g} (SE {e.adu_per_photon_se:.2g}; 95% interval "
            f"{low:.6g} to {high:.6g}), offset {e.offset:.6g} +- {e.offset_se:.2g} ADU, readout "
            f"{e.readout_sd:.4g}"
            + ("" if e.readout_sd_se == 0 else f" +- {e.readout_sd_se:.2g}")
            + f" ADU, from {e.blocks} background blocks of {BLOCK} x {BLOCK} pixels over "
            f"{e.frames} frame(s) away from {self.spots} spot(s) ({e.photons:.3g} photoelectrons "
            f"per pixel; {readout}; standard errors by a bootstrap over the blocks; assumes "
            "Poisson background photons)",
            ADVICE if self.dark is None else ADVICE_DARK,
        ]

    def summary(self) -> str:
        """What the command prints: the estimates, their errors and the advice."""
        return "\n".join(self.lines())

    def toml(self, command: str) -> str:
        """The camera file: its provenance and the advice as comments, then ``[geometry]``
        and ``[camera]`` (``bayespsf.io.camera_file.camera_file_text``)."""
        comments = [
            f"made by: {command}",
            *self.lines(),
            unit_comment(self.quantum_efficiency),
        ]
        tables = {} if self.pixel_size is None else {"geometry": {"pixel_size": self.pixel_size}}
        return camera_file_text({**tables, "camera": self.camera_table()}, comments)


def unit_comment(quantum_efficiency: float | None) -> str:
    """The camera file's comment on the unit of N and b.

    Parameters
    ----------
    quantum_efficiency : float or None
        The declared quantum efficiency, or None.

    Returns
    -------
    str
    """
    if quantum_efficiency is None:
        return "N and b: detected photoelectrons (no quantum efficiency declared)"
    return (
        f"N and b: incident photons (quantum efficiency {quantum_efficiency:g} as declared; "
        "the data cannot measure it)"
    )


def background_mask(image: np.ndarray, s0: float, pixel_size: float) -> tuple[np.ndarray, int]:
    """True away from the spots of ``image`` (the frames' mean), and the number of spots."""
    found = detect(image, psf_sd=s0, pixel_size=pixel_size, roi=3, false_positives=FALSE_POSITIVES)
    keep = np.ones(image.shape, bool)
    half = math.ceil(SPOT_SDS * s0 / pixel_size)
    for r, c in zip(found["row"].to_numpy(int), found["col"].to_numpy(int), strict=True):
        keep[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1] = False
    return keep, len(found)


def calibrate_short(
    movie,
    dark=None,
    *,
    kind: str,
    excess: float,
    s0: float,
    pixel_size: float,
    e_per_adu: float = 1.0,
    quantum_efficiency: float | None = None,
    readout_sd: float | None = None,
    seed: int = 0,
) -> ShortCalibration:
    """The camera from a short movie's background by spatial photon transfer.

    Parameters
    ----------
    movie : str, path or Movie
        One frame or a few (all are read into memory).
    dark : str, path, Movie or None, optional
        Dark frames of the same camera: they give the offset and readout.
    kind : {"emccd", "scmos"}
        The camera's kind; ``excess`` its excess-noise factor (2 or 1).
    excess : float
        2 for an EMCCD, 1 for a CCD or sCMOS.
    s0 : float
        The spot's SD (nm), for detection.
    pixel_size : float
        Pixel size (nm).
    e_per_adu : float, optional
        The electrons per ADU to state (EMCCD), and to turn a declared readout into ADU.
    quantum_efficiency : float or None, optional
        The camera's, to state.
    readout_sd : float or None, optional
        The camera's readout noise in electrons (EMCCD: after the register, ADU = e- /
        ``e_per_adu``; sCMOS: per photoelectron, ADU = e- x M), where no dark frames are given.
    seed : int, optional
        The bootstrap's seed.

    Returns
    -------
    ShortCalibration
        The estimates with their standard errors; ``toml(command)`` is the camera file.

    Raises
    ------
    BayespsfInputError
        Too little background away from the spots, no photon noise, or a readout the frames
        cannot measure (``--readout-sd`` or ``--dark`` fixes it).
    """
    movie = open_movie(movie)
    frames = np.asarray(movie[0 : len(movie)], dtype=np.float64)  # finite (``Movie.frames``)
    keep, spots = background_mask(frames.mean(axis=0), s0, pixel_size)
    first = None
    if dark is not None:
        first = dark_calibration(dark)
        known = Known(
            offset=first.offset,
            offset_se=first.offset_se,
            readout_sd=first.readout_sd,
            readout_sd_se=first.readout_sd_se,
        )
    elif readout_sd is not None:
        known = Known(readout_e=readout_sd, readout_per_photon=kind != "emccd", e_per_adu=e_per_adu)
    else:
        known = Known()
    estimate = spatial_photon_transfer(block_sums(frames, keep), excess, known, seed=seed)
    return ShortCalibration(
        kind, estimate, first, float(e_per_adu), pixel_size, quantum_efficiency, spots
    )


__all__ = [
    "ADVICE",
    "ADVICE_DARK",
    "ShortCalibration",
    "background_mask",
    "calibrate_short",
    "camera_entries",
    "unit_comment",
]
