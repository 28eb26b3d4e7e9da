"""The ``bayespsf`` command."""

from __future__ import annotations

import argparse
import sys


def _selfcheck(_args) -> int:
    from bayespsf import selfcheck

    print(selfcheck.run())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bayespsf",
        description="Bayesian analysis of single fluorescent molecule images.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    check = commands.add_parser(
        "selfcheck",
        help="check the camera likelihoods of a typical EMCCD and time each tier",
        description="Integrate the exact EMCCD law (normalisation, mean, variance), compare "
        "every likelihood tier with it and time each tier relative to the Poisson tier.",
    )
    check.set_defaults(run=_selfcheck)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
