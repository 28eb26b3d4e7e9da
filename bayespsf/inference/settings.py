"""The sampler's settings, checked by name before any work (a NaN, infinite, zero or negative
``ess`` or budget would never end or never start a run, and an ensemble too large for the
machine's memory would end in NumPy's ``MemoryError``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bayespsf._runtime import refuse_beyond_memory
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
# a chain's most pixel evaluations (max_steps x walkers x roi^2) without a wall-clock budget:
# at 20-40 ns each (measured: photon and EMCCD table tiers) half an hour to an hour per ROI
MAX_CHAIN_WORK = 1e11


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


def check_model(model) -> None:
    """Refuse anything but a ``bayespsf.Model`` as ``model`` (a clear error, not an
    ``AttributeError`` from the first use).

    Parameters
    ----------
    model : object
        What was given as the model.

    Raises
    ------
    BayespsfInputError
        If ``model`` is not a ``Model``.
    """
    from bayespsf.model import Model

    if not isinstance(model, Model):
        raise BayespsfInputError(
            "model must be a bayespsf.Model (Model.from_scene(scene), or Model(roi, "
            f"pixel_size, camera)); got {type(model).__name__} {model!r:.60}"
        )


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


def check_walkers_fit(walkers: int, roi: int, chunk: int = Settings.chunk) -> None:
    """Refuse an ensemble whose chain cannot be held in memory, before any work.

    Parameters
    ----------
    walkers : int
        The ensemble size (checked by ``check_settings``).
    roi : int
        The ROI side in pixels.
    chunk : int
        Steps of the chain's first chunk.

    Raises
    ------
    BayespsfInputError
        Naming ``walkers``: every step scores all walkers in one vectorised call, which holds
        several arrays of ``walkers x roi x roi`` values (at least four: the expected image,
        the camera law's terms), and the chain keeps ``chunk`` steps of ``walkers x 7``.
    """
    needed = 8.0 * walkers * (4 * roi * roi + 7 * chunk)
    refuse_beyond_memory(
        needed,
        f"walkers = {walkers} on {roi} x {roi} ROIs",
        "use fewer walkers (the default, 32, is enough for six parameters; more walkers do not "
        "make a posterior more exact, a longer chain or a higher ess does)",
    )


def check_chain_work(settings: Settings, roi: int) -> None:
    """Refuse, before it starts, a chain that may run for hours on large ROIs without a budget.

    Parameters
    ----------
    settings : Settings
        The run's settings (``walkers``, ``max_steps``, ``max_seconds``).
    roi : int
        The ROI side in pixels.

    Raises
    ------
    BayespsfInputError
        Where ``max_seconds`` is not given and ``max_steps x walkers x roi^2`` exceeds
        ``MAX_CHAIN_WORK`` (1e11 pixel evaluations): every step scores every walker on every
        pixel, so a 401 x 401 ROI costs 0.1-0.2 s per step and a chain that does not converge
        runs its 50 000 steps for 2-3 hours. The message names ``max_seconds`` and the
        ``max_steps`` that fits the bound. The default settings pass up to 249 x 249 ROIs.
    """
    work = float(settings.max_steps) * settings.walkers * roi * roi
    if settings.max_seconds is None and work > MAX_CHAIN_WORK:
        fits = int(MAX_CHAIN_WORK // (settings.walkers * roi * roi))
        raise BayespsfInputError(
            f"a chain on {roi} x {roi} ROIs may run max_steps = {settings.max_steps} steps of "
            f"walkers = {settings.walkers}: {work:.2g} pixel evaluations, about "
            f"{work * 3e-8 / 3600:.2g} hours per ROI at 30 ns each, with no wall-clock budget; "
            "give max_seconds (--max-seconds on the command line), a budget per ROI, or "
            f"max_steps <= {fits} (or use smaller ROIs)"
        )


__all__ = [
    "MAX_CHAIN_WORK",
    "MAX_ESS",
    "METHODS",
    "MOVES",
    "Settings",
    "check_chain_work",
    "check_model",
    "check_settings",
    "check_walkers_fit",
]
