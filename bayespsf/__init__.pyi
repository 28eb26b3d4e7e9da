# The public API of bayespsf, grouped by data-flow stage (imported lazily by __init__.py).
# The order is the data flow's, not the alphabet's (ruff's import sorting is off for this file).

# declare an experiment
from .scene import Scene, SceneError, load_scene, shipped_scenes

# simulate it
from .simulation import simulate, simulate_movie

# the model: spot, camera law, prior
from .psf import PARAMETER_NAMES
from .model import Model

# estimate and sample one ROI
from .inference import Posterior, fit_lsq, fit_mle, sample_posterior

# many ROIs
from .parallel import sample_many

# movies: molecules, camera, per-molecule results
from .movie import find_molecules, read_movie
from .calibration import calibrate_camera
from .analysis import analyze

# files
from .io import read_rois

# subpackages, by stage
from . import (
    psf,
    cameras,
    scene,
    simulation,
    theory,
    inference,
    parallel,
    io,
    movie,
    calibration,
    axial,
    analysis,
)

__all__ = [
    "PARAMETER_NAMES",
    "Model",
    "Posterior",
    "Scene",
    "SceneError",
    "analysis",
    "analyze",
    "axial",
    "calibrate_camera",
    "calibration",
    "cameras",
    "find_molecules",
    "fit_lsq",
    "fit_mle",
    "inference",
    "io",
    "load_scene",
    "movie",
    "parallel",
    "psf",
    "read_movie",
    "read_rois",
    "sample_many",
    "sample_posterior",
    "scene",
    "shipped_scenes",
    "simulate",
    "simulate_movie",
    "simulation",
    "theory",
]
