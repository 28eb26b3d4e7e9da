"""Whether ROI counts can be analysed under a camera law: the screen behind
``Model.roi_problems`` and ``Model.check_counts``.

A whole stack is first screened in one compiled pass (``_validate.suspect_rois``); only the
ROIs it flags are examined one by one, to name their problem.
"""

from __future__ import annotations

import numpy as np

from bayespsf._validate import saturation_plateau, suspect_rois
from bayespsf.cameras import EMCCD, Camera
from bayespsf.errors import BayespsfInputError

OFFSET_SDS = 5.0  # counts this many readout SDs below the offset are not the camera's
OFFSET_FRACTION = 0.1  # ... nor an ROI with more than this fraction of such pixels


def roi_problems(camera: Camera, counts: np.ndarray, saturation: float) -> list[str | None]:
    """Why each ROI of ``counts`` cannot be analysed under ``camera``, or ``None`` where it can.

    The reasons: NaN or infinite pixels; counts outside the camera's domain (a photon camera's
    are whole numbers >= 0); every pixel equal (an empty, dead or clipped ROI); counts far
    below the camera's offset (more than ``OFFSET_FRACTION`` of the pixels over ``OFFSET_SDS``
    readout SDs below it, which the camera law gives a probability below 1e-6 each: not ADU
    above the offset, e.g. an offset subtracted twice); pixels at or above a declared
    ``saturation``; and, where no saturation is declared, a plateau of equal maximal counts
    (``saturation_plateau``) that marks an undeclared one.

    Parameters
    ----------
    camera : Camera
    counts : ndarray, shape (..., roi, roi)
        Float counts in ADU, of a checked shape (``Model.check_shape``).
    saturation : float
        The ADC's full scale in ADU, 0 where none is declared.

    Returns
    -------
    list of str or None
        One entry per ROI, in C order of the leading dimensions: the reason, or ``None``.
    """
    side = counts.shape[-1]
    flat = counts.reshape(-1, side * side)
    _, offset = camera.photons_per_adu()
    offset = np.broadcast_to(np.asarray(offset, dtype=np.float64), counts.shape[-2:]).ravel()
    readout = np.sqrt(camera.variance(np.zeros(counts.shape[-2:]))).ravel()
    floor = offset - OFFSET_SDS * readout
    out: list[str | None] = [None] * len(flat)
    for i in np.flatnonzero(_suspects(camera, flat, floor, side, saturation)):  # the rest pass
        out[i] = _roi_problem(camera, flat[i], offset, readout, side, saturation)
    return out


def _suspects(camera, flat, floor, side, saturation) -> np.ndarray:
    """ROIs that may have a problem (``_roi_problem`` decides), by whole-stack screens."""
    try:
        camera.check_counts(flat.reshape(-1, side, side))
    except BayespsfInputError:
        return np.ones(len(flat), dtype=bool)
    no_readout = isinstance(camera, EMCCD) and camera.readout_sd == 0
    return suspect_rois(
        np.ascontiguousarray(flat, dtype=np.float64),
        np.ascontiguousarray(floor, dtype=np.float64),
        float(camera.offset if no_readout else -np.inf),
        OFFSET_FRACTION,
        float(saturation),
    )


def _roi_problem(camera, roi, offset, readout, side, saturation) -> str | None:
    bad = np.count_nonzero(~np.isfinite(roi))
    if bad:
        return f"{bad} pixels are NaN or infinite"
    try:
        camera.check_counts(roi.reshape(side, side))
    except BayespsfInputError as exc:
        return str(exc)
    if np.all(roi == roi[0]):
        return (
            f"every pixel has the same value ({roi[0]:g}): an empty, dead or clipped ROI "
            "carries no spot"
        )
    if isinstance(camera, EMCCD) and camera.readout_sd == 0 and np.any(roi < camera.offset):
        return (
            f"counts below the offset ({camera.offset:g} ADU) are impossible for an EMCCD "
            f"without readout noise; min is {roi.min():.6g} (declare its readout_sd)"
        )
    below = np.mean(roi < offset - OFFSET_SDS * readout)
    if np.any(readout > 0) and below > OFFSET_FRACTION:
        return (
            f"{below:.0%} of the pixels lie more than {OFFSET_SDS:g} readout SDs below the "
            f"camera's offset ({np.median(offset):g} ADU; median count "
            f"{np.median(roi):.6g}): the counts are not in ADU above the offset (was the "
            "offset subtracted already, or is the camera's offset wrong?)"
        )
    if saturation > 0:
        saturated = int(np.count_nonzero(roi >= saturation))
        if saturated:
            return (
                f"{saturated} pixels are saturated (>= {saturation:g} ADU); their true "
                "counts are unknown and the model has no censored likelihood: crop or mask "
                "the ROI, or lower the EM gain"
            )
        return None
    plateau = saturation_plateau(roi)
    if plateau:
        return (
            f"{plateau} pixels share the ROI's maximum of {roi.max():.6g} ADU, a plateau "
            "that marks a saturated ADC or full well, and no saturation is declared: "
            "posteriors of saturated spots are wrong. Declare the camera's saturation level "
            "(`saturation = ...` in the [camera] table, or Model(saturation=...)), so that "
            "saturated ROIs are named exactly and the others analysed"
        )
    return None
