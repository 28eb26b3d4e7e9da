"""Counts and a ``Model`` to estimates and posteriors, for one ROI or a block of ROIs.

Point estimates: ``fit_lsq`` (the paper's least squares), ``fit_mle`` (maximum likelihood with
the Cramér–Rao bound), ``fit_laplace``. Posteriors: ``sample_posterior`` (Laplace, importance
sampling or an emcee chain, chosen by their diagnostics), returned as a ``Posterior``;
``joint_posterior`` pools one molecule's frames. Model checks: ``bootstrap_check``.
"""

from bayespsf.inference.estimators import (
    covariance,
    fit_laplace,
    fit_mle,
    fit_screened,
    start_values,
)
from bayespsf.inference.gof import bootstrap_check
from bayespsf.inference.joint import JointPosterior, joint_posterior
from bayespsf.inference.lsq import fit_lsq
from bayespsf.inference.posterior import Posterior
from bayespsf.inference.sampling import sample_posterior
from bayespsf.inference.settings import Settings

__all__ = [
    "JointPosterior",
    "Posterior",
    "Settings",
    "bootstrap_check",
    "covariance",
    "fit_laplace",
    "fit_lsq",
    "fit_mle",
    "fit_screened",
    "joint_posterior",
    "sample_posterior",
    "start_values",
]
