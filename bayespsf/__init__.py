"""bayespsf: Bayesian analysis of single fluorescent molecule images.

The public names are declared in ``__init__.pyi`` (grouped by stage, as type checkers and IDEs
read them) and imported on first use, so that ``bayespsf --help`` and ``import bayespsf.cli`` do
not load NumPy, SciPy, ArviZ and numba (seconds) before they are needed.
"""

import lazy_loader as _lazy

__version__ = "0.1.0"

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
