"""The accuracy-time frontier (see :mod:`bayespsf.cli.bench`): every EMCCD likelihood tier at ESS
targets 100 / 400 / 1000 / 4000 and the MLE + CRLB and Laplace ends, for 12 molecules of the
`emccd-typical` scene at N = 200, 1000 and 5000 (the `exact` tier: 2 molecules per N, ESS 100 and
400). Where JAX is installed, also the JAX backend's `importance` and `auto` for the tiers it
supports, each N's molecules as one stack timed after a warm-up call (compilation excluded);
without JAX those rows are skipped and the output says so. Writes
benchmarks/results/frontier.{md,csv,png} and frontier-summary.csv, and its section of
benchmarks/README.md.

    python benchmarks/frontier.py [--workers K]   # full run: ~27 minutes on 2 cores, of
                                                  # which the JAX rows on the CPU ~19
    python benchmarks/frontier.py --quick         # = bayespsf bench --quick, to a temp folder
    python benchmarks/frontier.py --from-csv      # tables and figure again from frontier.csv
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from bayespsf.cli import bench

RESULTS = Path(__file__).with_name("results")


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    parser.add_argument("--workers", type=int, default=None, help="local processes")
    parser.add_argument(
        "--from-csv",
        action="store_true",
        help="rebuild tables and figure from results/frontier.csv",
    )
    args = parser.parse_args(argv)
    if args.from_csv:
        import pandas as pd

        rows = pd.read_csv(RESULTS / "frontier.csv")
    else:
        rows = bench.frontier(bench.QUICK if args.quick else bench.FULL, workers=args.workers)
    command = "python benchmarks/frontier.py" + (" --quick" if args.quick else "")
    out = Path(tempfile.mkdtemp(prefix="frontier-")) if args.quick else RESULTS
    text = bench.report(rows, out, command)
    print(text)
    if not args.quick:
        from _report import write_section

        write_section(
            "frontier",
            text.replace("frontier.png", "results/frontier.png").replace(
                "frontier.csv", "results/frontier.csv"
            ),
        )
    return text


if __name__ == "__main__":
    main()
