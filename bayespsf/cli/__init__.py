"""The ``bayespsf`` command: ``main(argv)`` runs it, ``build_parser()`` describes it.

Subcommands import the library only when they run, so that ``bayespsf --help`` stays fast.
"""

from bayespsf.cli.commands import build_parser, main

__all__ = ["build_parser", "main"]
