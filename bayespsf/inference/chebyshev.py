"""Degree-8 Chebyshev interpolation on [-1, 1], as ``bayespsf.inference.fused`` (the camera law
per pixel) and ``bayespsf.inference.spot_factors`` (the Gaussian's log tail per pixel edge)
use it: the nodes, the check points, the matrices from node values to coefficients and from
coefficients to values at the checks, and Clenshaw's recurrence unrolled for compiled loops.
"""

from __future__ import annotations

import numba
import numpy as np

DEGREE = 8  # DEGREE + 1 function values per interpolant
_K = np.arange(DEGREE + 1)
NODES = np.cos(np.pi * (_K + 0.5) / (DEGREE + 1))  # the Chebyshev points of the first kind
# the two ends and two midpoints between nodes (x = +-1, +-1/2), where the error peaks
CHECKS = np.cos(np.pi * np.array([0, 3, 6, 9]) / (DEGREE + 1))
POINTS = np.concatenate([NODES, CHECKS])  # where an interpolated function is evaluated
TO_COEFFICIENTS = np.cos(np.outer(_K, np.arccos(NODES))) * (2.0 / (DEGREE + 1))
TO_COEFFICIENTS[0] *= 0.5  # coefficients = TO_COEFFICIENTS @ values at NODES
AT_CHECKS = np.cos(np.outer(_K, np.arccos(CHECKS)))  # values at CHECKS = coefficients @ this


@numba.njit(cache=True, nogil=True, inline="always")
def terms(c):
    """The ``DEGREE + 1`` coefficients ``c`` (an array) as a tuple, for ``clenshaw``."""
    return (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8])


@numba.njit(cache=True, nogil=True, inline="always")
def clenshaw(c, x):
    """``sum_k c[k] T_k(x)`` for ``k <= 8`` (``c``: a tuple from ``terms``), unrolled so that
    a loop over ``x`` that calls it vectorises."""
    x2 = 2.0 * x
    b7 = c[7] + x2 * c[8]
    b6 = c[6] + x2 * b7 - c[8]
    b5 = c[5] + x2 * b6 - b7
    b4 = c[4] + x2 * b5 - b6
    b3 = c[3] + x2 * b4 - b5
    b2 = c[2] + x2 * b3 - b4
    b1 = c[1] + x2 * b2 - b3
    return c[0] + x * b1 - b2


__all__ = [
    "AT_CHECKS",
    "CHECKS",
    "DEGREE",
    "NODES",
    "POINTS",
    "TO_COEFFICIENTS",
    "clenshaw",
    "terms",
]
