"""The inference model: geometry, camera law (one likelihood tier) and prior of one molecule.

Built from the same scene as the simulator (``Model.from_scene``), or from geometry and a
camera for real data. It maps parameters ``x0 y0 s_x s_y N b`` (``PARAMETER_NAMES``) to
expected photons per pixel and scores counts under the camera law, vectorised over leading
batch dimensions (walkers, molecules).

What the model leaves out of the simulator's effects, by design: ADC rounding (the continuous
density is used for whole-ADU counts) and saturation (a ROI with a saturated pixel is rejected
with an error: its likelihood would need censoring). Clock-induced charge is added to the
expected photoelectrons, which is exact for the Poisson-Gamma law.

Modules: ``core`` (``Model``), ``camera`` (a scene's camera law and the default tier),
``prior`` (the prior table as a density, and draws from it), ``screen`` (which ROIs a camera
could have recorded).
"""

from bayespsf._validate import saturation_plateau
from bayespsf.model.camera import DEFAULT_TIER, camera_from_scene
from bayespsf.model.core import LOG_PARAMETERS, MIN_ROI, Model
from bayespsf.model.prior import PriorTerms
from bayespsf.psf import PARAMETER_NAMES

__all__ = [
    "DEFAULT_TIER",
    "LOG_PARAMETERS",
    "MIN_ROI",
    "PARAMETER_NAMES",
    "Model",
    "PriorTerms",
    "camera_from_scene",
    "saturation_plateau",
]
