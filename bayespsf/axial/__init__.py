"""Axial position z from the spot's widths: the bounds on z (``bounds``), its posterior per ROI
(``z_posterior``) or per table of ROIs (``z_posteriors``), the widths' posterior pushed through
a curve (``z_draws``), the unified interval near focus on a symmetric curve
(``distance_from_focus``), and the curves fitted to a bead z-stack (``calibrate``);
``bayespsf.axial.match.check_calibration`` refuses a calibration made at another pixel size
or camera than the model's.

The curves themselves (``Defocus``, ``DefocusCalibration``) live in ``bayespsf.psf``."""

from bayespsf.axial.bounds import crlb_z, first_order_z_sd, paper_delta_z
from bayespsf.axial.calibrate import bead_rois, calibrate, fit_curve, step_widths
from bayespsf.axial.match import calibration_setup, check_calibration
from bayespsf.axial.posterior import ZPosterior, z_posterior
from bayespsf.axial.push import check_z_range, nearest_z, z_draws
from bayespsf.axial.table import z_posteriors
from bayespsf.axial.unified import bounded_mean_interval, distance_from_focus

__all__ = [
    "ZPosterior",
    "bead_rois",
    "bounded_mean_interval",
    "calibrate",
    "calibration_setup",
    "check_calibration",
    "check_z_range",
    "crlb_z",
    "distance_from_focus",
    "first_order_z_sd",
    "fit_curve",
    "nearest_z",
    "paper_delta_z",
    "step_widths",
    "z_draws",
    "z_posterior",
    "z_posteriors",
]
