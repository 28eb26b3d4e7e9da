"""The `bayespsf` command."""

import subprocess
import sys

import pytest

from bayespsf import cli, selfcheck
from bayespsf.cameras import EMCCD


def test_selfcheck_moments_are_exact():
    table = selfcheck.moments_table(EMCCD(**selfcheck.DEFAULT_CAMERA))
    assert (table.abs() < 1e-8).all().all()


def test_selfcheck_command_prints_every_tier(capsys):
    assert cli.main(["selfcheck"]) == 0
    out = capsys.readouterr().out
    for tier in ("exact", "high-gain", "gaussian", "poisson"):
        assert tier in out


def test_help_and_unknown_command():
    result = subprocess.run(
        [sys.executable, "-m", "bayespsf.cli", "--help"], capture_output=True, text=True
    )
    assert result.returncode == 0 and "selfcheck" in result.stdout
    with pytest.raises(SystemExit):
        cli.main(["nonsense"])
