"""Every validation script runs in --quick mode and writes its table and figure (numbers are
not asserted here: the scripts' own claims are tested where the code they exercise is)."""

import importlib.util
from pathlib import Path

import pytest

SCRIPTS = sorted((Path(__file__).resolve().parents[1] / "validation").glob("[!_]*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_quick_run_writes_its_results(script, tmp_path):
    spec = importlib.util.spec_from_file_location(script.stem, script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    table = module.main(["--quick", "--out", str(tmp_path)])
    assert len(table) > 0 and not table.isna().all().any()
    written = {p.suffix for p in tmp_path.iterdir()}
    assert {".csv", ".md", ".png"} <= written
    assert "Command: `python validation/" in next(tmp_path.glob("*.md")).read_text()
