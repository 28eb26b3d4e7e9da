"""Repository tooling shared by ``benchmarks/`` and ``validation/``: a script's result section
of its README (not part of the installed package)."""

from __future__ import annotations

import re
from pathlib import Path


def write_section(readme: Path, name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` of ``readme``."""
    text = readme.read_text()
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise SystemExit(f"{readme} has no section {start} ... {end}")
    readme.write_text(pattern.sub(lambda _: f"{start}\n{body.strip()}\n{end}", text))
