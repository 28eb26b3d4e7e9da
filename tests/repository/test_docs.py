"""Every Python example in the README and docs runs as written."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCKS = [
    (path.name, i, block)
    for path in DOCS
    for i, block in enumerate(re.findall(r"```python\n(.*?)```", path.read_text(), re.S))
]


@pytest.mark.parametrize("name,index,code", BLOCKS, ids=[f"{b[0]}#{b[1]}" for b in BLOCKS])
def test_example_runs(name, index, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if "my-experiment.toml" in code or "my.toml" in code:
        from bayespsf import load_scene

        for stem in ("my-experiment", "my"):
            load_scene("paper-fig3").save(tmp_path / f"{stem}.toml")
    # run as a user's script runs: as __main__, so that an example's guard runs its body
    exec(compile(code, f"{name} example {index}", "exec"), {"__name__": "__main__"})
