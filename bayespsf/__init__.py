"""bayespsf: Bayesian analysis of single fluorescent molecule images."""

from bayespsf import cameras, psf
from bayespsf.psf import PARAMETER_NAMES

__all__ = ["PARAMETER_NAMES", "cameras", "psf"]
__version__ = "0.1.0"
