"""bayespsf: Bayesian analysis of single fluorescent molecule images."""

from bayespsf import cameras, psf, scenes, simulator, theory
from bayespsf.estimators import fit_lsq, fit_mle
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.scene import Scene, SceneError
from bayespsf.simulator import simulate

__all__ = [
    "PARAMETER_NAMES",
    "Model",
    "Scene",
    "SceneError",
    "cameras",
    "fit_lsq",
    "fit_mle",
    "psf",
    "scenes",
    "simulate",
    "simulator",
    "theory",
]
__version__ = "0.1.0"
