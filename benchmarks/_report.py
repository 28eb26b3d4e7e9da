"""Write a benchmark's markdown result into its marked section of benchmarks/README.md."""

from __future__ import annotations

from pathlib import Path

from bayespsf._report import machine
from bayespsf._report import write_section as _write_section

README = Path(__file__).with_name("README.md")


def write_section(name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->``."""
    _write_section(README, name, body)


__all__ = ["README", "machine", "write_section"]
