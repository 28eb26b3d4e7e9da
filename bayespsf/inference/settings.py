"""The sampler's settings, checked by name before any work (a NaN, infinite, zero or negative
``ess`` or budget would never end or never start a run)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bayespsf.errors import BayespsfInputError


@dataclass(frozen=True)
class Settings:
    """Sampler settings, checked by ``check_settings`` and stored in every result file.

    Attributes
    ----------
    seed : int
        Seeds the walkers' start, the chain and the chain-free methods' draws (0 to 2**64 - 1).
    walkers : int
        Ensemble size of the emcee run (even, >= 12).
    ess : float
        Effective sample size to reach on every parameter (1 to ``MAX_ESS``).
    chunk : int
        First (and smallest) chunk of steps between convergence checks.
    max_steps : int
        Step cap of the chain (>= 1).
    min_taus : float
        Shortest converged chain after burn-in, in autocorrelation times.
    moves : str
        emcee moves, one of ``MOVES`` (``bayespsf.inference.sampling``).
    method : str
        One of ``METHODS``: ``"mcmc"``, or ``"auto"``, ``"laplace"``, ``"importance"``
        (``bayespsf.inference.batched``).
    max_seconds : float or None
        Wall-clock budget of the chain in seconds (None: none).

    See Also
    --------
    check_settings : the settings from arguments, each checked by name.
    """

    seed: int = 0
    walkers: int = 32
    ess: float = 400.0
    chunk: int = 50  # first (and smallest) chunk of steps between convergence checks
    max_steps: int = 50_000
    min_taus: float = 50.0
    moves: str = "laplace-de"  # see MOVES and _moves
    method: str = "mcmc"  # or "auto", "laplace", "importance" (bayespsf.inference.batched)
    max_seconds: float | None = None  # wall-clock budget of the chain (None: none)


MOVES = ("laplace-de", "de-snooker", "stretch")
METHODS = ("mcmc", "auto", "laplace", "importance")
MAX_ESS = 1e7  # an ESS target beyond this is a typo (the chain would need ~1e9 draws)


def _whole(name: str, value, low: int, high: float = math.inf) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise BayespsfInputError(f"{name} must be an integer >= {low}, got {value!r}")
    if not low <= value <= high:
        raise BayespsfInputError(f"{name} must be an integer in [{low}, {high:g}], got {value!r}")
    return int(value)


def _positive(name: str, value, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise BayespsfInputError(f"{name} must be a number in (0, {high:g}], got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and 0 < v <= high):
        raise BayespsfInputError(f"{name} must be a number in (0, {high:g}], got {value!r}")
    return v


def check_settings(
    seed: int = 0,
    walkers: int = 32,
    ess: float = 400.0,
    max_steps: int = 50_000,
    moves: str = "laplace-de",
    method: str = "mcmc",
    max_seconds: float | None = None,
) -> Settings:
    """The sampler's settings, each checked before any work.

    Parameters
    ----------
    seed, walkers, ess, max_steps, moves, method, max_seconds
        As ``Settings``' attributes of the same names.

    Returns
    -------
    Settings
        The settings, as Python numbers; ``chunk`` and ``min_taus`` at their defaults.

    Raises
    ------
    BayespsfInputError
        Naming the argument and its allowed range: a NaN, infinite, zero or negative ``ess``
        or budget would never end or never start a run.
    """
    walkers = _whole("walkers", walkers, 12)
    if walkers % 2:
        raise BayespsfInputError(f"walkers must be an even number >= 12, got {walkers!r}")
    if moves not in MOVES:
        raise BayespsfInputError(f"moves must be one of {', '.join(MOVES)}; got {moves!r}")
    if method not in METHODS:
        raise BayespsfInputError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    if _positive("ess", ess, MAX_ESS) < 1:  # fewer than one effective draw is no posterior
        raise BayespsfInputError(f"ess must be a number in [1, {MAX_ESS:g}], got {ess!r}")
    return Settings(
        seed=_whole("seed", seed, 0, 2**64 - 1),
        walkers=walkers,
        ess=_positive("ess", ess, MAX_ESS),
        max_steps=_whole("max_steps", max_steps, 1),
        moves=moves,
        method=method,
        max_seconds=None if max_seconds is None else _positive("max_seconds", max_seconds, 1e9),
    )


__all__ = ["MAX_ESS", "METHODS", "MOVES", "Settings", "check_settings"]
