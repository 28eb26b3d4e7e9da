"""The sampler's settings, checked by name before any work (a NaN, infinite, zero or negative
``ess`` or budget would never end or never start a run)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bayespsf.errors import BayespsfInputError


@dataclass(frozen=True)
class Settings:
    """Sampler settings (stored in every result file)."""

    seed: int = 0
    walkers: int = 32
    ess: float = 400.0
    chunk: int = 50  # first (and smallest) chunk of steps between convergence checks
    max_steps: int = 50_000
    min_taus: float = 50.0
    moves: str = "laplace-de"  # see MOVES and _moves
    method: str = "mcmc"  # or "auto", "laplace", "importance" (bayespsf.stack_posterior)
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
    seed=0, walkers=32, ess=400.0, max_steps=50_000, moves="laplace-de", method="mcmc",
    max_seconds=None,
) -> Settings:  # fmt: skip
    """The sampler's settings, each checked (``BayespsfInputError`` naming the argument and its
    allowed range): a NaN, infinite, zero or negative ``ess`` or budget would never end or
    never start a run."""
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
