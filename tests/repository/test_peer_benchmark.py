"""The NumPyro peer's checks (``tests/repository/peer_checks.py``) in a process of their own.

JAX, once it has a backend, warns at every ``os.fork`` that the child may deadlock; the
suite's other tests fork workers (process pools, Dask), and under pytest-xdist they may run
in the same worker after the peer's tests. So the peer's checks run in a fresh interpreter,
with the suite's settings (warnings as errors). Skipped without numpyro, an optional extra
(``pip install -e ".[peer]"``).
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(importlib.util.find_spec("numpyro") is None, reason="numpyro not installed")
def test_peer_checks_pass_in_their_own_process():
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-n",
            "0",
            str(ROOT / "tests" / "repository" / "peer_checks.py"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "4 passed" in result.stdout, result.stdout[-2000:]
