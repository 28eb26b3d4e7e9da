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


def test_the_dask_configuration_in_scale_md_is_dask_settings_and_dask_knows_each_key():
    # the YAML that docs/scale.md gives for `dask worker` is dask_settings(), key for key, and
    # every key is one of the installed Dask's own (a renamed key would be silently ignored)
    import dask
    import distributed  # noqa: F401 (loads Dask's distributed defaults into dask.config)
    import yaml

    from bayespsf.parallel import dask_settings

    text = (ROOT / "docs" / "scale.md").read_text()
    (block,) = re.findall(r"```yaml\n(.*?)```", text, re.S)

    def flat(tree, prefix=""):
        for key, value in tree.items():
            if isinstance(value, dict):
                yield from flat(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}", value

    settings = dask_settings()
    assert dict(flat(yaml.safe_load(block))) == settings
    for key in settings:
        dask.config.get(key)  # KeyError if this Dask has no such setting
