"""Every shell command in the README and the user guide runs as written (a new user's
first hour). ``bash`` blocks are commands; plain blocks are usage synopses and are not run.

The user guide's commands run in order in one empty folder with the installed ``bayespsf`` on
the PATH; a ``toml`` block that follows "a `NAME` such as" is written to NAME before the page's
commands run. The
README's first command (set up and run the demo) runs in the repository root, as a new user
types it; its second (set up and run this suite) is what CI runs, so it is checked to be
``.ci/run``'s command verbatim rather than run again from inside the suite.
"""

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GUIDE = sorted((ROOT / "docs").glob("*.md"))
BLOCK = re.compile(r"```(bash|toml)\n(.*?)```", re.S)
WRITE_AS = re.compile(r"a `([\w.-]+)` such as\s*$")


def commands(path: Path):
    """(kind, text, file name for toml) of every bash and toml block of ``path``, in order."""
    text = path.read_text()
    out = []
    for match in BLOCK.finditer(text):
        kind, body = match.groups()
        before = text[: match.start()].rstrip().splitlines()[-1]
        name = WRITE_AS.search(before)
        out.append((kind, body, name.group(1) if name else None))
    return out


def _env():
    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    return env


def _bash(line: str, cwd: Path):
    return subprocess.run(
        ["bash", "-euo", "pipefail", "-c", line],
        cwd=cwd,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )


README = [line for _, body, _ in commands(ROOT / "README.md") for line in body.splitlines()]
# guide commands that another test runs exactly as written (in an empty folder, default
# output folders), and checks more closely than an exit status
RUN_ELSEWHERE = {"bayespsf bench --quick --workers 2": "tests/cli/test_bench.py"}


def test_commands_run_elsewhere_are_documented_and_run_there():
    guide = {
        line
        for page in GUIDE
        for kind, body, _ in commands(page)
        if kind == "bash"
        for line in body.splitlines()
    }
    for line, test in RUN_ELSEWHERE.items():
        assert line in guide and f'DOCUMENTED = "{line}"' in (ROOT / test).read_text()


def test_readme_starts_with_the_two_commands():
    assert len(README) == 2
    assert "bayespsf demo" in README[0] and "pytest" in README[1]
    assert README[1] in (ROOT / ".ci" / "run").read_text().splitlines()


def _copy_of_the_repository(tmp_path: Path) -> Path:
    """The repository's tracked files in ``tmp_path/bayespsf``, with a ``.venv`` that sees the
    suite's installed dependencies through a ``.pth`` file (so that setting it up does not
    download them again)."""
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    copy = tmp_path / "bayespsf"
    for name in filter(None, listed.stdout.decode().split("\0")):
        if (ROOT / name).is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, copy / name)
    subprocess.run([sys.executable, "-m", "venv", copy / ".venv"], check=True)
    site = next((copy / ".venv" / "lib").glob("python3*/site-packages"))
    (site / "suite-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return copy


@pytest.mark.slow
def test_readme_first_command_sets_up_and_runs_the_demo(tmp_path):
    # In a copy of the repository: the command reinstalls bayespsf into the .venv beside it,
    # and the suite's own .venv is in use by the other test processes (pytest-xdist).
    copy = _copy_of_the_repository(tmp_path)
    result = _bash(README[0], copy)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "posterior SD" in result.stdout
    assert (copy / "bayespsf-demo" / "corner.png").stat().st_size > 0
    assert (copy / "bayespsf-demo" / "posterior.nc").stat().st_size > 0
    used = subprocess.run(
        [
            copy / ".venv" / "bin" / "python",
            "-I",
            "-c",
            "import bayespsf; print(bayespsf.__file__)",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert Path(used.stdout.strip()).is_relative_to(copy)  # the copy ran, not the suite's


def test_notebook_commands_run_as_written():
    # from the repository root, where the README's setup puts .venv
    for kind, body, _ in commands(ROOT / "notebooks" / "README.md"):
        for line in body.splitlines() if kind == "bash" else []:
            result = _bash(line, ROOT)
            assert result.returncode == 0, f"{line}\n{result.stderr[-3000:]}"
    assert (ROOT / "notebooks" / "01_single_molecule.ipynb").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.parametrize("page", GUIDE, ids=[p.name for p in GUIDE])
def test_guide_commands_run_as_written(page, tmp_path):
    blocks = commands(page)
    for kind, body, name in blocks:  # the files the page names, before its commands use them
        if kind == "toml" and name is not None:
            (tmp_path / name).write_text(body)
    for kind, body, _ in blocks:
        if kind != "bash":
            continue
        for line in body.splitlines():
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            if line in README or line in RUN_ELSEWHERE:  # run as written by other tests
                continue
            result = _bash(line, tmp_path)
            assert result.returncode == 0, f"{page.name}: {line}\n{result.stderr[-3000:]}"
