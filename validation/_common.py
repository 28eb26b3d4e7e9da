"""Shared plumbing of the validation scripts: arguments, output files, the machine line."""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).with_name("results")


def parser(doc: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=doc.strip().split("\n")[0])
    p.add_argument("--quick", action="store_true", help="a small run (the test suite runs it)")
    p.add_argument("--out", type=Path, default=RESULTS, help="output folder")
    return p


def machine() -> str:
    import os

    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"numpy {np.__version__}"
    )


def write(out: Path, stem: str, table, text: str, command: str, started: float) -> None:
    """Write ``stem.csv`` and ``stem.md`` (the table, the command, the wall time, the machine)."""
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / f"{stem}.csv", index=False)
    seconds = time.perf_counter() - started
    (out / f"{stem}.md").write_text(
        f"{text}\n\nCommand: `{command}`; wall time {seconds:.0f} s on {machine()}.\n"
    )
