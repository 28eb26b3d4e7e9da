"""Write a benchmark's markdown result into its marked section of benchmarks/README.md."""

from __future__ import annotations

import platform
import re
from pathlib import Path

import numpy as np

README = Path(__file__).with_name("README.md")


def machine() -> str:
    import os

    return (
        f"{platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, numpy {np.__version__}"
    )


def write_section(name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->``."""
    text = README.read_text()
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise SystemExit(f"{README} has no section {start} ... {end}")
    README.write_text(pattern.sub(lambda _: f"{start}\n{body.strip()}\n{end}", text))
