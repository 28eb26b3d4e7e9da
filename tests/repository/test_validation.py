"""Every validation script runs in --quick mode exactly as a user types it (from the repository
root, default output folder) and writes its table and figure there, leaving validation/README.md
alone (the quick run did all the work and then failed on a README section). Numbers
are not asserted here: the scripts' own claims are tested where the code they exercise is."""

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted((ROOT / "validation").glob("[!_]*.py"))
RESULTS = ROOT / "validation" / "results"


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_quick_run_as_documented(script):
    readme = (ROOT / "validation" / "README.md").read_text()
    command = f"python validation/{script.name} --quick"
    python = str(Path(sys.executable))
    result = subprocess.run(
        [python, *command.split()[1:]], cwd=ROOT, capture_output=True, text=True, timeout=900
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert (ROOT / "validation" / "README.md").read_text() == readme
    written = sorted(RESULTS.glob(f"{script.stem}_quick*"))
    assert {p.suffix for p in written} >= {".csv", ".md", ".png"}, written
    table = pd.read_csv(next(p for p in written if p.suffix == ".csv"))
    assert len(table) > 0 and not table.isna().all().any()
    md = next(p for p in written if p.suffix == ".md").read_text()
    assert f"Command: `{command}`" in md


def test_the_calibration_study_runs_through_the_jax_backend(tmp_path):
    """``--backend jax`` as a user types it, quick, on one configuration and with the Laplace
    (the JAX programs of each likelihood tier and method compile anew; the backend's methods
    are tested in tests/inference/test_jax_backend.py): the study through the JAX backend,
    written under its own stem with its command; without a batched method it is refused."""
    python = str(Path(sys.executable))
    command = (
        "python validation/posterior_coverage.py --quick --method laplace --backend jax "
        "--configurations 0"
    )
    result = subprocess.run(
        [python, *command.split()[1:], "--out", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    md = (tmp_path / "posterior_coverage_laplace_jax_quick.md").read_text()
    assert f"Command: `{command}`" in md
    table = pd.read_csv(tmp_path / "posterior_coverage_laplace_jax_quick.csv")
    assert len(table) == 6 and table["molecules"].gt(0).all()
    refused = subprocess.run(
        [python, "validation/posterior_coverage.py", "--quick", "--backend", "jax"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2 and "--method auto, importance or laplace" in refused.stderr
