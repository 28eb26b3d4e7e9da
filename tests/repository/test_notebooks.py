"""Every notebook runs top to bottom in a fresh kernel, with small budgets, without errors or
warnings. The notebooks are jupytext py:percent sources (notebooks/*.py); each is converted in
memory and executed with nbclient, the engine nbmake uses, in the notebooks folder."""

import re
from pathlib import Path

import jupytext
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[2] / "notebooks").glob("[0-9]*.py"))
# budgets the tests use (set in each notebook's first cell)
SMALL = {"ESS": "100", "MOLECULES": "6", "IMAGES": "60"}


def shrink(source: str) -> str:
    for name, value in SMALL.items():
        source = re.sub(rf"^{name} = .*$", f"{name} = {value}", source, flags=re.M)
    return source


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path):
    notebook = jupytext.reads(shrink(path.read_text()), fmt="py:percent")
    client = NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": path.parent}}
    )
    client.execute()
    for cell in notebook.cells:
        for output in cell.get("outputs", []):
            if output.get("name") == "stderr":
                assert "Warning" not in output["text"], output["text"]
