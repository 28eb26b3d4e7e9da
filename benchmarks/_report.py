"""Write a benchmark's markdown result into its marked section of benchmarks/README.md."""

from __future__ import annotations

import sys
from pathlib import Path

from bayespsf._runtime import machine

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from report import write_section as _write_section

README = Path(__file__).with_name("README.md")


def write_section(name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->``."""
    _write_section(README, name, body)


def publish(name: str, text: str, quick: bool) -> None:
    """Print a benchmark's markdown; a full run also writes it into its README section."""
    print(text)
    if not quick:
        write_section(name, text)


def quick_run(doc: str, argv=None) -> bool:
    """Parse a benchmark's only option, ``--quick``; True for a quick run."""
    import argparse

    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small run that prints only")
    return parser.parse_args(argv).quick


def publish_table(name: str, intro: str, table, quick: bool) -> None:
    """Publish ``intro``, ``table`` as markdown and the command with the machine (``publish``)."""
    command = f"python benchmarks/{name}.py" + (" --quick" if quick else "")
    text = (
        f"{intro}\n\n{table.to_markdown(index=False, floatfmt='.3g')}\n\n"
        f"Command: `{command}` on {machine()}."
    )
    publish(name, text, quick)


__all__ = ["README", "machine", "publish", "publish_table", "quick_run", "write_section"]
