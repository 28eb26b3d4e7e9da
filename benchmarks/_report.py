"""Write a benchmark's markdown result into its marked section of benchmarks/README.md."""

from __future__ import annotations

from pathlib import Path

from bayespsf._report import machine
from bayespsf._report import write_section as _write_section

README = Path(__file__).with_name("README.md")


def write_section(name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->``."""
    _write_section(README, name, body)


def publish(name: str, text: str, quick: bool) -> None:
    """Print a benchmark's markdown; a full run also writes it into its README section."""
    print(text)
    if not quick:
        write_section(name, text)


__all__ = ["README", "machine", "publish", "write_section"]
