"""A camera file from data: offset and readout noise from dark frames, ADU per photon from the
movie's own immobile molecules (``bayespsf calibrate``).

The steps: ``dark_calibration`` of the dark frames gives the offset and readout noise in ADU;
a provisional ADU per photon from the movie's background pixels (their variance over frames
against their mean above the offset, the photon-transfer relation ``var = excess M (mean -
offset) + readout^2``) converts counts to photons for ``find_molecules``. It holds only for
Poisson background photons: paper-movie's background, Gaussian photon numbers of mean 2.75 and
SD 0.92 (variance 0.85, not 2.75), reads 10.8 against the true 16.7, which is why it is only
provisional (the selection's SNR rule is the one step it touches); the selected molecules'
frames before their bleaching step then give ``M`` by Eq. photonConv
(``gain_from_molecules``).

Without dark frames, the movie's own background pixels give the offset and readout noise by
photon transfer with their third cumulant (``bayespsf.calibration.photon_transfer``): first from the
dimmer half of the pixels with ``M`` from their fourth cumulant (for detection), then, once
the molecules have given ``M``, from the pixels that no candidate's ROI touches.

A movie of fewer than 20 frames has too few for either: its background away from the spots
gives the camera by spatial photon transfer (``bayespsf.calibration.short``), an approximate
result whose text and camera file say so and what would make it better.

The camera file holds the ``[camera]`` table of scenes and
``[geometry] pixel_size``, and records in its comments the command that made it and every
estimate with its error.

Units. An EMCCD's law depends on its gain and electrons per ADU only through ``M = gain /
e_per_adu`` (ADU per photon) and the readout in ADU: the file states ``e_per_adu`` (1 unless
the user gives the camera's value) and ``gain = M e_per_adu``, ``readout_sd`` = the readout in
ADU times ``e_per_adu``. For an sCMOS/CCD (``kind = "scmos"``, excess 1): ``gain = M`` ADU per
photoelectron and ``variance`` the readout variance in ADU^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bayespsf.calibration.dark import DarkCalibration, dark_calibration
from bayespsf.calibration.gain import GainEstimate, gain_from_molecules
from bayespsf.calibration.photon_transfer import (
    MIN_FRAMES,
    MovieOffset,
    away_from,
    first_adu_per_photon,
    offset_from_cumulants,
    pixel_cumulants,
)
from bayespsf.calibration.short import (
    ShortCalibration,
    calibrate_short,
    camera_entries,
    unit_comment,
)
from bayespsf.cameras import EMCCD, SCMOS
from bayespsf.errors import BayespsfInputError
from bayespsf.io.camera_file import camera_file_text
from bayespsf.model import MIN_ROI, Model
from bayespsf.movie.extract import check_sizes, open_movie
from bayespsf.movie.pipeline import find_molecules
from bayespsf.movie.project import project
from bayespsf.movie.psf_width import PsfWidth, estimate_psf_sd
from bayespsf.movie.select import Rules
from bayespsf.scene import units

EXCESS = {"emccd": 2.0, "scmos": 1.0}  # the excess-noise factor of each kind


@dataclass(frozen=True)
class CameraCalibration:
    """What ``calibrate_camera`` measured; ``toml`` writes the camera file.

    Attributes
    ----------
    kind : {"emccd", "scmos"}
        The camera's kind.
    offset : DarkCalibration or MovieOffset
        Offset and readout noise (ADU), from dark frames or from the movie's own pixels.
    provisional_adu_per_photon : float
        The first ADU per photon, from the background's photon transfer, that the molecules'
        estimate refines.
    gain : GainEstimate
        The ADU per photon from the movie's immobile molecules (Eq. photonConv), with its
        standard error and 95% interval.
    e_per_adu : float
        Electrons per ADU stated in the file (EMCCD).
    pixel_size : float or None
        Pixel size (nm) stated in the file's ``[geometry]``, if known.
    quantum_efficiency : float or None
        The camera's quantum efficiency as declared (the data cannot measure it); with it,
        N and b are incident photons.
    """

    kind: str
    offset: DarkCalibration | MovieOffset
    provisional_adu_per_photon: float
    gain: GainEstimate
    e_per_adu: float
    pixel_size: float | None
    quantum_efficiency: float | None = None

    def camera_table(self) -> dict:
        """The ``[camera]`` table (the scenes' keys) this calibration gives.

        Returns
        -------
        dict
            Keys of the scene schema's ``[camera]`` table.
        """
        return camera_entries(
            self.kind,
            self.gain.adu_per_photon,
            self.offset.offset,
            self.offset.readout_sd,
            self.e_per_adu,
            self.quantum_efficiency,
        )

    def summary(self) -> str:
        """What ``bayespsf calibrate`` prints: the ADU per photon with its error.

        Returns
        -------
        str
        """
        return str(self.gain)

    def toml(self, command: str) -> str:
        """The camera file: its provenance as comments, then ``[geometry]`` and ``[camera]``.

        Parameters
        ----------
        command : str
            The command that made the file, recorded in its first comment.

        Returns
        -------
        str
            The file's text (``bayespsf.io.camera_file.camera_file_text``), which
            ``bayespsf.io.read_camera_file`` reads.
        """
        g = self.gain
        low, high = g.interval
        comments = [
            f"made by: {command}",
            self.offset.describe(),
            f"ADU per photon {g.adu_per_photon:.6g} (SE {g.se:.2g}; 95% interval {low:.6g} to "
            f"{high:.6g}) from {int((~g.per_molecule['outlier']).sum())} molecules "
            f"({int(g.per_molecule['outlier'].sum())} outliers left out) by Eq. photonConv of "
            "DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)",
            f"provisional ADU per photon from the background: "
            f"{self.provisional_adu_per_photon:.4g}",
            unit_comment(self.quantum_efficiency),
        ]
        tables = {} if self.pixel_size is None else {"geometry": {"pixel_size": self.pixel_size}}
        return camera_file_text({**tables, "camera": self.camera_table()}, comments)


def provisional_adu_per_photon(movie, dark: DarkCalibration, excess: float) -> float:
    """The median over pixels of ``(var - readout^2) / (excess (mean - offset))``: the
    photon-transfer relation of the movie's (mostly background) pixels over its frames."""
    mean = project(movie, "mean")
    var = project(movie, "std") ** 2
    above = mean - dark.offset
    usable = above > 3.0 * dark.readout_sd / np.sqrt(len(movie))
    if usable.sum() < 0.5 * mean.size:
        raise BayespsfInputError(
            "the movie's pixels lie at the dark frames' offset: no background light to "
            "calibrate against (are the dark frames, --dark, from this camera and setting?)"
        )
    ratio = (var[usable] - dark.readout_sd**2) / (excess * above[usable])
    value = float(np.median(ratio))
    if not value > 0:
        raise BayespsfInputError(
            "the movie's pixels vary no more than the dark frames: no photon noise to calibrate "
            "(are the dark frames, --dark, from this camera and setting, and is the movie one of "
            "light?)"
        )
    return value


def calibrate_camera(
    movie,
    dark=None,
    *,
    kind: str,
    s0: float | PsfWidth | None = None,
    pixel_size: float | None = None,
    e_per_adu: float = 1.0,
    roi: int = 25,
    fit: int = 15,
    quantum_efficiency: float | None = None,
    readout_sd: float | None = None,
    rules: Rules | None = None,
) -> CameraCalibration | ShortCalibration:
    """A camera's offset, readout noise and ADU per photon from a movie (and dark frames).

    Offset and readout come from ``dark``, or without dark frames from the movie's own
    background pixels (``bayespsf.calibration.photon_transfer``); the ADU per photon from the
    movie's immobile molecules by Eq. photonConv (``gain_from_molecules``; module docstring).
    A movie of fewer than ``MIN_FRAMES`` (20) frames, one frame included, is calibrated
    instead from its background by spatial photon transfer (``calibrate_short``): an
    approximate result that says so.

    Parameters
    ----------
    movie : str, path or Movie
        The movie of immobile molecules.
    dark : str, path, Movie or None, optional
        Dark frames of the same camera and frame shape; None to calibrate from the movie alone.
    kind : {"emccd", "scmos"}
        The camera's kind (its excess-noise factor: 2 or 1).
    s0 : float, PsfWidth or None, optional
        The spot's SD (nm), for detection, or a ``PsfWidth`` (``bayespsf.movie.psf_width``:
        one already estimated is reported as estimated); default estimated from the movie's
        spots by least squares on its projection (``bayespsf.movie.estimate_psf_sd`` without
        a camera).
    pixel_size : float or None, optional
        Pixel size (nm); default the movie's metadata.
    e_per_adu : float, optional
        The electrons per ADU to state (EMCCD).
    roi, fit : int, optional
        The ROI cut around each molecule and its fitted centre (pixels, odd).
    quantum_efficiency : float or None, optional
        The camera's, to state (the data measure ADU per photoelectron, not the QE): the
        file's N and b are then incident photons.
    readout_sd : float or None, optional
        The camera's readout noise in electrons (its specification: after the EM register
        for an EMCCD, in ADU ``readout_sd / e_per_adu``; per photoelectron for an sCMOS, in
        ADU ``readout_sd M``); stands in where no dark frames are given and the movie cannot
        measure it.
    rules : Rules or None, optional
        The selection rules of the molecules the ADU per photon is measured on (default the
        paper's, ``Rules()``).

    Returns
    -------
    CameraCalibration or ShortCalibration
        What was measured (a ``ShortCalibration`` for fewer than 20 frames); its
        ``toml(command)`` is the camera file's text and ``summary()`` what the command prints.

    Raises
    ------
    BayespsfInputError
        For a bad argument, dark frames of another shape, no pixel size, or a movie whose
        molecules or background cannot calibrate the camera.

    See Also
    --------
    dark_calibration, gain_from_molecules, bayespsf.io.read_camera_file
    """
    if kind not in EXCESS:
        raise BayespsfInputError(f"kind must be one of {', '.join(EXCESS)} (--kind), got {kind!r}")
    check_sizes(roi, fit)  # before any frame is read
    if fit == roi:
        raise BayespsfInputError(
            f"fit ({fit}) must be smaller than roi ({roi}): the ROI's periphery outside the "
            "fit gives the background of Eq. photonConv (--fit, --roi)"
        )
    if quantum_efficiency is not None:
        units.check(quantum_efficiency, "incident")
    if readout_sd is not None and not (np.isfinite(readout_sd) and readout_sd >= 0):
        raise BayespsfInputError(
            f"readout_sd must be a number >= 0 (electrons; --readout-sd), got {readout_sd!r}"
        )
    if readout_sd is not None and dark is not None:
        raise BayespsfInputError(
            "readout_sd: the dark frames measure the readout; give one of them (--dark or "
            "--readout-sd), not both"
        )
    if not (np.isfinite(e_per_adu) and e_per_adu > 0):
        raise BayespsfInputError(f"e_per_adu must be a number > 0 (--e-per-adu), got {e_per_adu!r}")
    movie = open_movie(movie)
    dark_movie = None if dark is None else open_movie(dark)
    if dark_movie is not None and dark_movie.shape[1:] != movie.shape[1:]:
        raise BayespsfInputError(
            f"dark frames {dark_movie.shape[1:]} and movie frames {movie.shape[1:]} differ in "
            "shape: the dark frames (--dark) must come from the same camera region"
        )
    stated = pixel_size is not None
    pixel_size = movie.pixel_size if pixel_size is None else pixel_size
    if pixel_size is None:
        raise BayespsfInputError(
            "pixel_size: the movie's metadata give none; state it (nm): --pixel-size on the "
            "command line (the camera file written then holds it as [geometry] pixel_size), "
            "or pixel_size= from Python"
        )
    s0_source = "given"
    if isinstance(s0, PsfWidth):
        s0, s0_source = s0.sd, s0.source
    if s0 is None:  # the spot's SD: estimated where not stated (no camera yet)
        s0, s0_source = estimate_psf_sd(movie, pixel_size=pixel_size, fit=fit).sd, "estimated"
    excess = EXCESS[kind]
    if len(movie) < MIN_FRAMES:  # too few frames for the cumulants or the molecules
        return calibrate_short(
            movie,
            dark_movie,
            kind=kind,
            excess=excess,
            s0=s0,
            pixel_size=pixel_size,
            e_per_adu=float(e_per_adu),
            quantum_efficiency=None if quantum_efficiency is None else float(quantum_efficiency),
            readout_sd=readout_sd,
        )
    if dark_movie is not None:
        first = dark_calibration(dark_movie)
        m0 = provisional_adu_per_photon(movie, first, excess)
    else:
        cumulants = pixel_cumulants(movie)
        dimmer = cumulants.k1 <= np.median(cumulants.k1)  # mostly background, few molecules
        m0 = first_adu_per_photon(cumulants, excess, dimmer)
        declared = _readout_adu(readout_sd, kind, m0, e_per_adu)
        first = offset_from_cumulants(
            cumulants, m0, excess, dimmer, readout_adu=declared, check=False
        )
    if kind == "emccd":
        camera = EMCCD(m0, first.readout_sd, first.offset, 1.0, likelihood="table")
    else:
        # the exact law: Huang's approximation has no support where counts fall more than
        # s^2 below the offset, which 2 in 3 of a 15 x 15 ROI hold at 3 background photons and
        # a readout of 1.6 e- (its stack fits then ran to ~160 nm widths for 120)
        camera = SCMOS(m0, first.offset, first.readout_sd**2, likelihood="exact")
    found = find_molecules(
        movie, Model(MIN_ROI, pixel_size, camera), s0=s0, roi=roi, fit=fit, rules=rules
    )
    chosen = found.molecules[found.molecules["selected"]]
    if len(chosen) < 2:
        raise BayespsfInputError(
            _too_few_molecules(found, len(chosen), (s0, s0_source), pixel_size, stated)
        )
    frames = found.frames
    frames = frames[frames["before_bleach"] & frames["molecule"].isin(chosen["molecule"])]
    gain = gain_from_molecules(movie, chosen, frames, roi=roi, fit=fit, excess=excess)
    if dark_movie is None:  # the final offset: the pixels no candidate's ROI touches
        background = away_from(found.candidates, movie.shape[1:], roi // 2)
        declared = _readout_adu(readout_sd, kind, gain.adu_per_photon, e_per_adu)
        first = offset_from_cumulants(
            cumulants,
            gain.adu_per_photon,
            excess,
            background,
            adu_per_photon_se=gain.se,
            readout_adu=declared,
        )
    return CameraCalibration(
        kind,
        first,
        m0,
        gain,
        float(e_per_adu),
        pixel_size,
        None if quantum_efficiency is None else float(quantum_efficiency),
    )


def _too_few_molecules(found, selected: int, s0, pixel_size: float, stated: bool) -> str:
    """Why fewer than 2 molecules can calibrate the ADU per photon, and what would help
    (``s0``: the spot's SD in nm and ``"given"`` or ``"estimated"``)."""
    s0, source = s0
    candidates = found.candidates
    accepted = int((candidates["status"] == "accepted").sum())
    left_out = found.molecules.loc[~found.molecules["selected"].astype(bool), "rejected_by"]
    reasons = ", ".join(f"{rule} {n}" for rule, n in left_out.value_counts().items())
    helps = (
        f"if the movie holds spots, check --psf-sd (the spot's SD, {s0:g} nm {source}) and "
        f"--pixel-size ({pixel_size:g} nm, "
        + ("as given" if stated else "from the movie's metadata")
        + "), and --roi and --fit; `bayespsf detect` on the movie shows what was found and why "
        "each candidate was left out (its selection report)"
    )
    if "photon_window" in set(left_out):  # a short movie, or molecules that bleach early
        helps = (
            "molecules with fewer valid frames than the rules ask count with --min-valid-frames "
            f"N or --rules none; {helps}"
        )
    if selected == 0:
        if accepted == 0:
            what = (
                "detection found no spot on the movie's mean projection"
                if candidates.empty
                else f"detection accepted none of {len(candidates)} candidate spots"
            )
        else:
            what = (
                f"{accepted} spot(s) were detected but none passed the selection rules (left "
                f"out by: {reasons})"
            )
        return (
            f"no immobile molecule was found to calibrate the ADU per photon against: {what}. "
            "The ADU per photon comes from the frames of immobile single molecules (Eq. "
            "photonConv): give a movie of them (dark frames or background alone cannot give "
            f"it); {helps}"
        )
    return (
        f"{selected} molecule(s) passed the selection rules; the gain needs at least 2 "
        f"immobile single molecules (left out by: {reasons}); {helps}"
    )


def _readout_adu(readout_sd, kind: str, adu_per_photon: float, e_per_adu: float):
    """A declared readout SD in electrons as ADU (None stays None)."""
    if readout_sd is None:
        return None
    return readout_sd / e_per_adu if kind == "emccd" else readout_sd * adu_per_photon


__all__ = ["CameraCalibration", "calibrate_camera", "provisional_adu_per_photon"]
