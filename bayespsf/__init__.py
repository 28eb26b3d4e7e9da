"""bayespsf: Bayesian analysis of single fluorescent molecule images."""

from bayespsf import cameras, psf, scenes, simulator
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import Scene, SceneError
from bayespsf.simulator import simulate

__all__ = [
    "PARAMETER_NAMES",
    "Scene",
    "SceneError",
    "cameras",
    "psf",
    "scenes",
    "simulate",
    "simulator",
]
__version__ = "0.1.0"
