"""The local background and noise under each pixel of a projection or frame, estimated from the
image with the spots left out, and the fixed-pattern noise beyond a camera law.

Background. At each pixel, a quartic surface ``b(u, v) = Σ β_ab u^a v^b`` (``a + b <= 4``, 15
terms) is fitted by least squares to the pixels of a ``size`` × ``size`` window around it,
leaving out the spots: local polynomial regression (Cleveland & Devlin, J. Am. Stat. Assoc. 83
(1988) 596) with a box kernel, computed as a normalized convolution (Knutsson & Westin, Proc.
IEEE CVPR 1993, 515): the masked image and the mask are summed against the window's monomials
and each window's 15 × 15 normal equations are solved. The fit is unbiased for any background
that is a quartic over the window and follows a ramp or an illumination profile to the
image's edges: a window is cut by the image's edge (pixels beyond it are missing), never
reflected. Why a quartic: a mean projection averages the noise away, so a bias of a tenth of
a photon is several SDs of the matched filter's score. Without noise, on 128 × 128 pixels and
a 63-pixel window, a Gaussian illumination of 25 photons over 3 is fitted to within 0.021
photons by the quartic and 0.35 by a quadratic at a profile SD of 45 pixels, and to within
0.15 and 1.3 at 30 pixels; on 256 × 256 and a 75-pixel window (a ramp from 4 to 10 photons
across, or a profile of SD 133 pixels) both are within 0.011. A local mean is biased by the
curvature and, reflected at an edge, by the slope: 0.43 photons at the edges of that ramp.

The price is a little of a faint spot: one that is not left out (below the threshold) is
partly absorbed by the fit, by about ``(Σ g)² H / ||g||²`` of its score, ``H`` the fit's
leverage at the pixel (a few percent at a 63-pixel window; 0.5 % for a local mean), and the
fit's own noise, about twice the quadratic's in variance. Spots above the threshold are left
out and lose nothing.

The spots left out: first none; then, twice, the pixels beyond ``PIXEL_CLIP`` noise SDs of the
previous fit (a spot's bright pixels, which would bend the first fits); then, twice (once where
the second pass finds the first's pixels), those ``background_pixels`` finds from the matched
filter's score against the previous fit: pixels above the threshold, and within the template's
reach (4 SDs) of a local maximum above it.

The fits are solved on a grid of anchor pixels ``size // 8`` apart in rows and columns (every
pixel for a window under 16 pixels) and evaluated at each pixel from its nearest
anchor's surface: the background is smooth on the window's scale, and the sums become sparse
matrix products. Where the kept pixels leave the quartic's value poorly determined (its
variance at the anchor over 4 times the full window's: much of the window left out, or all on
one side) the quadratic is fitted, and where that is poorly determined too a constant (the
masked local mean); a window with under a tenth of its pixels kept keeps the previous
estimate. A window (or an image) narrower than twice the template gets the constant
everywhere; a window cut by the image's edge is judged by its own unmasked variance, so that
the quartic reaches the edges.

Noise. Without a camera law, each pixel's noise variance is estimated from the differences of
adjacent kept pixels within the same window (``local_noise_variance``), as
``_noise.estimate_noise_variance`` does over the whole image, so that it follows a noise that
grows with the background. With one, the variance beyond the law that the background pixels
share (``fixed_pattern_variance``) is added to it.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
from scipy import ndimage, sparse

from bayespsf.movie._noise import CLIP, KEPT_VARIANCE, MASK_SCORE, checked_map, matched_filter

DEGREE = 4  # the surface's degree
# its monomials u^a v^b as (a, b), a in rows and b in columns, by total degree: the first 6
# are the quadratic's, the first the constant's
_TERMS = tuple((t - b, b) for t in range(DEGREE + 1) for b in range(t + 1))
_QUADRATIC = 6
_WELL_DETERMINED = 4.0  # the most variance of a surface's value at an anchor, over the
# unmasked window's, for it to be fitted
PIXEL_CLIP = 3.0  # first passes: pixels beyond PIXEL_CLIP noise SDs of the fit are left out
_KEPT_SHARE = 0.1  # the least share of a window's pixels kept for any fit


def estimate_background(
    image: np.ndarray,
    spot: tuple[np.ndarray, np.ndarray],
    size: int,
    mask_score: float,
    variance,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The local background (photons per pixel), the mask of the pixels it kept and the
    surface's degree (``DEGREE``, or 0 where the window spans under twice the template).

    First fitted to every pixel, then twice to the pixels within ``PIXEL_CLIP`` noise SDs of
    the previous fit (the spots' bright pixels out, so that they cannot bend the first fits),
    then twice to the pixels ``background_pixels`` keeps against the previous fit: those away
    from the spots, found by their matched-filter score against ``mask_score`` (detection
    passes its threshold, so that the background's own noise excursions are not left out,
    which would bias it low). Where the second mask is the first, its fit would be the first's
    to the last bit, so it is not made (in 21 of 24 emccd-typical frames of 256 x 256 pixels):
    a fit depends on the image and its mask, and the previous surface only fills the windows
    with under ``_KEPT_SHARE`` of their pixels kept, which the first fit filled with the same.
    ``variance``: the noise variance that scores the pixels (a number or a map).
    """
    image = np.asarray(image, dtype=np.float64)
    window = _Window(image.shape, size, len(spot[0]))
    back = window.fit(image, np.ones(image.shape, dtype=bool), None)
    for _ in range(2):
        back = window.fit(image, np.abs(image - back) < PIXEL_CLIP * np.sqrt(variance), back)
    keep = None
    for _ in range(2):
        mask = background_pixels(image, back, variance, spot, mask_score)
        if keep is not None and np.array_equal(mask, keep):
            break
        keep = mask
        back = window.fit(image, keep, back)
    return back, keep, DEGREE if window.curved else 0


def background_pixels(image, back, variance, spot, mask_score: float) -> np.ndarray:
    """The pixels whose matched-filter score against ``back`` is at most ``mask_score`` (at
    least ``MASK_SCORE``) and that lie beyond the template's reach of any local maximum of the
    score above it: the spots' light, which falls within the template (4 SDs) of their peaks."""
    score, _ = matched_filter(image - back, variance, spot)
    above = score > max(mask_score, MASK_SCORE)
    peaks = above & (score == ndimage.maximum_filter(score, 3))
    return ~(above | ndimage.maximum_filter(peaks, len(spot[0])))


def background_and_noise(image, spot, size: int, level: float, estimate, background, noise, law):
    """The background and noise variance maps that detection scores against, with their
    sources, the camera law with the fixed-pattern variance added, and that variance.

    ``background``: given (a number or map) or None (``estimate_background`` over ``size``
    pixels, spots found against ``level``); ``noise``: given, None (``local_noise_variance``)
    or a callable of the background (the camera law, with ``law`` its ``PixelLaw``), to which
    the image's ``fixed_pattern_variance`` is added; ``estimate``: the whole image's noise
    variance (``estimate_noise_variance``), or None where neither is estimated.
    """
    keep = None
    if background is None:
        back, keep, degree = estimate_background(image, spot, size, level, estimate)
        back_source = f"local {'quartic' if degree else 'mean'} ({size} px)"
    else:
        back, back_source = checked_map("background", background, image.shape), "given"
    if noise is None:
        if keep is None:
            keep = background_pixels(image, back, estimate, spot, level)
        var = local_noise_variance(image, keep, size, estimate)
        return back, back_source, var, "estimated", law, 0.0
    if not callable(noise):
        return back, back_source, checked_map("noise_var", noise, image.shape), "given", law, 0.0
    var = noise(back)
    if keep is None:
        keep = background_pixels(image, back, var, spot, level)
    extra = fixed_pattern_variance(image - back, keep, var)
    if law is not None:  # a Gaussian term of the mean of law.frames frames: variance `extra`
        law = replace(law, readout_var=law.readout_var + law.frames * extra)
    return back, back_source, var + extra, "camera", law, extra


def fixed_pattern_variance(residual, keep, variance) -> float:
    """The variance that the image's background pixels show beyond ``variance`` (the camera
    law's), the same at every pixel: fixed-pattern noise, such as an offset that differs from
    pixel to pixel, which a temporal projection keeps whole while it averages the photon and
    readout noise (the dark signal non-uniformity of EMVA Standard 1288: the spatial variance of
    a mean image apart from its temporal variance).

    From the differences ``d`` of adjacent kept pixels of ``residual`` (the image less its
    smooth background), whose variance is ``v_i + v_j + 2 e`` for independent pixels: ``e``
    solves ``mean(d² / (v_i + v_j + 2 e)) = KEPT_VARIANCE`` over the differences within
    ``CLIP`` of their SD (fixed-point steps from 0); 0 where the pixels vary no more than the
    law says. An excess that is spatially correlated (whole columns or rows offset) is seen
    only in part.
    """
    var = np.broadcast_to(np.asarray(variance, dtype=np.float64), residual.shape)
    diffs, sums = [], []
    for axis in (0, 1):
        first = (slice(None, -1),) if axis == 0 else (slice(None), slice(None, -1))
        second = (slice(1, None),) if axis == 0 else (slice(None), slice(1, None))
        both = keep[first] & keep[second]
        diffs.append((residual[second] - residual[first])[both])
        sums.append((var[first] + var[second])[both])
    d2, total = np.concatenate(diffs) ** 2, np.concatenate(sums)
    if d2.size < 100:
        return 0.0
    extra = 0.0
    for _ in range(10):
        scale = total + 2.0 * extra
        kept = d2 < CLIP**2 * scale
        if not kept.any():
            break
        ratio = float(np.mean(d2[kept] / scale[kept])) / KEPT_VARIANCE
        step = max(0.0, extra + (ratio - 1.0) * float(np.mean(scale[kept])) / 2.0)
        if step == extra:  # a fixed point (0 where the law explains the pixels)
            break
        extra = step
    return extra


def local_noise_variance(image, keep, size: int, start: float) -> np.ndarray:
    """Each pixel's noise variance from the differences of adjacent kept pixels in its window.

    As ``_noise.estimate_noise_variance``, window by window: the variance of the horizontal
    and vertical differences within ``CLIP`` SDs of 0 (their SD from the previous pass,
    started from ``start``, the whole image's variance), over the share of a normal law's
    variance kept within them, halved; three passes. A window with under a tenth of its
    differences kept gets ``start``.
    """
    image = np.asarray(image, dtype=np.float64)
    pairs = []
    for axis in (0, 1):
        diff = np.diff(image, axis=axis)
        both = keep[(slice(1, None),) if axis == 0 else (slice(None), slice(1, None))]
        both = both & keep[(slice(None, -1),) if axis == 0 else (slice(None), slice(None, -1))]
        pad = ((0, 1), (0, 0)) if axis == 0 else ((0, 0), (0, 1))
        pairs.append((np.pad(diff, pad), np.pad(both, pad)))
    var = np.full(image.shape, float(start))
    inside = ndimage.uniform_filter(np.ones(image.shape), size, mode="constant")
    for _ in range(3):
        total = np.zeros(image.shape)
        count = np.zeros(image.shape)
        for diff, both in pairs:
            kept = both & (diff**2 < CLIP**2 * 2.0 * var)
            total += np.where(kept, diff**2, 0.0)
            count += kept
        total = ndimage.uniform_filter(total, size, mode="constant")
        count = ndimage.uniform_filter(count, size, mode="constant")
        enough = count > _KEPT_SHARE * 2.0 * inside
        with np.errstate(divide="ignore", invalid="ignore"):
            var = np.where(enough, total / count / KEPT_VARIANCE / 2.0, float(start))
    return var


class _Window:
    """The local polynomial fits of an image's shape (see the module docstring): each axis's
    anchors (``size // 8`` apart, and its last pixel), the monomials ``u**k`` of their windows
    as sparse matrices (anchors × pixels; ``u`` the offset from the anchor over the window's
    half-side, 0 off the window), each pixel's anchor and offset, and the unmasked windows'
    pixel counts and variances of the fitted value (quartic and quadratic)."""

    def __init__(self, shape: tuple[int, int], size: int, reach: int):
        parts = _window_parts(tuple(shape), size, reach)
        self.axes, self.full, self.curved, self.variance, self.inverse = parts
        self.count = self.full[0, 0]

    def fit(self, image: np.ndarray, keep: np.ndarray, previous) -> np.ndarray:
        """The surfaces of the ``keep`` pixels at every pixel; ``previous`` (or the mean of
        the kept pixels where None) where a window keeps under ``_KEPT_SHARE`` of its pixels."""
        weight = keep.astype(np.float64)
        degree = DEGREE if self.curved else 0
        unmasked = keep.all()  # the first fit: the windows' sums and inverses kept per shape
        masked = self.full if unmasked else _moments(self.axes, weight, 2 * degree)
        data = _moments(self.axes, weight * image, degree)
        count = masked[0, 0]
        coef = np.zeros((*count.shape, len(_TERMS)))
        with np.errstate(divide="ignore", invalid="ignore"):
            coef[..., 0] = data[0, 0] / count
        if self.curved:
            rhs = np.stack([data[a, b] for a, b in _TERMS], axis=-1)
            if unmasked:  # every window's quartic is well determined
                coef = np.einsum("...ij,...j->...i", self.inverse, rhs)
            else:
                _masked_fit(masked, rhs, self.variance, coef.reshape(-1, len(_TERMS)))
        coef[count < _KEPT_SHARE * self.count] = np.nan
        back = _evaluate(coef, self.axes, degree)
        if previous is None:
            previous = np.full(image.shape, image[keep].mean() if keep.any() else image.mean())
        return np.where(np.isfinite(back), back, previous)


def _masked_fit(masked: np.ndarray, rhs: np.ndarray, full, coef: np.ndarray) -> None:
    """Each anchor's coefficients, written into ``coef`` (anchors, terms): the quartic where
    its value is well determined (variance at most ``_WELL_DETERMINED`` times the unmasked
    window's, ``full``), else the quadratic where it is, else left as they are (``fit``'s
    constant)."""
    gram = _normal_matrix(masked)
    k = gram.shape[-1]
    gram = gram.reshape(-1, k, k)
    quadratic = gram[:, :_QUADRATIC, :_QUADRATIC].copy()  # before the quartic's ridge
    rhs = rhs.reshape(-1, k)
    todo = np.arange(len(gram))
    for system, limit in zip((gram, quadratic), full, strict=True):
        terms = system.shape[-1]
        chosen = system if len(todo) == len(gram) else system[todo]
        found, variance = _solve(chosen, rhs[todo, :terms])
        solve = variance <= _WELL_DETERMINED * limit.ravel()[todo]
        coef[todo[solve], :terms] = found[solve]
        todo = todo[~solve]
        if not todo.size:
            break


def _evaluate(coef: np.ndarray, axes, degree: int) -> np.ndarray:
    """Each pixel's value of its nearest anchor's surface ``Σ coef[k] u^a v^b`` (``coef``:
    anchors × anchors × terms of ``_TERMS``, those of degree up to ``degree``), summed in
    columns first: for each power ``a`` of ``u``, the anchor rows' polynomials in ``v`` at
    every column, then those rows taken to the pixels' rows and weighted by ``u^a``."""
    (_, row_anchor, u), (_, col_anchor, v) = axes
    back = np.zeros((row_anchor.size, col_anchor.size))
    powers = v[None, :] ** np.arange(degree + 1)[:, None]  # (b, columns)
    for a in range(degree + 1):
        terms = [k for k, (p, _) in enumerate(_TERMS[: _count(degree)]) if p == a]
        rows = np.einsum("rck,kc->rc", coef[..., terms][:, col_anchor], powers[: len(terms)])
        back += rows[row_anchor] * (u[:, None] ** a) if a else rows[row_anchor]
    return back


def _count(degree: int) -> int:
    """The number of terms of a surface of ``degree``."""
    return (degree + 1) * (degree + 2) // 2


def _moments(axes, values: np.ndarray, degree: int) -> np.ndarray:
    """``m[a, b]``: the sums of ``values u^a v^b`` over each anchor's window of ``axes``
    (``_axis``'s, rows then columns) for ``a + b <= degree`` (else 0), shape ``(degree + 1,
    degree + 1, row anchors, column anchors)``: one sparse product for every power of ``u``,
    then one for each with every power of ``v`` it takes."""
    (rows, _, _), (cols, _, _) = axes
    n_rows, n_cols = rows[0].shape[0], cols[0].shape[0]
    left = rows[degree] @ values  # (powers of u x row anchors, columns)
    out = np.zeros((degree + 1, degree + 1, n_rows, n_cols))
    for a in range(degree + 1):
        both = cols[degree - a] @ left[a * n_rows : (a + 1) * n_rows].T
        out[a, : degree + 1 - a] = both.reshape(-1, n_cols, n_rows).transpose(0, 2, 1)
    return out


@functools.lru_cache(maxsize=8)
def _window_parts(shape: tuple[int, int], size: int, reach: int):
    """``_Window``'s fixed parts for an image shape, window and template reach (one per
    shape: every frame of a movie shares them): the axes, the unmasked windows' moments,
    whether the window is wide enough for a curved surface, and the quartic's and the
    quadratic's variances at the anchors."""
    axes = [_axis(n, size) for n in shape]
    full = _moments(axes, np.ones(shape), 2 * DEGREE)
    curved = min(min(size, n) for n in shape) >= 2 * reach  # else a constant: too narrow a window
    if not curved:
        return axes, full, curved, None, None
    gram = _normal_matrix(full)
    variance = [_centre_variance(gram), _centre_variance(gram[..., :_QUADRATIC, :_QUADRATIC])]
    inverse = np.linalg.inv(_regularised(gram.reshape(-1, *gram.shape[-2:]))[0])
    return axes, full, curved, variance, inverse.reshape(gram.shape)


def _axis(length: int, size: int):
    """``(powers, anchor, u)`` of one axis (see ``_Window``): ``powers[m]`` stacks the sparse
    matrices of ``u**0`` to ``u**m`` (anchors × pixels each) in rows."""
    half = max(1, size // 2)
    step = max(1, size // 8)
    anchors = np.unique(np.r_[np.arange(0, length, step), length - 1])
    offsets = np.arange(-half, half + 1)
    where = anchors[:, None] + offsets
    inside = (where >= 0) & (where < length)
    rows = np.broadcast_to(np.arange(anchors.size)[:, None], where.shape)[inside]
    u = np.broadcast_to(offsets / half, where.shape)[inside]
    shape = (anchors.size, length)
    single = [
        sparse.csr_array((u**k, (rows, where[inside])), shape=shape) for k in range(2 * DEGREE + 1)
    ]
    powers = [sparse.vstack(single[: m + 1], format="csr") for m in range(2 * DEGREE + 1)]
    anchor = np.abs(np.arange(length)[:, None] - anchors[None, :]).argmin(axis=1)
    return powers, anchor, (np.arange(length) - anchors[anchor]) / half


def _centre_variance(gram: np.ndarray) -> np.ndarray:
    """``(gram⁻¹)₀₀``: the variance of the fitted value at the anchor over the pixels'
    (``_solve``'s)."""
    flat = gram.reshape(-1, *gram.shape[-2:]).copy()
    return _solve(flat, np.zeros(flat.shape[:-1]))[1].reshape(gram.shape[:-2])


def _regularised(gram: np.ndarray) -> np.ndarray:
    """``gram`` (n, k, k) with a ridge of 1e-12 of its trace on the diagonal (1 where the
    trace is 0: no pixel), added in place; returned with its traces."""
    k = gram.shape[-1]
    scale = np.einsum("nii->n", gram)
    gram[:, np.arange(k), np.arange(k)] += (1e-12 * scale + (scale == 0))[:, None]
    return gram, scale


def _solve(gram: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares coefficients ``gram⁻¹ rhs`` (n, k) and ``(gram⁻¹)₀₀`` (n,), the
    variance of the fitted value at the anchor over the pixels', from one batched solve with
    ``rhs`` and the first unit vector as right-hand sides. A singular ``gram``, kept from a
    ridge of 1e-12 of its trace, gives a huge variance; no pixel, an infinite one. ``gram``
    is overwritten (the ridge is added to it)."""
    n, k = gram.shape[:2]
    regular, scale = _regularised(gram)
    sides = np.zeros((n, k, 2))
    sides[..., 0], sides[:, 0, 1] = rhs, 1.0
    out = np.linalg.solve(regular, sides)
    return out[..., 0], np.where(scale > 0, out[:, 0, 1], np.inf)


_PAIRS = np.array([[(a + c, b + d) for c, d in _TERMS] for a, b in _TERMS])  # (15, 15, 2)


def _normal_matrix(moments: np.ndarray) -> np.ndarray:
    """The surface's normal matrix at each anchor, ``(..., 15, 15)`` (its leading 6 × 6 block
    the quadratic's)."""
    side = moments.shape[0]
    flat = np.ascontiguousarray(moments.reshape(side * side, -1).T)  # (anchors, a * side + b)
    gram = np.take(flat, _PAIRS[..., 0] * side + _PAIRS[..., 1], axis=1)
    return gram.reshape(*moments.shape[2:], len(_TERMS), len(_TERMS))
