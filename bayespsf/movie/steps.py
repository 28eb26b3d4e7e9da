"""Photobleaching steps of one time trace.

``bleach_steps`` finds the steps with PELT (Killick, Fearnhead & Eckley, J. Am. Stat. Assoc.
107, 1590 (2012)) from ``ruptures`` (Truong, Oudre & Vayatis, Signal Process. 167, 107299
(2020)), each level scored as a Gaussian with its own mean and variance (a trace is noisier
where it is brighter), then places each step inside its frame by the exact least-squares scan
and tests it again against the penalty. The paper kept molecules whose trace shows a single
bleaching step: DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), section "Data
acquisition and selection".
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np
import ruptures as rpt
from ruptures.base import BaseCost

from bayespsf._validate import finite_array
from bayespsf.errors import BayespsfInputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

PENALTY = 4.0  # c of the penalty c * log(n); measured in tests/movie/test_movie_traces.py
MIN_SEGMENT = 3  # frames: a step needs a level on either side
PRIOR_WEIGHT = 2.0  # pseudo-frames at the trace's noise variance in each segment's variance
GRID = 150  # PELT's candidate change points: every frame up to this many, a grid beyond
LIT = 0.1  # a frame holding less than this share of the old level counts at the new level


@dataclass(frozen=True)
class BleachSteps:
    """The steps of one trace.

    Attributes
    ----------
    steps : int
        Number of steps (changes of level) found.
    change_points : tuple of int
        The first frame of each new level.
    levels : tuple of float
        The mean of each level, in the trace's units.
    bleach_frame : int or None
        First frame after the last step when that step goes down (where the signal is gone);
        None when there is no step or the last goes up.
    frames_before : int
        Frames before ``bleach_frame`` (all frames when it is None).
    multiple_steps : bool
        More than one step: several fluorophores (or blinking), excluded by the paper.

    See Also
    --------
    bleach_steps : finds them.
    """

    steps: int
    change_points: tuple[int, ...]
    levels: tuple[float, ...]
    bleach_frame: int | None
    frames_before: int
    multiple_steps: bool


class _GaussianSegments(BaseCost):
    """-2 log-likelihood (up to constants) of a segment of Gaussian values with their own mean
    and variance, ``n log v``, in O(1) by cumulative sums. The variance is regularised by
    ``weight`` pseudo-frames at the trace's noise variance (a conjugate scaled-inverse-χ²
    prior), so that short segments cannot fake a tiny variance."""

    model = "gaussian-mean-variance"

    def __init__(self, noise_variance: float, weight: float, min_size: int):
        self.noise_variance, self.weight, self.min_size = noise_variance, weight, min_size

    def fit(self, signal) -> _GaussianSegments:
        y = np.asarray(signal, dtype=np.float64).ravel()
        self.signal = y[:, None]  # ruptures reads the length from it
        self._sum = np.concatenate([[0.0], np.cumsum(y)])
        self._squares = np.concatenate([[0.0], np.cumsum(y * y)])
        return self

    def error(self, start: int, end: int) -> float:
        n = end - start
        s = self._sum[end] - self._sum[start]
        scatter = max(self._squares[end] - self._squares[start] - s * s / n, 0.0)
        v = (scatter + self.weight * self.noise_variance) / (n + self.weight)
        return n * float(np.log(v))


def bleach_steps(
    trace: ArrayLike,
    *,
    frames: ArrayLike | None = None,
    penalty: float = PENALTY,
    min_size: int = MIN_SEGMENT,
) -> BleachSteps:
    """Photobleaching steps of one molecule's trace.

    Parameters
    ----------
    trace : array_like, shape (n,)
        Photons per frame of one molecule, in frame order: ``molecules_over_time`` gives
        ``traces(...)["photons_psf"]``, the PSF-weighted photons, whose noise is the least
        where the background dominates.
    frames : array_like of int, shape (n,), optional
        The frame number of each value (default ``0..n-1``).
    penalty : float, default ``PENALTY`` (4.0)
        ``c`` of the penalty ``c * log(n)`` charged per step.
    min_size : int, default ``MIN_SEGMENT`` (3)
        Fewest frames of a level (but the last, after a step within the last ``min_size -
        1`` frames).

    Returns
    -------
    BleachSteps
        The number of steps, their change points (frame numbers), the levels' means (the
        trace's units), the bleaching frame and the frames before it.

    Raises
    ------
    BayespsfInputError
        A trace that is not 1-D and finite, or ``frames`` of another shape.

    See Also
    --------
    molecules_over_time : every molecule's trace and steps.
    select : the ``single_step`` rule.

    Notes
    -----
    PELT (Killick et al. 2012, through ``ruptures``) minimises the sum of the levels' costs
    plus ``c * log(n)`` per step. A level's cost is ``n_k log v_k``, -2 log-likelihood of a
    Gaussian with its own mean and variance: the trace's noise grows with its signal (shot
    noise and EM excess noise), so a single noise variance would invent steps in the bright
    part or miss them in the dark. Each ``v_k`` is regularised toward the trace's noise
    variance (``1.4826 MAD`` of the first differences over ``sqrt(2)``) by two pseudo-frames.
    The penalty is thus in units of -2 log-likelihood: BIC charges each step its three
    parameters (a mean, a variance, a location) ``3 log n``; the default ``c = 4`` keeps the
    false-step rate on constant traces at 0.1–0.3% (docs/movies.md). Each step is
    then placed by the exact least-squares scan (a Gaussian likelihood with one variance)
    over the frames between its neighbours, with the step inside a frame: a fluorophore
    that bleaches at time ``T`` holds the fraction ``T - floor(T)`` of frame ``floor(T)``'s
    exposure, so that frame is fitted between the two levels, and the change point is the
    first frame at the new level, ``ceil(T)``, the frame ``bayespsf``'s movies call the
    bleach frame (a frame holding less than a tenth of the old level, ``LIT``, counts at the
    new one). Placing every frame's share at the nearer level instead would report
    ``floor(T)`` whenever less than half of that frame is lit (half the time), one frame
    early, and a dim step's noise then adds a second. The placed steps are tested again
    against the penalty, and those that do not pay it (or leave a level shorter than
    ``min_size``) are dropped, until every step reported pays it where it is reported.
    Last, a step within the last ``min_size - 1`` frames (a molecule that bleaches as the
    movie ends, which PELT's levels cannot hold) is added when it pays the penalty.

    References
    ----------
    .. [1] R. Killick, P. Fearnhead and I. A. Eckley, J. Am. Stat. Assoc. 107, 1590 (2012).
    .. [2] C. Truong, L. Oudre and N. Vayatis, Signal Process. 167, 107299 (2020).

    Examples
    --------
    >>> import numpy as np
    >>> from bayespsf.movie import bleach_steps
    >>> rng = np.random.default_rng(0)
    >>> trace = np.r_[np.full(60, 1000.0), np.full(40, 5.0)] + rng.normal(0, 30, 100)
    >>> found = bleach_steps(trace)
    >>> found.steps, found.bleach_frame, found.frames_before
    (1, 60, 60)
    """
    y = finite_array("trace", trace)
    if y.ndim != 1:
        raise BayespsfInputError(f"trace must be one-dimensional, got shape {y.shape}")
    n = len(y)
    at = np.arange(n) if frames is None else np.asarray(frames)
    if at.shape != y.shape:
        raise BayespsfInputError(f"frames must have one entry per value ({n}), got {at.shape}")
    cuts: list[int] = []
    if n >= 2 * min_size:
        d = np.diff(y)
        noise = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)
        floor = 1e-12 * max(float(np.mean(y * y)), 1.0)
        cost = _GaussianSegments(max(noise**2, floor), PRIOR_WEIGHT, min_size)
        jump = max(1, n // GRID)
        pelt = rpt.Pelt(custom_cost=cost, min_size=min_size, jump=jump).fit(y - np.median(y))
        pen = penalty * np.log(n)
        cuts = pelt.predict(pen=pen)[:-1]
        while True:  # each pass drops a point or ends: at most len(cuts) + 1 passes
            cuts = _place(y, cuts)
            kept = _eliminate(cost, cuts, pen, min_size)
            if kept == cuts:
                break
            cuts = kept
        cuts = _at_the_end(cost, cuts, pen, min_size)
    bounds = [0, *cuts, n]
    levels = tuple(float(y[lo:hi].mean()) for lo, hi in pairwise(bounds))
    bleach = cuts[-1] if cuts and levels[-1] < levels[-2] else None
    return BleachSteps(
        steps=len(cuts),
        change_points=tuple(int(at[k]) for k in cuts),
        levels=levels,
        bleach_frame=None if bleach is None else int(at[bleach]),
        frames_before=n if bleach is None else bleach,
        multiple_steps=len(cuts) > 1,
    )


def _place(y: np.ndarray, cuts: list[int]) -> list[int]:
    """Each change point placed by least squares over the span between its neighbours, with
    the step inside a frame: frame ``k`` holds a fraction ``f`` of its exposure at the old level
    and the rest at the new one. For each ``k``, the levels are the means of the frames before
    and after it, and ``f`` takes the value that fits frame ``k`` (its residual is zero when
    the frame lies between the levels, the distance to the nearer level otherwise); the best
    ``k`` minimises ``SSE(lo:k) + SSE(k+1:hi) + residual²``, exactly, by cumulative sums. The
    change point is the first frame at the new level: ``k + 1`` when ``f > LIT``, else ``k``
    (a frame lit for less than a tenth of its exposure counts as dark, so that a step at a
    frame's edge, ``f`` = 0 within its noise, is not reported one frame late half the
    time)."""
    z = y - y.mean()
    s = np.concatenate([[0.0], np.cumsum(z)])
    q = np.concatenate([[0.0], np.cumsum(z * z)])

    def fit(lo, hi):
        m = hi - lo
        return q[hi] - q[lo] - (s[hi] - s[lo]) ** 2 / m, (s[hi] - s[lo]) / m

    cuts = list(cuts)
    for i in range(len(cuts)):
        lo = cuts[i - 1] if i else 0
        hi = cuts[i + 1] if i + 1 < len(cuts) else len(y)
        k = np.arange(lo + 1, hi - 1)  # at least one frame at each level
        if not len(k):
            continue
        (sse_old, old), (sse_new, new) = fit(lo, k), fit(k + 1, hi)
        outside = np.clip(np.abs(z[k] - (old + new) / 2) - np.abs(old - new) / 2, 0.0, None)
        best = int(np.argmin(sse_old + sse_new + outside**2))
        f = (z[k[best]] - new[best]) / (old[best] - new[best]) if old[best] != new[best] else 0.0
        cuts[i] = int(k[best]) + (1 if f > LIT else 0)
    return cuts


def _eliminate(cost: _GaussianSegments, cuts: list[int], pen: float, min_size: int) -> list:
    """Drop, one at a time, the change point whose removal lowers the penalised cost most, until
    none does; first, among those that leave a level shorter than ``min_size``, the one whose
    removal costs least. PELT on a grid of frames can place two points around a step that
    falls between grid points, and placing a step inside its frame (``_place``) moves points
    that PELT scored elsewhere: every step kept pays its penalty where it is reported."""
    cuts = list(cuts)
    while cuts:
        b = [0, *cuts, len(cost.signal)]
        gain = np.array(
            [
                cost.error(b[i], b[i + 2])
                - cost.error(b[i], b[i + 1])
                - cost.error(b[i + 1], b[i + 2])
                - pen
                for i in range(len(cuts))
            ]
        )
        short = np.array(
            [min(b[i + 1] - b[i], b[i + 2] - b[i + 1]) < min_size for i in range(len(cuts))]
        )
        worst = (
            int(np.argmin(np.where(short, gain, np.inf))) if short.any() else int(np.argmin(gain))
        )
        if not short[worst] and gain[worst] >= 0:
            break
        del cuts[worst]
    return cuts


def _at_the_end(cost: _GaussianSegments, cuts: list[int], pen: float, min_size: int) -> list:
    """A step within the trace's last ``min_size - 1`` frames (a molecule that bleaches as the
    movie ends), which PELT cannot place: the best such split of the last level, kept when it
    pays the penalty as any step does, and when the level before it keeps ``min_size``
    frames."""
    n = len(cost.signal)
    lo = cuts[-1] if cuts else 0
    ends = np.arange(max(lo + min_size, n - min_size + 1), n)
    if not len(ends):
        return cuts
    gain = [cost.error(lo, n) - cost.error(lo, k) - cost.error(k, n) - pen for k in ends]
    best = int(np.argmax(gain))
    return [*cuts, int(ends[best])] if gain[best] > 0 else cuts


__all__ = ["PENALTY", "BleachSteps", "bleach_steps"]
