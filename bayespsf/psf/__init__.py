"""What the spot looks like: the pixel-integrated elliptical Gaussian and how its widths change
with the emitter's axial position.

``gaussian``: expected photons per pixel (``expected_counts``), its analytic Jacobian, and the
sampled Gaussian of the paper's Eq. A3.1. ``defocus``: the widths against z (``Defocus``,
``HuangCurve``, ``PolynomialCurve``) and a fitted z calibration (``DefocusCalibration``).
"""

from bayespsf.psf.defocus import (
    CURVES,
    TERMS,
    Defocus,
    DefocusCalibration,
    HuangCurve,
    PolynomialCurve,
    widths_of_terms,
)
from bayespsf.psf.gaussian import (
    PARAMETER_NAMES,
    PIXEL_MODELS,
    check_geometry,
    check_pixel_model,
    expected_counts,
    expected_counts_and_jacobian,
    expected_counts_unchecked,
    pixel_centres,
    sampled_gaussian,
)

__all__ = [
    "CURVES",
    "PARAMETER_NAMES",
    "PIXEL_MODELS",
    "TERMS",
    "Defocus",
    "DefocusCalibration",
    "HuangCurve",
    "PolynomialCurve",
    "check_geometry",
    "check_pixel_model",
    "expected_counts",
    "expected_counts_and_jacobian",
    "expected_counts_unchecked",
    "pixel_centres",
    "sampled_gaussian",
    "widths_of_terms",
]
