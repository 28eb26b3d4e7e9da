"""The declared public API: a literal ``__all__`` in the top level's stub and in every public
subpackage, each name importable, and numpydoc sections on the functions and classes they
export and on those classes' public methods (``Parameters`` where a callable takes arguments,
``Returns`` or ``Yields`` where it gives a value). A method without a docstring inherits the
one it overrides, as ``inspect.getdoc`` reads it; one with its own needs its own sections."""

import ast
import importlib
import inspect
import re
import textwrap
from pathlib import Path

import pytest

import bayespsf

PACKAGE = Path(bayespsf.__file__).parent
SUBPACKAGES = sorted(
    p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists() and p.name[0] != "_"
)


def _literal_all(path: Path) -> list[str] | None:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return ast.literal_eval(node.value)
    return None


def _exports():
    """(where, name, object) of every function and class that a public face exports."""
    seen = {}
    faces = [("bayespsf", bayespsf)] + [
        (f"bayespsf.{s}", importlib.import_module(f"bayespsf.{s}")) for s in SUBPACKAGES
    ]
    for where, module in faces:
        for name in module.__all__:
            obj = getattr(module, name)
            if (inspect.isfunction(obj) or inspect.isclass(obj)) and id(obj) not in seen:
                seen[id(obj)] = (where, name, obj)
    return list(seen.values())


def _needs(obj) -> tuple[bool, bool]:
    """(needs Parameters, needs Returns) for a function or class."""
    target = obj.__init__ if inspect.isclass(obj) else obj
    try:
        signature = inspect.signature(target)
    except (TypeError, ValueError):
        return False, False
    params = [p for p in signature.parameters.values() if p.name not in ("self", "cls")]
    if inspect.isclass(obj):
        if target is object.__init__:
            params = []
        return bool(params), False
    source = inspect.getsource(obj)
    tree = ast.parse(textwrap.dedent(source))
    returns = any(
        isinstance(n, ast.Return) and n.value is not None
        for n in ast.walk(tree.body[0])
        if not isinstance(n, ast.FunctionDef | ast.Lambda) or n is tree.body[0]
    ) or any(isinstance(n, ast.Yield | ast.YieldFrom) for n in ast.walk(tree.body[0]))
    return bool(params), returns


def _documented(obj, doc: str | None = None) -> bool:
    doc = doc or inspect.getdoc(obj) or ""
    need_params, need_returns = _needs(obj)
    ok = True
    if need_params:
        ok &= "Parameters\n----------" in doc or (
            inspect.isclass(obj) and "Attributes\n----------" in doc
        )
    if need_returns:
        ok &= "Returns\n-------" in doc or "Yields\n------" in doc
    return ok


def test_top_level_all_is_declared_literally_and_importable():
    names = _literal_all(PACKAGE / "__init__.pyi")
    assert names is not None and sorted(names) == sorted(bayespsf.__all__)
    for name in names:
        getattr(bayespsf, name)


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_subpackage_all_is_literal_and_importable(name):
    names = _literal_all(PACKAGE / name / "__init__.py")
    assert names, f"bayespsf.{name} declares no literal __all__"
    module = importlib.import_module(f"bayespsf.{name}")
    for export in names:
        assert hasattr(module, export), f"bayespsf.{name}.{export}"


def test_exported_callables_carry_numpydoc_sections():
    missing = [f"{where}.{name}" for where, name, obj in _exports() if not _documented(obj)]
    assert not missing, f"exported without their numpydoc sections: {', '.join(sorted(missing))}"


def _public_methods():
    """(qualified name, function, docstring) of each public method, class method and static
    method that an exported class defines itself (properties and inherited ones aside)."""
    for where, name, cls in _exports():
        if not inspect.isclass(cls):
            continue
        for attr, raw in vars(cls).items():
            function = getattr(raw, "__func__", raw)
            if attr.startswith("_") or not inspect.isfunction(function):
                continue
            yield f"{where}.{name}.{attr}", function, inspect.getdoc(getattr(cls, attr))


def test_public_methods_carry_numpydoc_sections():
    methods = list(_public_methods())
    assert len(methods) > 100  # the reading finds the classes' methods
    missing = [name for name, function, doc in methods if not _documented(function, doc)]
    assert not missing, f"public methods without their numpydoc sections: {', '.join(missing)}"


def _parameter_names(doc: str) -> list[str] | None:
    """The names a numpydoc ``Parameters`` section documents (``a, b : type`` gives both;
    ``**options`` gives ``options``), or None without one."""
    found = re.search(r"Parameters\n----------\n(.*?)(\n\n[A-Z][A-Za-z ]+\n-+\n|\Z)", doc, re.S)
    if found is None:
        return None
    heads = [line.split(" : ")[0] for line in found.group(1).split("\n") if line[:1].strip()]
    return [name.strip().lstrip("*") for head in heads for name in head.split(",")]


def test_parameters_sections_name_exactly_the_signature():
    """A Parameters section names each argument of the signature and nothing else: a renamed
    or added argument shows up here, not in a user's confusion."""
    items = [(f"{where}.{name}", obj, inspect.getdoc(obj)) for where, name, obj in _exports()]
    items += list(_public_methods())
    wrong = []
    for name, obj, doc in items:
        try:
            signature = inspect.signature(obj.__init__ if inspect.isclass(obj) else obj)
        except (TypeError, ValueError):
            continue
        documented = _parameter_names(doc or "")
        arguments = {p for p in signature.parameters if p not in ("self", "cls")}
        if documented is not None and set(documented) != arguments:
            wrong.append(f"{name}: {sorted(arguments)} documented as {sorted(documented)}")
    assert not wrong, "\n".join(wrong)


def test_api_reference_lists_each_exported_callable_by_stage():
    """docs/api.md lists, function by function, every function and class that a subpackage
    exports, and nothing private."""
    text = (PACKAGE.parent / "docs" / "api.md").read_text()
    listed = set(re.findall(r"^::: (bayespsf\.[\w.]+)$", text, re.M))
    expected = {
        f"bayespsf.{s}.{n}"
        for s in SUBPACKAGES
        for n in importlib.import_module(f"bayespsf.{s}").__all__
        if inspect.isfunction(getattr(importlib.import_module(f"bayespsf.{s}"), n))
        or inspect.isclass(getattr(importlib.import_module(f"bayespsf.{s}"), n))
    }
    assert expected <= listed, sorted(expected - listed)
    assert not [name for name in listed if "._" in name], "private names in docs/api.md"
