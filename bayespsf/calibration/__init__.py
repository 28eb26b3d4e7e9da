"""The camera from data: offset and readout noise from dark frames (``dark_calibration``) or
from the movie itself (``photon_transfer``), an sCMOS camera's per-pixel gain from flat fields
(``flat_field_gain``), the ADU per photon from immobile molecules (``gain_from_molecules``, the
paper's Eq. photonConv), and all of it as a camera file (``calibrate_camera``; for fewer than 20
frames from the background by spatial photon transfer, ``bayespsf.calibration.short``)."""

from bayespsf.calibration.camera import CameraCalibration, calibrate_camera
from bayespsf.calibration.dark import (
    DarkCalibration,
    FlatFieldGain,
    dark_calibration,
    flat_field_gain,
)
from bayespsf.calibration.gain import (
    GainCalibration,
    GainEstimate,
    calibrate_gain,
    gain_from_molecules,
    photon_conv,
)

__all__ = [
    "CameraCalibration",
    "DarkCalibration",
    "FlatFieldGain",
    "GainCalibration",
    "GainEstimate",
    "calibrate_camera",
    "calibrate_gain",
    "dark_calibration",
    "flat_field_gain",
    "gain_from_molecules",
    "photon_conv",
]
