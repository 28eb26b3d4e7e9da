"""A bead z-stack: the scene's emitter imaged at a series of stage positions z, several frames
per step (the input of ``bayespsf.axial.calibrate``)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError
from bayespsf.scene import Scene
from bayespsf.simulation.pipeline import simulate


def zstack_positions(start: float, step: float, steps: int, frames_per_step: int) -> np.ndarray:
    """The stage z of every frame of a stack: ``steps`` positions ``start + k step``, each
    held for ``frames_per_step`` frames.

    Parameters
    ----------
    start : float
        The first position, nm.
    step : float
        The distance between positions, nm (nonzero; negative steps down).
    steps : int
        Number of positions (>= 1).
    frames_per_step : int
        Frames at each position (>= 1).

    Returns
    -------
    ndarray, shape (steps * frames_per_step,)
        z of each frame in nm.

    Raises
    ------
    BayespsfInputError
        If ``steps`` or ``frames_per_step`` is not a positive integer, ``start`` or ``step`` is
        not finite, or ``step`` is 0.

    See Also
    --------
    simulate_zstack : the frames at these positions.

    Examples
    --------
    >>> from bayespsf.simulation import zstack_positions
    >>> zstack_positions(-200.0, 200.0, steps=3, frames_per_step=2)
    array([-200., -200.,    0.,    0.,  200.,  200.])
    """
    for name, value in (("steps", steps), ("frames_per_step", frames_per_step)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise BayespsfInputError(f"{name} must be a positive integer, got {value!r}")
    start, step = (float(finite_array(n, v)) for n, v in (("start", start), ("step", step)))
    if step == 0:
        raise BayespsfInputError("step must not be 0")
    return np.repeat(start + step * np.arange(steps), frames_per_step)


def simulate_zstack(scene: Scene, z: ArrayLike, seed: int) -> tuple[np.ndarray, pd.DataFrame]:
    """Images of the scene's emitter at each stage position of a bead z-stack.

    Parameters
    ----------
    scene : Scene
        A scene with an ``[axial]`` table; its z law is replaced by each position.
    z : array_like, shape (n,)
        Stage position of each frame, nm (e.g. from ``zstack_positions``).
    seed : int
        Non-negative integer; frame ``i`` depends on ``seed`` and its step only.

    Returns
    -------
    counts : ndarray, shape (n, roi, roi)
        Counts in ADU, in the order of ``z``.
    truth : pandas.DataFrame
        One row per frame: ``x0 y0 s_x s_y N b z`` (nm, photons), as ``simulate`` gives it.

    Raises
    ------
    BayespsfInputError
        If the scene declares no ``[axial]`` table or ``z`` is not finite.

    See Also
    --------
    bayespsf.axial.calibrate : fits the defocus curves to such a stack.

    Examples
    --------
    >>> from bayespsf import load_scene
    >>> from bayespsf.simulation import simulate_zstack, zstack_positions
    >>> z = zstack_positions(-400.0, 200.0, steps=5, frames_per_step=2)
    >>> counts, truth = simulate_zstack(load_scene("astigmatic"), z, seed=1)
    >>> counts.shape, list(truth["z"][:3])
    ((10, 15, 15), [-400.0, -400.0, -200.0])
    """
    if "axial" not in scene.to_dict():
        raise BayespsfInputError("the scene declares no [axial] table: no defocus to image")
    z = finite_array("z", z)
    counts, truths = [], []
    values, first = np.unique(z, return_index=True)
    for k, value in enumerate(values[np.argsort(first)]):
        n = int(np.sum(z == value))
        step_seed = int(np.random.SeedSequence([seed, k]).generate_state(1)[0])
        c, t = simulate(scene.replace(axial={"z": "fixed", "z0": float(value)}), n, step_seed)
        counts.append(c)
        truths.append(t)
    order = np.argsort(np.concatenate([np.flatnonzero(z == v) for v in values[np.argsort(first)]]))
    return np.concatenate(counts)[order], pd.concat(truths, ignore_index=True).iloc[order]


__all__ = ["simulate_zstack", "zstack_positions"]
