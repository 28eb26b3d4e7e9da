"""The user guide builds as a strict mkdocs site, with the API reference from docstrings."""

import argparse
import os
import subprocess
import sys
from pathlib import Path

from bayespsf.cli.commands import build_parser

ROOT = Path(__file__).resolve().parents[2]


def test_site_builds_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    api = (tmp_path / "api" / "index.html").read_text()
    assert "sample_posterior" in api
    assert "importance" in api
    assert (tmp_path / "cli" / "index.html").exists()


def test_cli_page_names_every_command_and_option():
    text = (ROOT / "docs" / "cli.md").read_text()
    parser = build_parser()
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for name, sub in commands.choices.items():
        assert f"## `bayespsf {name}`" in text, name
        for action in sub._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}" in text, (name, option)
