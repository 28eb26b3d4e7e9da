"""A quick, self-contained check of the camera laws: what ``bayespsf selfcheck`` prints.

For a typical EMCCD it integrates the exact law over counts (normalisation, mean, variance
against their closed forms), compares every likelihood tier with the exact one on counts drawn
from the law, and times each tier on a 15x15 ROI x 32 walkers, relative to the Poisson tier.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from bayespsf._runtime import best_time
from bayespsf.cameras import EMCCD
from bayespsf.cameras.emccd import TIERS

DEFAULT_CAMERA = dict(gain=200.0, readout_sd=40.0, offset=100.0, e_per_adu=10.0)


def moments_table(camera: EMCCD, lams=(0.1, 1.0, 10.0, 100.0)) -> pd.DataFrame:
    """Mass, mean and variance of the law by Gauss-Legendre quadrature over counts."""
    x, w = np.polynomial.legendre.leggauss(24)
    rows = []
    for lam in lams:
        g, s, k = camera.gain, camera.readout_sd, camera.e_per_adu
        sd = np.sqrt(2 * lam * g * g + s * s)
        edges = (
            camera.offset
            + np.unique(
                np.concatenate(
                    [
                        np.linspace(max(0.0, lam * g - 14 * sd), lam * g + 14 * sd + 60 * g, 120),
                        np.linspace(-14 * s, 14 * s, 57),
                    ]
                )
            )
            / k
        )
        half = 0.5 * np.diff(edges)[:, None]
        c = (0.5 * (edges[1:] + edges[:-1])[:, None] + half * x).ravel()
        pw = np.exp(camera.log_likelihood(c, lam)) * (half * w).ravel()
        mass = pw.sum()
        mean = (c * pw).sum() / mass
        var = ((c - mean) ** 2 * pw).sum() / mass
        rows.append(
            {
                "lam": lam,
                "mass - 1": mass - 1.0,
                "mean rel. err": (mean - camera.offset) / (lam * g / k) - 1.0,
                "var rel. err": var / ((2 * lam * g * g + s * s) / k**2) - 1.0,
            }
        )
    return pd.DataFrame(rows).set_index("lam")


def tier_table(camera_kwargs: dict, seed: int = 0, shape=(32, 15, 15)) -> pd.DataFrame:
    """Each tier's worst |log p - exact| on counts drawn from the law, and its speed."""
    rng = np.random.default_rng(seed)
    lam = 10 ** rng.uniform(-1, 3, size=shape)
    exact = EMCCD(**camera_kwargs, likelihood="exact")
    counts = exact.sample(lam, rng)
    reference = exact.log_likelihood(counts, lam)
    rows = []
    timings = {}
    for tier in TIERS:
        cam = EMCCD(**camera_kwargs, likelihood=tier)
        values = cam.log_likelihood_unchecked(counts, lam)
        timings[tier] = best_time(lambda cam=cam: cam.log_likelihood_unchecked(counts, lam))
        finite = np.isfinite(values)
        rows.append(
            {
                "tier": tier,
                "max |d log p|": np.max(np.abs(values[finite] - reference[finite]))
                if finite.any()
                else np.nan,
                "non-finite": int((~finite).sum()),
                "evals/s": lam.size / timings[tier],
            }
        )
    table = pd.DataFrame(rows).set_index("tier")
    table["throughput vs poisson"] = table["evals/s"] / table.loc["poisson", "evals/s"]
    return table


def run() -> str:
    """The self-check report as text."""
    camera = EMCCD(**DEFAULT_CAMERA)
    with pd.option_context("display.float_format", "{:.3g}".format, "display.width", 120):
        return (
            f"bayespsf self-check of {camera!r}\n\n"
            "Exact law integrated over counts (should be ~0):\n"
            f"{moments_table(camera)}\n\n"
            "Tiers on 32 walkers x 15x15 counts drawn from the law, lam in [0.1, 1000]:\n"
            f"{tier_table(DEFAULT_CAMERA)}\n"
        )
