"""Candidates from a score map: local maxima above a threshold, refined to sub-pixel positions,
and the rejections that keep each molecule's ROI inside the image and its windows clear of its
neighbours' light (``crowded``; ``bayespsf.movie.geometry`` states the light)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage, spatial, special

from bayespsf.movie.geometry import ring_masks, window_light

STATUSES = ("accepted", "rejected: edge", "rejected: neighbour")
NEIGHBOUR_SDS = 1.0  # a neighbour's light allowed in a window, in SDs of its summed noise


def find_peaks(score: np.ndarray, threshold: float, roi: int, min_distance: float | None):
    """``(rows, cols, status, dy, dx)`` of the local maxima (3 × 3) of ``score`` above
    ``threshold``, in image order: ``rejected: edge`` where a ``roi`` × ``roi`` cut centred on
    the peak would cross the image's edge, else (unless ``min_distance`` is None) ``rejected:
    neighbour`` where another peak is closer than ``min_distance`` in rows or in columns, else
    ``accepted``."""
    peak = score == ndimage.maximum_filter(score, size=3, mode="constant", cval=-np.inf)
    rows, cols = np.nonzero(peak & (score > threshold))
    status = np.full(rows.size, STATUSES[0], dtype=object)
    if min_distance is not None:
        status[_near(rows, cols, min_distance)] = STATUSES[2]
    h = roi // 2
    height, width = score.shape
    edge = (rows < h) | (cols < h) | (rows >= height - h) | (cols >= width - h)
    status[edge] = STATUSES[1]
    return (rows, cols, status, *_subpixel(score, rows, cols))


def crowded(peaks, amplitude, variance, noise_var, s: float, roi: int, fit: int, least: int):
    """Where a neighbour's light costs a candidate its place (``rejected: neighbour``).

    ``peaks`` is ``(rows, cols, status, dy, dx)`` (``find_peaks``); only candidates not at
    the edge are judged, every candidate is a source of light. Candidate ``i`` is crowded when

    1. another candidate ``j`` puts more than ``NEIGHBOUR_SDS`` (1) SD of the summed noise of
       ``i``'s ``fit`` x ``fit`` window into it: ``window_light(A_j) > sqrt(Σ var_i)``, the
       pixels' variances with ``i``'s own spot on them (``variance``: ``spot_variance``),
       ``A`` the matched filter's amplitudes; or
    2. the periphery left once the pixels that the neighbours' light reaches are masked out
       (``geometry.ring_masks``, bound ``sqrt(n v_i)`` over the ring's ``n`` pixels at
       ``noise_var`` ``v_i``) holds fewer than ``least`` pixels (``min_periphery``).

    The rule holds whoever is brighter: a faint neighbour that barely touches a bright spot's
    window puts little light into it and leaves it, a bright one takes a faint spot's place,
    and of two spots that overlap both go.
    """
    rows, cols, status, dy, dx = peaks
    judged = np.flatnonzero(status != STATUSES[1])
    out = np.zeros(rows.size, dtype=bool)
    if rows.size < 2 or not judged.size:
        return out
    amplitude = np.maximum(np.asarray(amplitude, dtype=np.float64), 0.0)
    y, x = rows + dy, cols + dx
    h = fit // 2
    offsets = np.arange(-h, h + 1)
    win_r, win_c = rows[judged, None] + offsets, cols[judged, None] + offsets

    def fractions(delta):  # the spot's share per pixel of the window, along one axis
        edges = (offsets[None, :] - delta[:, None])[..., None] + np.array([-0.5, 0.5])
        return np.diff(special.ndtr(edges / s), axis=-1)[..., 0]

    own = amplitude[judged, None, None] * fractions(dy[judged])[:, :, None]
    own = own * fractions(dx[judged])[:, None, :]
    bound = np.full(rows.size, np.inf)
    bound[judged] = NEIGHBOUR_SDS * np.sqrt(variance(win_r, win_c, own).sum(axis=(1, 2)))
    ring = np.sqrt((roi * roi - fit * fit) * np.broadcast_to(noise_var, rows.shape))
    least_bound = max(min(ring.min() if roi > fit else np.inf, bound[judged].min()), 1e-300)
    reach = roi // 2 + 2.0 + s * np.sqrt(2.0 * np.log(max(amplitude.max() / least_bound, 1.0)))
    tree = spatial.cKDTree(np.column_stack([rows, cols]))
    pairs = tree.query_pairs(reach, p=np.inf, output_type="ndarray")
    i, j = np.concatenate([pairs, pairs[:, ::-1]]).T
    light = window_light(amplitude[j], y[j], x[j], rows[i], cols[i], s, fit)
    np.logical_or.at(out, i, light > bound[i])
    if roi > fit:
        left = judged[~out[judged]]
        kept = ring_masks(rows[left], cols[left], left, y, x, amplitude, ring[left], s, roi, fit)
        out[left] |= kept.sum(axis=(1, 2)) < least
    return out


def _near(rows: np.ndarray, cols: np.ndarray, distance: float) -> np.ndarray:
    """Indices of the points closer than ``distance`` (Chebyshev) to another point."""
    if rows.size < 2 or distance <= 0:
        return np.zeros(0, dtype=int)
    pairs = spatial.cKDTree(np.column_stack([rows, cols])).query_pairs(
        np.nextafter(distance, 0), p=np.inf, output_type="ndarray"
    )
    return np.unique(pairs)


def _subpixel(score: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """Offsets (dy, dx) in (-0.5, 0.5) of the score's peak from the peak pixel: a Gaussian
    (parabola through log T) through the peak and its two neighbours along each axis, a
    parabola through T where a neighbour is not positive, 0 at the image's edge."""
    padded = np.pad(score, 1, mode="constant", constant_values=np.nan)
    r, c = rows + 1, cols + 1
    offsets = []
    for minus, plus in (((r - 1, c), (r + 1, c)), ((r, c - 1), (r, c + 1))):
        low, mid, high = padded[minus], padded[r, c], padded[plus]
        positive = (low > 0) & (mid > 0) & (high > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            fl, fm, fh = (np.log(np.where(positive, v, 1.0)) for v in (low, mid, high))
            fl, fm, fh = (np.where(positive, f, v) for f, v in ((fl, low), (fm, mid), (fh, high)))
            delta = (fl - fh) / (2.0 * (fl - 2.0 * fm + fh))
        offsets.append(np.clip(np.nan_to_num(delta), -0.499, 0.499))
    return offsets[0], offsets[1]


ELONGATION_CHI2 = float(-2.0 * np.log(1e-3))  # chi-square (2 d.o.f.) with tail 0.001: 13.8
CENTRE_STEPS = 8  # fixed-point steps of the spot's centre (each at least halves its error)


def saturated_near(mask, rows: np.ndarray, cols: np.ndarray, half: int) -> np.ndarray:
    """The number of pixels of ``mask`` (saturated in some frame) within ``half`` pixels (in
    rows and in columns) of each peak; zeros where there is no mask."""
    if mask is None or not rows.size:
        return np.zeros(rows.size, dtype=np.int64)
    counts = ndimage.uniform_filter(mask.astype(np.float64), 2 * half + 1, mode="constant")
    return np.rint(counts[rows, cols] * (2 * half + 1) ** 2).astype(np.int64)


def elongation(residual, variance, rows, cols, dy, dx, psf_sd: float, pixel_size: float):
    """``(elongation, elongated)`` of each peak, from the second moments of its spot.

    In a square window of half-side ``h = max(1, round(3 psf_sd / a))`` pixels around the peak
    pixel, with ``X``, ``Y`` the pixel offsets from the spot's centre, ``r`` the
    background-removed photons and ``m`` the pixel-integrated template at that centre, two
    anisotropy components ``e = Σ r w (q - q̄)``, for ``q = X² - Y²`` and ``q = 2 X Y`` with
    ``q̄ = Σ m w q / Σ m w``, vanish in expectation for one round spot, of the template's
    width or not (``q̄`` removes the window's own asymmetry about the centre). With
    ``w = m / var`` they are the locally most powerful statistics for an elliptical spot
    against a round one (the derivatives of the Gaussian by its anisotropy are ``m`` times
    ``X² - Y²`` and ``X Y``); ``var`` is each pixel's variance with the spot on it
    (``variance``: a callable of the window and the spot's photons, ``spot_variance``). They
    are linear in the pixels, so their covariance is ``C = Σ var w² (q - q̄)(q' - q̄')``, and
    ``elongated`` where ``e' C⁻¹ e > ELONGATION_CHI2`` (13.8: a round spot is flagged with
    probability 0.001). The centre is where ``Σ r w X`` and ``Σ r w Y`` vanish, reached from
    the score's sub-pixel peak by ``CENTRE_STEPS`` fixed-point steps: a centre off by ``δ``
    biases ``e`` by about ``δ²`` times the flux, which would flag every bright spot.
    ``elongation``: the ratio of major to minor SD of the unweighted (``w = 1``) moments,
    ``sqrt((σ² + A/2) / (σ² - A/2))``, ``A = |e| / Σ r`` and ``σ²`` the template's own second
    moment in the window; two equal spots ``d`` pixels apart give ``A ≈ d²/4``. NaN and False
    where the window leaves the image or holds no photons.
    """
    from bayespsf import psf

    a = float(pixel_size)
    h = max(1, round(3.0 * psf_sd / a))
    height, width = residual.shape
    ratio = np.full(rows.size, np.nan)
    flagged = np.zeros(rows.size, dtype=bool)
    k = np.flatnonzero((rows >= h) & (cols >= h) & (rows < height - h) & (cols < width - h))
    if not k.size:
        return ratio, flagged
    offsets = np.arange(-h, h + 1)
    win_r, win_c = rows[k, None] + offsets, cols[k, None] + offsets
    r = residual[win_r[:, :, None], win_c[:, None, :]]
    flux = r.sum(axis=(1, 2))
    good = flux > 0
    sd, zero = np.full(k.size, float(psf_sd)), np.zeros(k.size)

    def spot(cx, cy):  # the template at (cx, cy) and each pixel's variance with the spot
        params = np.column_stack([cx * a, cy * a, sd, sd, np.ones(k.size), zero])
        m = psf.expected_counts(params, 2 * h + 1, a)
        scale = np.maximum(flux / m.sum(axis=(1, 2)), 0.0)[:, None, None]
        return m, variance(win_r, win_c, scale * m)

    cx, cy = dx[k].astype(np.float64), dy[k].astype(np.float64)
    for _ in range(CENTRE_STEPS):  # the centre where the weighted first moments vanish
        m, var = spot(cx, cy)
        w = r * m / var
        total = w.sum(axis=(1, 2))
        ok = good & (total > 0)
        safe = np.where(ok, total, 1.0)
        step_x = (w * (offsets[None, None, :] - cx[:, None, None])).sum(axis=(1, 2)) / safe
        step_y = (w * (offsets[None, :, None] - cy[:, None, None])).sum(axis=(1, 2)) / safe
        cx = np.clip(np.where(ok, cx + step_x, cx), -1.0, 1.0)
        cy = np.clip(np.where(ok, cy + step_y, cy), -1.0, 1.0)
    m, var = spot(cx, cy)
    X = offsets[None, None, :] - cx[:, None, None]
    Y = offsets[None, :, None] - cy[:, None, None]
    qs = [np.broadcast_to(q, m.shape) for q in (X**2 - Y**2, 2.0 * X * Y)]
    e, cov = _anisotropy(r, m, m / var, qs, var)
    good &= np.linalg.det(cov) > 0
    chi2 = np.zeros(k.size)
    solved = np.linalg.solve(cov[good], e[good][..., None])[..., 0]
    chi2[good] = np.einsum("ki,ki->k", e[good], solved)
    flagged[k] = good & (chi2 > ELONGATION_CHI2)
    e, _ = _anisotropy(r, m, np.ones_like(m), qs, var)
    sigma2 = ((m * (X**2 + Y**2)).sum(axis=(1, 2))) / (2.0 * m.sum(axis=(1, 2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.hypot(e[:, 0], e[:, 1]) / flux
        major, minor = sigma2 + spread / 2, sigma2 - spread / 2
        ratio[k] = np.where(good, np.where(minor > 0, np.sqrt(major / minor), np.inf), np.nan)
    return ratio, flagged


def _anisotropy(r, m, w, qs, var):
    """``e = Σ r w (q - q̄)`` (one column per ``q``) with ``q̄ = Σ m w q / Σ m w``, and their
    covariance ``Σ var w² (q - q̄)(q' - q̄')``."""
    axes = (1, 2)
    centred = [q - ((m * w * q).sum(axis=axes) / (m * w).sum(axis=axes))[:, None, None] for q in qs]
    e = np.stack([(r * w * c).sum(axis=axes) for c in centred], axis=-1)
    cov = np.empty((len(r), 2, 2))
    for i, ci in enumerate(centred):
        for j, cj in enumerate(centred):
            cov[:, i, j] = (var * w**2 * ci * cj).sum(axis=axes)
    return e, cov
