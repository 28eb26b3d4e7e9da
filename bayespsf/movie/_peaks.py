"""Candidates from a score map: local maxima above a threshold, refined to sub-pixel positions,
and the rejections that keep each molecule's ROI inside the image and apart from the others."""

from __future__ import annotations

import numpy as np
from scipy import ndimage, spatial

STATUSES = ("accepted", "rejected: edge", "rejected: neighbour")


def find_peaks(score: np.ndarray, threshold: float, roi: int, min_distance: float):
    """``(rows, cols, status, dy, dx)`` of the local maxima (3 × 3) of ``score`` above
    ``threshold``, in image order: ``rejected: edge`` where a ``roi`` × ``roi`` cut centred on
    the peak would cross the image's edge, else ``rejected: neighbour`` where another peak is
    closer than ``min_distance`` in rows or in columns, else ``accepted``."""
    peak = score == ndimage.maximum_filter(score, size=3, mode="constant", cval=-np.inf)
    rows, cols = np.nonzero(peak & (score > threshold))
    status = np.full(rows.size, STATUSES[0], dtype=object)
    status[_near(rows, cols, min_distance)] = STATUSES[2]
    h = roi // 2
    height, width = score.shape
    edge = (rows < h) | (cols < h) | (rows >= height - h) | (cols >= width - h)
    status[edge] = STATUSES[1]
    return (rows, cols, status, *_subpixel(score, rows, cols))


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
