"""The prior table of a scene as a density: the log prior of many parameter vectors in a few
array passes (``PriorTerms``), and independent draws from it (``sample_prior``)."""

from __future__ import annotations

import numpy as np

from bayespsf.psf import PARAMETER_NAMES


class PriorTerms:
    """The prior table as arrays, so that the log prior of many walkers is a few array passes.

    Up to a constant: uniform 0, log-uniform ``-log x``, normal ``-(x - mean)^2 / (2 sd^2)``,
    half-normal ``-x^2 / (2 scale^2)``; ``-inf`` outside the support.

    Parameters
    ----------
    prior : dict
        A checked ``[prior]`` table (``Scene.prior``, ``Model.prior``): for each of
        ``PARAMETER_NAMES`` its ``kind`` and that kind's parameters.

    Attributes
    ----------
    low, high : ndarray, shape (6,)
        Each parameter's support (infinite where unbounded).
    centre, scale : ndarray, shape (6,)
        The normal's mean and SD, the half-normal's 0 and scale (0 and 1 elsewhere).
    log_uniform, quadratic : ndarray of int
        The parameters with a ``-log x`` term and with a quadratic term.
    """

    def __init__(self, prior: dict):
        specs = [prior[name] for name in PARAMETER_NAMES]
        kinds = np.array([spec["kind"] for spec in specs])
        self.low, self.high = np.full(6, -np.inf), np.full(6, np.inf)
        self.centre, self.scale = np.zeros(6), np.ones(6)
        for k, spec in enumerate(specs):
            if spec["kind"] in ("uniform", "log-uniform"):
                self.low[k], self.high[k] = spec["low"], spec["high"]
            elif spec["kind"] == "normal":
                self.centre[k], self.scale[k] = spec["mean"], spec["sd"]
            else:
                self.low[k], self.scale[k] = 0.0, spec["scale"]
        self.log_uniform = np.flatnonzero(kinds == "log-uniform")
        self.quadratic = np.flatnonzero((kinds == "normal") | (kinds == "half-normal"))

    def __call__(self, p: np.ndarray) -> np.ndarray:
        inside = np.all((p >= self.low) & (p <= self.high), axis=-1)
        total = np.zeros(p.shape[:-1])
        if self.log_uniform.size:
            safe = np.where(inside[..., None], p[..., self.log_uniform], 1.0)
            total -= np.log(safe).sum(axis=-1)
        if self.quadratic.size:
            q = self.quadratic
            with np.errstate(over="ignore"):  # beyond ~1e154 scales: density 0, log -inf
                total -= 0.5 * (((p[..., q] - self.centre[q]) / self.scale[q]) ** 2).sum(axis=-1)
        return np.where(inside, total, -np.inf)


def sample_prior(prior: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` parameter vectors drawn independently from a prior table (``PriorTerms``' law).

    Parameters
    ----------
    prior : dict
        A checked ``[prior]`` table.
    n : int
        The number of draws (checked by the caller).
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (n, 6)
        ``x0 y0 s_x s_y N b`` per draw.
    """
    return np.column_stack([_draws(prior[name], n, rng) for name in PARAMETER_NAMES])


def _draws(spec: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` independent draws from one parameter's prior."""
    kind = spec["kind"]
    if kind == "uniform":
        return rng.uniform(spec["low"], spec["high"], n)
    if kind == "log-uniform":
        return np.exp(rng.uniform(np.log(spec["low"]), np.log(spec["high"]), n))
    if kind == "normal":
        return rng.normal(spec["mean"], spec["sd"], n)
    return np.abs(rng.normal(0.0, spec["scale"], n))  # half-normal
