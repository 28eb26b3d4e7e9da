"""Whether a z calibration belongs to the model it is used with: the pixel size and the
camera's kind its bead stack was measured at, where its ``source`` records them.

A calibration's curves are the spot's widths in nm against z through the optics of its bead
stack. The pixel size in the sample is the camera's pixel over the magnification, so another
pixel size means another magnification, camera port or binning: another optical path, whose
astigmatism and focus differ, and z from the first path's curves is then biased without a
sign (a 100 nm calibration with a 160 nm model gave z = 608 +- 26 nm for a true 50 nm).
Another kind of camera (EMCCD against sCMOS) is another port too. A camera's gain, offset or
readout do not change the widths in nm, so they are not compared.

Where a calibration records them: ``source["pixel_size"]`` and ``source["camera_kind"]``
(``bayespsf.axial.calibrate`` puts there the model's of ``step_widths``), else the
``[geometry] pixel_size`` and ``[camera] kind`` of the camera file that ``bayespsf
calibrate-z`` keeps in ``source["camera file"]`` (its files before the keys existed). A
calibration that records neither (curves fitted to a table of widths) is not checked.
"""

from __future__ import annotations

import tomllib
from typing import TYPE_CHECKING

import numpy as np

from bayespsf.errors import BayespsfInputError
from bayespsf.psf import DefocusCalibration

if TYPE_CHECKING:
    from bayespsf.model import Model

PIXEL_RTOL = 1e-3  # pixel sizes closer than this (relative) are the same


def calibration_setup(calibration: DefocusCalibration) -> dict:
    """The pixel size and camera kind a z calibration records, and where it records them.

    Parameters
    ----------
    calibration : DefocusCalibration
        A calibration from ``bayespsf.axial.calibrate`` or ``bayespsf.io.read_z_calibration``.

    Returns
    -------
    dict
        ``pixel_size`` (nm) and ``camera_kind`` (``"emccd"``, ``"scmos"``, ...), each a pair
        ``(value, where)`` with ``where`` the key that holds it, or None where the
        calibration does not record it.

    See Also
    --------
    check_calibration : compares them with a model.
    """
    source = calibration.source if isinstance(calibration.source, dict) else {}
    camera_file = {}
    text = source.get("camera file")
    if isinstance(text, str):
        try:
            camera_file = tomllib.loads(text)
        except tomllib.TOMLDecodeError:
            camera_file = {}
    out = {}
    for key, table, field in (
        ("pixel_size", "geometry", "pixel_size"),
        ("camera_kind", "camera", "kind"),
    ):
        if key in source:
            out[key] = (source[key], f"[source] {key}")
        elif isinstance(camera_file.get(table), dict) and field in camera_file[table]:
            where = f'the [{table}] {field} of the camera file in its [source] "camera file"'
            out[key] = (camera_file[table][field], where)
        else:
            out[key] = None
    return out


def check_calibration(calibration: DefocusCalibration, model: Model) -> None:
    """Refuse a z calibration measured at another pixel size or camera kind than ``model``.

    Parameters
    ----------
    calibration : DefocusCalibration
        The curves, with the ``source`` that records how they were made.
    model : Model
        The model of the ROIs whose z the curves are to give.

    Raises
    ------
    BayespsfInputError
        Where the calibration records a pixel size that differs from the model's by more than
        ``PIXEL_RTOL`` (relative), or a camera kind other than the model's: the message gives
        both values, where the calibration records its own and what to do.

    See Also
    --------
    calibration_setup : what a calibration records.
    bayespsf.axial.z_posterior, bayespsf.axial.z_posteriors : call this first.

    Notes
    -----
    The module docstring gives the reason: another pixel size or camera means another
    optical path, whose curves differ. Where both data and stack do image through the same
    optics (binning alone), the calibration file's ``[source] pixel_size`` (or
    ``camera_kind``) set to the model's value states so, and the check passes.
    """
    setup = calibration_setup(calibration)
    name = calibration.source.get("file") if isinstance(calibration.source, dict) else None
    what = "the z calibration" + (f" {name}" if name else "")
    if setup["pixel_size"] is not None:
        value, where = setup["pixel_size"]
        try:
            made = float(value)
        except (TypeError, ValueError):
            raise BayespsfInputError(
                f"{what}: {where} must be a pixel size in nm, got {value!r}"
            ) from None
        used = float(model.pixel_size)
        if not np.isclose(made, used, rtol=PIXEL_RTOL, atol=0.0):
            raise BayespsfInputError(
                f"{what} was made at {made:g} nm pixels ({where}), but the model's pixels are "
                f"{used:g} nm: another pixel size means another magnification or camera, whose "
                "defocus curves differ, so z from these would be biased. Calibrate a z-stack "
                f"taken at {used:g} nm pixels (`bayespsf calibrate-z` with the data's camera "
                "file), or check the data's pixel size (--pixel-size, else the camera file's "
                "[geometry] pixel_size, else the movie's metadata); if both image through the "
                "same optics "
                f"(binning alone), set pixel_size = {used:g} in the calibration file's [source]"
            )
    if setup["camera_kind"] is not None:
        made, where = setup["camera_kind"]
        used = str(model.camera.to_dict()["kind"])
        if str(made) != used:
            raise BayespsfInputError(
                f"{what} was made with a camera of kind {made} ({where}), but the model's is "
                f"{used}: another camera images through another port, whose defocus curves "
                "differ. Calibrate a z-stack taken on this camera (`bayespsf calibrate-z` with "
                "its camera file), or check the camera file (--camera); if both image through "
                f'the same optics, set camera_kind = "{used}" in the calibration file\'s [source]'
            )


__all__ = ["calibration_setup", "check_calibration"]
