"""bayespsf: Bayesian analysis of single fluorescent molecule images.

The public names below are imported on first use (PEP 562), so that ``bayespsf --help`` and
``import bayespsf.cli`` do not load NumPy, SciPy, ArviZ and numba (seconds) before they are
needed.
"""

import importlib

_NAMES = {
    "PARAMETER_NAMES": "bayespsf.psf",
    "Model": "bayespsf.model",
    "Posterior": "bayespsf.posterior",
    "Scene": "bayespsf.scene",
    "SceneError": "bayespsf.scene",
    "analyze": "bayespsf.analysis.pipeline",
    "fit_lsq": "bayespsf.estimators",
    "fit_mle": "bayespsf.estimators",
    "sample_many": "bayespsf.batch",
    "sample_posterior": "bayespsf.sampling",
    "simulate": "bayespsf.simulator",
}
_MODULES = ("cameras", "psf", "scenes", "simulator", "theory")

__all__ = sorted([*_NAMES, *_MODULES])
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(_NAMES[name]), name)
    elif name in _MODULES:
        value = importlib.import_module(f"bayespsf.{name}")
    else:
        raise AttributeError(f"module 'bayespsf' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted([*globals(), *__all__])
