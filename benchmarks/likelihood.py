"""Pixel-likelihood cost and accuracy of every EMCCD tier.

For a 15x15 ROI x 32 walkers (one vectorised call, as in the log-posterior), each tier's
evaluations per second as a ratio to the Poisson tier measured in the same run, and its worst
|log p - exact| on (a) that ROI and (b) 20 000 counts drawn from the law with lam log-uniform in
[1e-2, 1e4] (the realistic domain). Also the table tier's memory; its first use, the
table built, is ``benchmarks/first_use.py``'s.

    python benchmarks/likelihood.py            # full run, rewrites its section of README.md
    python benchmarks/likelihood.py --quick    # small and fast, prints only
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from bayespsf._runtime import best_time
from bayespsf.cameras import EMCCD, _emccd_table
from bayespsf.cameras.emccd import TIERS
from bayespsf.psf import expected_counts

CAMERAS = {
    "G1000 σ10": dict(gain=1000.0, readout_sd=10.0, offset=100.0, e_per_adu=20.0),
    "G300 σ30": dict(gain=300.0, readout_sd=30.0, offset=500.0, e_per_adu=12.0),
    "G100 σ100": dict(gain=100.0, readout_sd=100.0, offset=100.0, e_per_adu=2.0),
}


def walker_roi(rng, walkers=32):
    """Expected photons of a typical spot (N 1000, b 5, s 120 nm, a 79 nm) under 32 walkers."""
    truth = np.array([0.0, 0.0, 120.0, 120.0, 1000.0, 5.0])
    spread = np.array([10.0, 10.0, 8.0, 8.0, 80.0, 0.5])
    params = truth + spread * rng.standard_normal((walkers, 6))
    return expected_counts(params, 15, 79.0)


def run(quick: bool) -> pd.DataFrame:
    rng = np.random.default_rng(2026)
    repeat = 3 if quick else 15
    n_domain = 2000 if quick else 20_000
    rows = []
    for name, params in CAMERAS.items():
        exact = EMCCD(**params)
        lam_roi = walker_roi(rng)
        counts_roi = exact.sample(lam_roi[0], rng)[None]  # one observed ROI, 32 walkers
        lam_dom = 10 ** rng.uniform(-2, 4, n_domain)
        counts_dom = exact.sample(lam_dom, rng)
        ref_roi = exact.log_likelihood_unchecked(counts_roi, lam_roi)
        ref_dom = exact.log_likelihood_unchecked(counts_dom, lam_dom)
        timing = {}
        for tier in TIERS:
            cam = EMCCD(**params, likelihood=tier)
            cam.log_likelihood_unchecked(counts_roi, lam_roi)  # warm (table build)
            timing[tier] = best_time(
                lambda cam=cam, c=counts_roi, lam=lam_roi: cam.log_likelihood_unchecked(c, lam),
                max(1, repeat // 5) if tier == "exact" else repeat,
            )
            roi_err = np.abs(cam.log_likelihood_unchecked(counts_roi, lam_roi) - ref_roi)
            dom = cam.log_likelihood_unchecked(counts_dom, lam_dom)
            finite = np.isfinite(dom)
            rows.append(
                {
                    "camera": name,
                    "tier": tier,
                    "evals/s": lam_roi.size / timing[tier],
                    "worst |Δlog p| ROI": np.nanmax(
                        np.where(np.isfinite(roi_err), roi_err, np.nan)
                    ),
                    "worst |Δlog p| domain": np.max(np.abs(dom[finite] - ref_dom[finite])),
                    "-inf in domain": int((~finite).sum()),
                }
            )
        for row in rows[-len(TIERS) :]:
            row["throughput / poisson"] = row["evals/s"] / (lam_roi.size / timing["poisson"])
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame, command: str) -> str:
    from _report import machine

    table = df.copy()
    table["evals/s"] = table["evals/s"].map(lambda v: f"{v:.3g}")
    for col in ("worst |Δlog p| ROI", "worst |Δlog p| domain"):
        table[col] = table[col].map(lambda v: f"{v:.1e}")
    table["throughput / poisson"] = table["throughput / poisson"].map(lambda v: f"{v:.3f}")
    mem = _emccd_table.table_for(0.1).nbytes / 1e6
    return (
        f"Command: `{command}` on {machine()}.\n\n"
        f"Table memory per camera: {mem:.1f} MB.\n\n" + table.to_markdown(index=False)
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    args = parser.parse_args()
    df = run(args.quick)
    command = "python benchmarks/likelihood.py" + (" --quick" if args.quick else "")
    text = markdown(df, command)
    from _report import publish

    publish("likelihood", text, args.quick)
    return df


if __name__ == "__main__":
    main()
