"""sCMOS camera: Poisson photoelectrons, per-pixel gain and offset, Gaussian readout noise.

Model (Huang et al., "Video-rate nanoscopy using sCMOS camera-specific single-molecule
localization algorithms", Nat. Methods 10, 653-658 (2013)): every pixel has its own gain ``g``
(ADU per photoelectron, > 0), offset ``o`` (ADU) and readout variance ``v`` (ADU^2, >= 0).
Given ``lam`` expected photoelectrons,

    n ~ Poisson(lam),    counts = o + g n + Normal(0, sqrt(v))    (ADU).

Working in electrons, ``y = (c - o) / g`` and ``s = sqrt(v) / g`` (readout sd in electrons), the
density of the counts in ADU is ``p(c) = q(y) / g`` with

    q(y) = sum_{n >= 0} Pois(n; lam) phi_s(y - n),    phi_s = Normal(0, s) density.

Two likelihood tiers:

``"exact"``
    ``log q(y)`` by a log-space sum over a window of ``n`` (see ``log_mixture``). The
    summand is log-concave in ``n`` (its second difference is ``-log((n+1)/n) - 1/s^2 < 0``), so
    it has one mode; the sum starts at the mode and walks outward in both directions, stopping
    once the geometric bound on the remaining terms (valid by log-concavity) is below ``1e-17``
    of the running total, and in any case after ``12 min(sqrt(n_c + 1), s) + 12`` terms from
    the integer ``n_c`` nearest the mode, where the summand has provably dropped below
    ``exp(-46)`` of its peak. No Python loop runs over pixels (only over window offsets).
    Measured absolute error in ``log p``: <= 4e-11 (a few ulp of ``log p``) against a 30-digit
    mpmath sum, for ``lam`` in [0, 1e5], readout sd in [0.1, 20] e- and counts in
    ``o + g [-50, lam + 50 sqrt(lam) + 50]``.
``"huang"``
    Huang et al.'s approximation: ``y + s^2`` is treated as Poisson with mean ``lam + s^2``
    (continuous in its argument via ``gammaln``), plus the Jacobian ``-log g``. It has no support
    where ``y + s^2 < 0``: ``log p = -inf`` there (no clipping). It is not exactly normalised
    (mass 0.947 at ``lam = 1``, ``s = 1``). Its error shrinks as ``lam`` grows; measured for
    readout sd 1-3 e-, the total-variation distance to the exact law is <= 0.08 at ``lam = 1``,
    0.015 at 10, 1.2e-3 at 100 and 5e-5 at 1000, and within 4 sd of the mean
    ``|log p_huang - log p_exact|`` is <= 1.2e-1 at ``lam = 100`` and 3e-3 at ``lam = 1000``
    (at ``lam <~ 10`` it exceeds 1 near the edge of its support).

Readout-free pixels (``v == 0``): the law is a scaled Poisson on the lattice ``o + g n``. The
likelihood returns ``log Pois(n; lam) - log g`` at lattice points and ``-inf`` off the lattice:
the mass of a lattice point spread over a cell of width ``g`` ADU, i.e. the limit of the density
averaged over that cell as ``v -> 0``, so it is in the same units (per ADU) as the ``v > 0``
densities. A count is on the lattice when ``|y - round(y)| <= 1e-9 (1 + (|c| + |o|) / g)`` and
``round(y) >= 0``. Both tiers use this convention for ``v == 0`` pixels, so for ``g = 1, o = 0``
the law is the ``Photon`` law. Pixels with ``v > 0`` must have a readout
sd of at least ``0.01`` photoelectrons (no physical readout is that quiet; use 0 for an ideal
readout-free pixel). The floor bounds the cost of the exact Fisher information, whose
quadrature step shrinks with the readout sd.

Fisher information about ``lam`` (independent of gain and offset): ``method="exact"`` integrates
``q(y) score(y)^2`` with a trapezoid rule in ``y`` (``fisher_exact``; relative error
~1e-13); ``method="approx"`` is Huang et al.'s ``1 / (lam + s^2)``, a lower bound of the exact
value, which is itself at most the readout-free ``1 / lam``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from bayespsf._checks import finite_array, nonnegative_array
from bayespsf.cameras.base import Camera
from bayespsf.cameras.photon import poisson_log_pmf, poisson_score
from bayespsf.errors import BayespsfInputError

_LIKELIHOODS = ("exact", "huang")
_FISHER_METHODS = ("exact", "approx")
_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_MIN_READOUT_SD = 0.01  # photoelectrons; smaller (but nonzero) readout is rejected
_LATTICE_TOL = 1e-9

# exact likelihood: window walk
_TAIL_TOL = 1e-17  # stop when the bound on the remaining terms is below this share of the sum
_WINDOW_SCALE = 12.0  # hard cap of the walk: 12 min(sqrt(m + 1), s) + 12 terms each side
_WINDOW_PAD = 12.0
_NEWTON_MAX_ITER = 100

# exact Fisher information: trapezoid rule in y
_FISHER_DROP = 34.0  # target log-error of the rule (exp(-34) ~ 2e-15 before prefactors)
_FISHER_POISSON_WIDTH = 10.0  # n in lam -/+ (10 sqrt(lam + 1) + 10): pmf drop > exp(-42)
_FISHER_READOUT_WIDTH = 9.0  # readout padding 9 s: Gaussian drop exp(-40.5)
_FISHER_SEGMENT = 1 << 15  # grid points per segment (memory bound)
_FISHER_CHUNK = 1 << 17  # density evaluations per vectorised call


# --------------------------------------------------------------------------------------------
# The exact law in electron units
# --------------------------------------------------------------------------------------------


def _stirlerr(n: np.ndarray) -> np.ndarray:
    """``log n! - (n + 1/2) log n + n - log sqrt(2 pi)`` for ``n >= 1`` (series above 15)."""
    big = n > 15.0
    nb = np.where(big, n, 16.0)
    inv = 1.0 / nb
    inv2 = inv * inv
    series = inv * (
        1.0 / 12 - inv2 * (1.0 / 360 - inv2 * (1.0 / 1260 - inv2 * (1.0 / 1680 - inv2 / 1188)))
    )
    ns = np.where(big, 1.0, np.maximum(n, 1.0))
    direct = special.gammaln(ns + 1.0) - (ns + 0.5) * np.log(ns) + ns - _LOG_SQRT_2PI
    return np.where(big, series, direct)


def _log_poisson_lattice(n: np.ndarray, lam: np.ndarray, log_lam: np.ndarray) -> np.ndarray:
    """``log Pois(n; lam)`` at integer ``n >= 0`` for ``lam > 0``, accurate for large n and lam.

    Loader's saddle-point form ``-stirlerr(n) - log sqrt(2 pi n) - bd0(n, lam)`` with
    ``bd0 = n log(n / lam) + lam - n`` through ``log1p`` near ``n = lam``: the naive
    ``n log lam - lam - gammaln(n + 1)`` loses ~1e-10 to cancellation at ``n ~ 1e5``.
    """
    pos = n >= 1.0
    ns = np.where(pos, n, 1.0)
    diff = ns - lam
    near = np.abs(diff) < 0.5 * ns
    bd0_near = ns * np.log1p(np.where(near, diff, 0.0) / np.where(near, lam, 1.0)) - diff
    bd0_far = ns * (np.log(ns) - log_lam) - diff
    bd0 = np.where(near, bd0_near, bd0_far)
    value = -_stirlerr(ns) - 0.5 * np.log(ns) - _LOG_SQRT_2PI - bd0
    return np.where(pos, value, -lam)


def _mixture_mode(y: np.ndarray, log_lam: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Mode over real ``n >= 0`` of ``n log lam - gammaln(n + 1) - (y - n)^2 / (2 s^2)``.

    Start from the root with ``digamma(n + 1) ~ log(n + 1/2)`` (a Wright omega function), then
    Newton on the derivative, which is convex and decreasing in ``n``, with ``trigamma(n + 1)``
    replaced by the slightly larger ``1 / (n + 1/2)``: steps are at most Newton's, so after the
    first the iterates approach the root monotonically (contraction <= 0.18 per step). The sum
    only needs the mode to within ~1; iteration stops when every step is below 1e-3.
    """
    s2 = s * s
    z = log_lam - np.log(s2) + (y + 0.5) / s2
    m = np.maximum(s2 * special.wrightomega(z) - 0.5, 0.0)
    for _ in range(_NEWTON_MAX_ITER):
        slope = log_lam - special.digamma(m + 1.0) + (y - m) / s2
        curvature = -1.0 / (m + 0.5) - 1.0 / s2
        new = np.maximum(m - slope / curvature, 0.0)
        done = np.all(np.abs(new - m) < 1e-3)
        m = new
        if done:
            break
    return m


def log_mixture(y: ArrayLike, lam: ArrayLike, s: ArrayLike) -> np.ndarray:
    """``log sum_n Pois(n; lam) phi_s(y - n)``: the exact sCMOS law in electron units.

    Parameters
    ----------
    y : array_like
        Counts in photoelectrons, ``(c - o) / g``.
    lam : array_like
        Expected photoelectrons, ``>= 0``.
    s : array_like
        Readout sd in photoelectrons, ``sqrt(v) / g``, ``> 0``.

    Returns
    -------
    numpy.ndarray
        The log density of ``y`` (per photoelectron), broadcast shape. Unchecked input.

    Notes
    -----
    The summand ``f(n) = log Pois(n; lam) - (y - n)^2 / (2 s^2)`` is log-concave in ``n``. The
    sum is centred on the integer ``n_c`` nearest the mode; terms are built outward by the
    recursion ``log Pois(n + 1) = log Pois(n) + log(lam / (n + 1))`` (no cancellation between
    large ``gammaln`` values) and summed as ``exp(f(n) - f(n_c))``, so nothing overflows. Each
    direction stops once ``t_j r_j / (1 - r_j)`` (``t_j`` the last term, ``r_j`` its ratio to
    the previous one; ratios only shrink, by log-concavity) is below ``1e-17`` of the sum, or
    after ``12 min(sqrt(n_c + 1), s) + 12`` terms, where the summand has dropped below
    ``exp(-46)`` of its peak (its curvature is at least ``1/(n + 1) + 1/s^2``).
    """
    y, lam, s = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (y, lam, s)))
    shape = y.shape
    y, lam, s = y.ravel(), lam.ravel(), s.ravel()
    pos = lam > 0
    lam_safe = np.where(pos, lam, 1.0)
    log_lam = np.log(lam_safe)
    nc = np.where(pos, np.round(_mixture_mode(y, log_lam, s)), 0.0)
    d0 = nc - y
    inv2s2 = 0.5 / (s * s)
    log_centre = (
        np.where(pos, _log_poisson_lattice(nc, lam_safe, log_lam), 0.0)
        - d0 * d0 * inv2s2
        - np.log(s)
        - _LOG_SQRT_2PI
    )
    cap = np.ceil(_WINDOW_SCALE * np.minimum(np.sqrt(nc + 1.0), s) + _WINDOW_PAD)
    kmax = int(cap.max()) if cap.size else 0
    total = np.ones_like(y)
    for direction in (1, -1):
        log_pois = np.zeros_like(y)  # log Pois(nc + direction j) - log Pois(nc)
        previous = np.zeros_like(y)
        for j in range(1, kmax + 1):
            n = nc + direction * j
            if direction == 1:
                log_pois += log_lam - np.log(n)
                gauss = -j * (j + 2.0 * d0) * inv2s2
                live = pos & (j <= cap)
            else:
                log_pois += np.log(np.maximum(n + 1.0, 1.0)) - log_lam
                gauss = -j * (j - 2.0 * d0) * inv2s2
                live = pos & (n >= 0) & (j <= cap)
            log_term = np.where(live, log_pois + gauss, -np.inf)
            term = np.exp(log_term)
            total += term
            step = np.where(live, log_term - np.where(live, previous, 0.0), -1.0)
            previous = log_term
            falling = step < 0
            ratio_log = np.where(falling, step, -1.0)
            tail = np.where(falling, term * np.exp(ratio_log) / -np.expm1(ratio_log), np.inf)
            if np.all(np.where(live, tail, 0.0) <= _TAIL_TOL * total):
                break
    return (log_centre + np.log(total)).reshape(shape)


# --------------------------------------------------------------------------------------------
# Exact Fisher information
# --------------------------------------------------------------------------------------------


def _fisher_step(s: np.ndarray) -> np.ndarray:
    """Trapezoid step in electrons for readout sd ``s``.

    Two error terms of the trapezoid rule for ``q(y) score(y)^2``: the Gaussian peaks (width
    ``s``) alias as ``exp(-2 pi^2 s^2 / h^2)``; the score has poles where ``q`` vanishes, at
    distance ``pi s^2`` from the real axis near half-integers where ``q`` is down by
    ``exp(-1 / (8 s^2))``, giving ``exp(-1 / (8 s^2) - 2 pi^2 s^2 / h)``. Both are set to
    ``exp(-34)``.
    """
    gauss = np.pi * np.sqrt(2.0 / _FISHER_DROP) * s
    room = _FISHER_DROP - 1.0 / (8.0 * s * s)
    pole = np.where(room > 0, 2.0 * np.pi**2 * s * s / np.where(room > 0, room, 1.0), np.inf)
    return np.minimum(gauss, pole)


def fisher_exact(lam: ArrayLike, s: ArrayLike) -> np.ndarray:
    """Exact Fisher information ``E[(d log p / d lam)^2]`` of the sCMOS law, ``s > 0``.

    Parameters
    ----------
    lam : array_like
        Expected photoelectrons, ``>= 0``.
    s : array_like
        Readout sd in photoelectrons, ``> 0``.

    Returns
    -------
    numpy.ndarray
        Per-element Fisher information (per photoelectron^2), broadcast shape. It does not
        depend on the gain or offset.

    Notes
    -----
    ``d q / d lam = q(y - 1) - q(y)``, so the score is ``exp(log q(y - 1) - log q(y)) - 1``
    (``= E[n | y] / lam - 1``) and ``I = integral q(y) score(y)^2 dy``. The integral is a
    trapezoid rule on ``y`` over ``[n_lo - 9 s, n_hi + 1 + 9 s]`` with ``n_lo, n_hi = lam -/+
    (10 sqrt(lam + 1) + 10)``; the step is ``_fisher_step``, rounded to ``1/M`` when below
    2 so that ``y - 1`` is a grid point (one density evaluation per point). The integrand is
    analytic and negligible at both ends, so the rule converges geometrically. Measured relative
    error: <= 2e-13 against adaptive quadrature of a brute-force ``q`` for ``lam`` in [1e-5, 200]
    and ``s`` in [0.1, 20]; ~1e-11 at ``lam = 1e5`` (the accuracy of ``log q`` itself). Cost per
    pixel is ``~(20 sqrt(lam) + 18 s + 20) / h`` density evaluations (``h ~ 0.6 s^2`` for
    ``0.1 < s < 1``, ``0.76 s`` otherwise): ~2 ms for ``lam = 1e3, s = 1.5``, ~40 ms for
    ``lam = 1e3, s = 0.1``, ~0.25 s for ``lam = 1e5, s = 0.1``. At ``lam = 0`` the closed form
    ``exp(1 / s^2) - 1`` is used.
    """
    lam, s = np.broadcast_arrays(np.asarray(lam, dtype=np.float64), np.asarray(s, dtype=np.float64))
    shape = lam.shape
    lam, s = lam.ravel(), s.ravel()
    out = np.empty(lam.shape)
    zero = lam == 0
    with np.errstate(over="ignore"):
        out[zero] = np.expm1(1.0 / (s[zero] * s[zero]))
    todo = np.flatnonzero(~zero)
    if todo.size:
        out[todo] = _fisher_trapezoid(lam[todo], s[todo])
    return out.reshape(shape)


def _fisher_trapezoid(lam: np.ndarray, s: np.ndarray) -> np.ndarray:
    width = _FISHER_POISSON_WIDTH * np.sqrt(lam + 1.0) + _FISHER_POISSON_WIDTH
    pad = _FISHER_READOUT_WIDTH * s
    y_lo = np.maximum(np.floor(lam - width), 0.0) - pad
    y_hi = np.ceil(lam + width) + 1.0 + pad
    h = _fisher_step(s)
    shift = h < 2.0
    m = np.where(shift, np.ceil(1.0 / np.minimum(h, 2.0)), 0.0).astype(np.int64)
    h = np.where(shift, 1.0 / np.maximum(m, 1), h)
    npts = np.ceil((y_hi - y_lo) / h).astype(np.int64) + 1

    # split each pixel's grid into segments; a shifted segment also needs M points below it
    nseg = -(-npts // _FISHER_SEGMENT)
    seg_pix = np.repeat(np.arange(lam.size), nseg)
    first_seg = np.cumsum(nseg) - nseg
    seg_start = (np.arange(seg_pix.size) - np.repeat(first_seg, nseg)) * _FISHER_SEGMENT
    seg_len = np.minimum(npts[seg_pix] - seg_start, _FISHER_SEGMENT)
    seg_shift = shift[seg_pix]
    seg_m = m[seg_pix]
    seg_eval = seg_len + np.where(seg_shift, seg_m, seg_len)

    acc = np.zeros(lam.size)
    cum = np.cumsum(seg_eval)
    a = 0
    while a < seg_pix.size:
        limit = (cum[a - 1] if a else 0) + _FISHER_CHUNK
        b = max(int(np.searchsorted(cum, limit, side="right")), a + 1)
        sl = slice(a, b)
        sp, st, ln, sh, mm, ne = (
            seg_pix[sl],
            seg_start[sl],
            seg_len[sl],
            seg_shift[sl],
            seg_m[sl],
            seg_eval[sl],
        )
        # density evaluations
        e_seg = np.repeat(np.arange(b - a), ne)
        e_off = np.cumsum(ne) - ne
        t = np.arange(e_seg.size) - e_off[e_seg]
        sp_e, st_e, ln_e, sh_e, mm_e = sp[e_seg], st[e_seg], ln[e_seg], sh[e_seg], mm[e_seg]
        index = np.where(sh_e, st_e + t - mm_e, st_e + t % np.maximum(ln_e, 1))
        y = y_lo[sp_e] + index * h[sp_e] - np.where(~sh_e & (t >= ln_e), 1.0, 0.0)
        log_q = log_mixture(y, lam[sp_e], s[sp_e])
        # integrand at the grid points
        i_seg = np.repeat(np.arange(b - a), ln)
        i_loc = np.arange(i_seg.size) - (np.cumsum(ln) - ln)[i_seg]
        base = e_off[i_seg]
        i0 = base + np.where(sh[i_seg], mm[i_seg] + i_loc, i_loc)
        i1 = base + np.where(sh[i_seg], i_loc, ln[i_seg] + i_loc)
        score = np.expm1(log_q[i1] - log_q[i0])
        with np.errstate(divide="ignore"):
            integrand = np.exp(log_q[i0] + 2.0 * np.log(np.abs(score)))
        acc += np.bincount(sp[i_seg], integrand, minlength=lam.size)
        a = b
    return acc * h


# --------------------------------------------------------------------------------------------
# The camera
# --------------------------------------------------------------------------------------------


class SCMOS(Camera):
    """An sCMOS camera with per-pixel gain, offset and readout variance (Huang et al. 2013).

    Parameters
    ----------
    gain_map : array_like
        Gain ``g`` in ADU per photoelectron, ``> 0``.
    offset_map : array_like
        Offset ``o`` in ADU.
    variance_map : array_like
        Readout variance ``v`` in ADU^2, ``>= 0``; where ``v > 0`` the readout sd in electrons
        ``sqrt(v) / g`` must be at least ``0.01``.
    likelihood : {"exact", "huang"}
        ``"exact"``: the Poisson-Gaussian convolution summed in log space; ``"huang"``: the
        shifted-Poisson approximation of Huang et al. (2013). See the module docstring.

    Notes
    -----
    Each map is a scalar or a ``(rows, columns)`` array (a 1-D map is one row) that broadcasts
    against the last two dimensions of ``counts`` / ``expected``; leading dimensions (walkers,
    frames) are batch dimensions. The law of a pixel is

        n ~ Poisson(lam),    counts = o + g n + Normal(0, sqrt(v))    (ADU),

    and ``log_likelihood`` is a density per ADU (``v == 0`` pixels: ``log Pois - log g``
    on the lattice ``o + g n``, ``-inf`` off it).

    References
    ----------
    F. Huang, T. M. P. Hartwich, F. E. Rivera-Molina, Y. Lin, W. C. Duim, J. J. Long,
    P. D. Uchil, J. R. Myers, M. A. Baird, W. Mothes, M. W. Davidson, D. Toomre and J. Bewersdorf,
    "Video-rate nanoscopy using sCMOS camera-specific single-molecule localization algorithms",
    Nat. Methods 10, 653-658 (2013).
    """

    fisher_methods = _FISHER_METHODS

    def __init__(
        self,
        gain_map: ArrayLike,
        offset_map: ArrayLike,
        variance_map: ArrayLike,
        likelihood: str = "exact",
    ) -> None:
        g = _map("gain_map", gain_map)
        o = _map("offset_map", offset_map)
        v = _map("variance_map", variance_map)
        if np.any(g <= 0):
            raise BayespsfInputError(
                f"gain_map must be > 0 ADU per photoelectron; min is {g.min():.6g}"
            )
        if np.any(v < 0):
            raise BayespsfInputError(f"variance_map must be >= 0 ADU^2; min is {v.min():.6g}")
        try:
            shape = np.broadcast_shapes(g.shape, o.shape, v.shape)
        except ValueError as exc:
            raise BayespsfInputError(
                f"gain_map {g.shape}, offset_map {o.shape} and variance_map {v.shape} "
                "do not broadcast against each other"
            ) from exc
        sd, readout = np.broadcast_arrays(np.sqrt(v) / g, v > 0)
        if np.any(readout & (sd < _MIN_READOUT_SD * (1.0 - 1e-12))):
            raise BayespsfInputError(
                "variance_map: readout sd sqrt(v) / g must be 0 or >= "
                f"{_MIN_READOUT_SD:g} photoelectrons; min nonzero is {sd[readout].min():.3g}"
            )
        if likelihood not in _LIKELIHOODS:
            raise BayespsfInputError(
                f"likelihood must be one of {', '.join(_LIKELIHOODS)}; got {likelihood!r}"
            )
        self._g, self._o, self._v = g, o, v
        self._map_shape = shape
        self._likelihood = likelihood
        self._any_readout = bool(np.any(v > 0))
        self._all_readout = bool(np.all(v > 0))

    # ---- parameters --------------------------------------------------------------------------

    @property
    def gain_map(self) -> np.ndarray:
        """Gain in ADU per photoelectron (read-only)."""
        return self._g

    @property
    def offset_map(self) -> np.ndarray:
        """Offset in ADU (read-only)."""
        return self._o

    @property
    def variance_map(self) -> np.ndarray:
        """Readout variance in ADU^2 (read-only)."""
        return self._v

    @property
    def likelihood(self) -> str:
        """``"exact"`` or ``"huang"``."""
        return self._likelihood

    def to_dict(self) -> dict:
        """``{"kind": "scmos", "gain_map", "offset_map", "variance_map", "likelihood"}``.

        Maps are nested lists (a float for a scalar map); ``SCMOS(**{k: d[k] for k in ...})``
        rebuilds the camera.
        """
        return {
            "kind": "scmos",
            "gain_map": self._g.tolist(),
            "offset_map": self._o.tolist(),
            "variance_map": self._v.tolist(),
            "likelihood": self._likelihood,
        }

    def __repr__(self) -> str:
        def show(a: np.ndarray) -> str:
            return repr(float(a)) if a.ndim == 0 else f"<array {a.shape}>"

        return (
            f"SCMOS(gain_map={show(self._g)}, offset_map={show(self._o)}, "
            f"variance_map={show(self._v)}, likelihood={self._likelihood!r})"
        )

    # ---- public API ---------------------------------------------------------------------------

    def fisher_information(self, expected: ArrayLike, method: str = "exact") -> np.ndarray:
        """Per-pixel Fisher information about the expected photoelectrons.

        Parameters
        ----------
        expected : array_like
            Expected photoelectrons (``>= 0``), shape ``(..., rows, columns)`` matching the maps.
        method : {"exact", "approx"}
            ``"exact"``: ``E[(d log p / d lam)^2]`` of the exact law by quadrature (see
            ``fisher_exact``; ``1 / lam`` where ``v == 0``). ``"approx"``: Huang et al.'s
            ``1 / (lam + v / g^2)``, the information of the shifted-Poisson approximation.

        Returns
        -------
        numpy.ndarray
            Fisher information per photoelectron^2, shape of ``expected``. The exact value lies
            between ``1 / (lam + v / g^2)`` (Cramér-Rao bound for the statistic ``counts``,
            whose mean is ``o + g lam`` and variance ``g^2 lam + v``) and ``1 / lam`` (the
            readout only loses information); at ``lam = 0`` it is ``exp(g^2 / v) - 1``.
        """
        if method not in _FISHER_METHODS:
            raise BayespsfInputError(
                f"method must be one of {', '.join(_FISHER_METHODS)}; got {method!r}"
            )
        lam = nonnegative_array("expected", expected)
        if method == "approx":
            self._check_shape("expected", lam.shape)
            lam, s2 = np.broadcast_arrays(lam, self._v / (self._g * self._g))
            with np.errstate(divide="ignore"):
                return 1.0 / (lam + s2)
        return self._fisher_information(lam)

    # ---- unchecked implementations ----------------------------------------------------------

    def _check_counts(self, counts: np.ndarray) -> None:
        self._check_shape("counts/expected", counts.shape)

    def _check_shape(self, name: str, shape: tuple[int, ...]) -> None:
        try:
            ok = np.broadcast_shapes(shape, self._map_shape) == tuple(shape)
        except ValueError:
            ok = False
        if not ok:
            raise BayespsfInputError(
                f"the camera maps (gain_map/offset_map/variance_map, shape {self._map_shape}) "
                f"do not broadcast against the (row, column) dims of {name} with shape "
                f"{tuple(shape)}"
            )

    def _electrons(self, counts: np.ndarray, expected: np.ndarray):
        """Flat broadcast ``c, lam, g, o``, ``y = (c - o) / g`` and ``s = sqrt(v) / g``."""
        c, lam, g, o, v = np.broadcast_arrays(counts, expected, self._g, self._o, self._v)
        c, lam, g, o, v = (a.ravel() for a in (c, lam, g, o, v))
        return c, lam, g, o, (c - o) / g, np.sqrt(v) / g

    def _log_likelihood(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        shape = np.broadcast_shapes(counts.shape, expected.shape)
        c, lam, g, o, y, s = self._electrons(counts, expected)
        out = np.empty(y.shape)
        readout = s > 0
        if self._likelihood == "exact":
            if self._all_readout:
                out[:] = log_mixture(y, lam, s)
            else:
                out[readout] = log_mixture(y[readout], lam[readout], s[readout])
        else:
            yh = y + s * s
            support = yh >= 0
            huang = poisson_log_pmf(np.where(support, yh, 0.0), lam + s * s)
            out[:] = np.where(support, huang, -np.inf)
        if not self._all_readout:
            lattice = ~readout
            out[lattice] = _log_lattice(
                c[lattice], o[lattice], g[lattice], y[lattice], lam[lattice]
            )
        out -= np.log(g)
        return out.reshape(shape)

    def _score(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """Differences of the log-likelihood (base class) where ``v > 0``; on the lattice of
        readout-free pixels the Poisson score ``n / lam - 1`` (``poisson_score``), where
        differences would step onto ``lam = 0``, outside the support of any ``n >= 1``."""
        score = super()._score(counts, expected)
        if self._all_readout:
            return score
        shape = score.shape
        _, lam, _, _, y, s = self._electrons(counts, expected)
        score = score.ravel()  # a fresh array: safe to write into
        lattice = s == 0
        score[lattice] = poisson_score(np.round(y[lattice]), lam[lattice])
        return score.reshape(shape)

    def _sample(self, expected: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        self._check_shape("expected", expected.shape)
        n = rng.poisson(expected)
        counts = self._o + self._g * n
        if self._any_readout:
            counts = counts + np.sqrt(self._v) * rng.standard_normal(expected.shape)
        return np.broadcast_to(counts, expected.shape).astype(np.float64)

    def _variance(self, expected: np.ndarray) -> np.ndarray:
        """``g^2 lam + v`` (ADU^2)."""
        return self._g**2 * expected + self._v

    def photons_per_adu(self):
        return 1.0 / self._g, self._o

    def _fisher_information(self, expected: np.ndarray) -> np.ndarray:
        self._check_shape("expected", expected.shape)
        lam, g, v = np.broadcast_arrays(expected, self._g, self._v)
        s = (np.sqrt(v) / g).ravel()
        lam = lam.ravel()
        out = np.empty(lam.shape)
        readout = s > 0
        out[readout] = fisher_exact(lam[readout], s[readout])
        with np.errstate(divide="ignore"):
            out[~readout] = 1.0 / lam[~readout]
        return out.reshape(expected.shape)

    def _step_information(self, expected: np.ndarray) -> np.ndarray:
        """Huang et al.'s ``1 / (lam + s^2)`` (``s`` the readout SD in photoelectrons), a lower
        bound of the exact information within a few percent beyond a few photoelectrons: the
        exact one costs a quadrature per pixel (~2 ms each), which made every step of the
        stack MLE on sCMOS ROIs take seconds."""
        self._check_shape("expected", expected.shape)
        with np.errstate(divide="ignore"):
            return 1.0 / (expected + self._v / self._g**2)


def _map(name: str, value: ArrayLike) -> np.ndarray:
    arr = finite_array(name, value)
    if arr.ndim > 2:
        raise BayespsfInputError(
            f"{name} must be a scalar or a (rows, columns) array; got shape {arr.shape}"
        )
    arr = arr.copy()
    arr.setflags(write=False)
    return arr


def _log_lattice(c, o, g, y, lam) -> np.ndarray:
    """``log Pois(round(y); lam)`` on the lattice ``c = o + g n`` (``-inf`` off it), v == 0."""
    n = np.round(y)
    tol = _LATTICE_TOL * (1.0 + (np.abs(c) + np.abs(o)) / g)
    on = (np.abs(y - n) <= tol) & (n >= 0)
    pos = lam > 0
    lam_safe = np.where(pos, lam, 1.0)
    n_safe = np.where(on, n, 0.0)
    value = np.where(pos, _log_poisson_lattice(n_safe, lam_safe, np.log(lam_safe)), 0.0)
    value = np.where(pos | (n_safe == 0), value, -np.inf)  # lam == 0: all mass at n = 0
    return np.where(on, value, -np.inf)
