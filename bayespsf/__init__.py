"""bayespsf: Bayesian analysis of single fluorescent molecule images."""

from bayespsf import cameras, psf, scenes, simulator, theory
from bayespsf.batch import sample_many
from bayespsf.estimators import fit_lsq, fit_mle
from bayespsf.model import Model
from bayespsf.posterior import Posterior
from bayespsf.psf import PARAMETER_NAMES
from bayespsf.sampling import sample_posterior
from bayespsf.scene import Scene, SceneError
from bayespsf.simulator import simulate

__all__ = [
    "PARAMETER_NAMES",
    "Model",
    "Posterior",
    "Scene",
    "SceneError",
    "cameras",
    "fit_lsq",
    "fit_mle",
    "psf",
    "sample_many",
    "sample_posterior",
    "scenes",
    "simulate",
    "simulator",
    "theory",
]
__version__ = "0.1.0"
