"""The package's layer rule, checked from the code's own imports.

Subpackages are ordered by data flow, foundations first (docs/decisions.md, Package layout):
a module imports only from its own layer or those before it, and never a private name (a
module or attribute whose name starts with ``_``) of another subpackage. The top-level private
modules ``_validate`` and ``_runtime`` and ``errors`` are the foundation every layer shares.
Function-level imports count as imports. Attribute uses count too: ``obj._name`` outside
``obj``'s own class (not ``self``, ``cls`` or ``super()``) where ``_name`` is defined only in
other subpackages (a camera's private method called from ``inference``).
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "bayespsf"
LAYERS = [
    ("errors", "_validate", "_runtime"),
    ("psf",),
    ("cameras",),
    ("scene",),
    ("model",),
    ("simulation",),
    ("theory",),
    ("inference",),
    ("parallel",),
    ("io",),
    ("movie",),
    ("calibration",),
    ("axial",),
    ("analysis",),
    ("cli",),
]
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}
FOUNDATION = set(LAYERS[0])


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        yield path, parts


def _top_level_homes() -> dict[str, str]:
    """The unit each lazily exported top-level name comes from (``__init__.pyi``)."""
    homes = {}
    for node in ast.parse((PACKAGE / "__init__.pyi").read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            for alias in node.names:
                homes[alias.name] = node.module or alias.name
    return homes


HOMES = _top_level_homes()


def _imports(path: Path, parts: tuple[str, ...]):
    """(unit, names, line) of every import of bayespsf in the module at ``path``."""
    package = ["bayespsf", *parts[:-1]]  # a module and a package's __init__ alike
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            if module.split(".")[0] != "bayespsf":
                continue
            dotted = module.split(".")[1:]
            names = [alias.name for alias in node.names]
            if dotted:
                yield dotted, names, node.lineno
            else:  # from bayespsf import X: a subpackage, a lazily exported name, or metadata
                for name in names:
                    if name == "__version__":
                        continue
                    yield [HOMES.get(name, name).split(".")[0]], [name], node.lineno
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "bayespsf" and "." in alias.name:
                    yield alias.name.split(".")[1:], [], node.lineno


CASES = [
    (path, parts)
    for path, parts in _modules()
    if parts[0] in RANK and not (len(parts) == 1 and parts[0] == "__init__")
]


@pytest.mark.parametrize("path,parts", CASES, ids=["/".join(p) for _, p in CASES])
def test_imports_point_down_and_stay_public(path, parts):
    unit = parts[0]
    problems = []
    for dotted, names, line in _imports(path, parts):
        target = dotted[0]
        if target not in RANK:
            problems.append(f"line {line}: bayespsf.{'.'.join(dotted)} is in no layer")
            continue
        if RANK[target] > RANK[unit]:
            problems.append(
                f"line {line}: {unit} (layer {RANK[unit]}) imports {'.'.join(dotted)} "
                f"(layer {RANK[target]}), which is above it"
            )
        if target != unit and target not in FOUNDATION:
            private = [p for p in dotted[1:] if p.startswith("_")]
            private += [n for n in names if n.startswith("_")]
            if private:
                problems.append(
                    f"line {line}: {unit} uses the private {', '.join(private)} of {target}"
                )
    assert not problems, f"{path.relative_to(PACKAGE.parent)}:\n" + "\n".join(problems)


def _private_names(tree) -> set[str]:
    """The ``_``-prefixed names a module defines: functions, classes, assigned names and
    attributes (``self._x = ...``), imported aliases."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.alias):
            names.add(node.asname or node.name.split(".")[-1])
    return {n for n in names if n.startswith("_") and not n.startswith("__")}


def _foreign_attributes(tree):
    """(line, text, name) of each ``obj._name`` whose ``obj`` is not ``self``, ``cls`` or
    ``super()``."""
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and node.attr.startswith("_")):
            continue
        if node.attr.startswith("__"):
            continue
        owner = node.value
        if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
            continue
        if isinstance(owner, ast.Call) and getattr(owner.func, "id", None) == "super":
            continue
        yield node.lineno, ast.unparse(node), node.attr


TREES = {parts: ast.parse(path.read_text()) for path, parts in _modules()}
DEFINED: dict[str, set[str]] = {}
for _parts, _tree in TREES.items():
    DEFINED.setdefault(_parts[0], set()).update(_private_names(_tree))


def test_no_private_attribute_of_another_subpackage():
    problems = []
    for parts, tree in TREES.items():
        unit = parts[0]
        for line, text, name in _foreign_attributes(tree):
            homes = sorted(u for u, names in DEFINED.items() if name in names and u != unit)
            if homes and name not in DEFINED.get(unit, set()):
                where = "/".join(parts)
                problems.append(f"{where}.py line {line}: {text} is private to {', '.join(homes)}")
    assert not problems, "\n".join(problems)


def test_the_attribute_rule_sees_a_private_method_called_across_subpackages():
    # the rule above, on a line that calls a camera's private method from inference
    tree = ast.parse("def f(model, c, lam):\n    return model.camera._score(c, lam)\n")
    found = [(text, name) for _, text, name in _foreign_attributes(tree)]
    assert found == [("model.camera._score", "_score")]
    assert "_sample" in DEFINED["cameras"] and "_sample" not in DEFINED["inference"]


def test_every_subpackage_and_module_has_a_layer():
    units = {parts[0] for _, parts in _modules() if not parts[0].startswith("__")}
    assert units <= set(RANK), sorted(units - set(RANK))


def test_no_module_over_500_lines():
    long = {
        str(path.relative_to(PACKAGE)): n
        for path, _ in _modules()
        if (n := len(path.read_text().splitlines())) > 500
    }
    assert not long, long


def test_at_most_ten_public_modules_at_the_top():
    public = [
        p.name
        for p in PACKAGE.iterdir()
        if not p.name.startswith("_")
        and (p.suffix == ".py" or (p.is_dir() and (p / "__init__.py").exists()))
    ]
    modules = [name for name in public if name.endswith(".py")]
    assert len(modules) <= 10, modules
