"""The package's layers: data flows model -> instrument -> identify -> position -> study, with
diagnose beside identify and position, and the command line on top. A module may import its own
sub-package, the shared leaves and the layers below it, never a layer above; module-level imports
form no cycle. Checked from the source (``ast``), not from what happens to be imported."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxafm"
LEAVES = {"config", "checks", "plots", "_precision", "_version", "data"}
BELOW = {
    "model": set(),
    "instrument": {"model"},
    "identify": {"model", "instrument"},
    "position": {"model", "instrument", "identify"},
    "diagnose": {"model", "instrument", "identify"},
    "study": {"model", "instrument", "identify", "position"},
    "cli": {"model", "instrument", "identify", "position", "diagnose", "study"},
}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        yield path, ("jaxafm",) + tuple(p for p in parts if p != "__init__"), path.name == "__init__.py"


def _imports(path: Path, name: tuple, is_package: bool):
    """(imported module as a tuple of names, module level?) for every import of jaxafm code."""
    tree = ast.parse(path.read_text())
    top = set(map(id, tree.body))
    base = name if is_package else name[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level:
            origin = base[: len(base) - node.level + 1]
            target = origin + tuple(node.module.split(".")) if node.module else origin
            subs = [()] if node.module else [(a.name,) for a in node.names]
            for s in subs:
                yield target + s, id(node) in top
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            for m in mods:
                if m and m.split(".")[0] == "jaxafm":
                    yield tuple(m.split(".")), id(node) in top


def _layer(name: tuple) -> str:
    return name[1] if len(name) > 1 else ""


GRAPH = {name: list(_imports(path, name, pkg)) for path, name, pkg in _modules()}


@pytest.mark.parametrize("module", sorted(GRAPH), ids=".".join)
def test_no_module_imports_a_higher_layer(module):
    layer = _layer(module)
    if layer in ("", "cli"):
        return  # the package's public names and the command line may import every layer
    allowed = {layer} | LEAVES | BELOW.get(layer, set())
    if layer in LEAVES:
        allowed = {layer} if layer == "config" else LEAVES  # checking a YAML file imports no JAX code
    bad = sorted({".".join(t) for t, _ in GRAPH[module] if _layer(t) not in allowed})
    assert not bad, f"{'.'.join(module)} (layer {layer!r}) imports {bad}; allowed: {sorted(allowed)}"


def test_every_subpackage_is_a_known_layer():
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert found <= set(BELOW) | LEAVES, f"unknown layers {sorted(found - set(BELOW) - LEAVES)}"


def test_module_level_imports_form_no_cycle():
    known = set(GRAPH)

    def resolve(t):  # 'from . import x' names a module when x is one, else the package
        while t and t not in known:
            t = t[:-1]
        return t

    edges = {m: {resolve(t) for t, top in GRAPH[m] if top} - {m} for m in GRAPH}
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for n in edges[m]:
            if state.get(n) == "open":
                cycle = stack[stack.index(n) :] + [n]
                pytest.fail("import cycle: " + " -> ".join(".".join(c) for c in cycle))
            if n not in state:
                visit(n, stack + [n])
        state[m] = "done"

    for m in sorted(GRAPH):
        if m not in state:
            visit(m, [m])


def test_the_public_names_have_one_list():
    """``jaxafm``'s public names are the keys of its ``_HOMES`` (``__all__`` is derived from it),
    and the ``TYPE_CHECKING`` imports that static tools read name the same names from the same
    modules. Read from the source, as the static tools read it."""
    tree = ast.parse((PACKAGE / "__init__.py").read_text())
    homes = next(
        ast.literal_eval(n.value)
        for n in tree.body
        if isinstance(n, ast.Assign) and any(getattr(t, "id", None) == "_HOMES" for t in n.targets)
    )
    static = next(
        n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING"
    )
    imported = {a.asname or a.name: node.module for node in static.body for a in node.names}
    assert imported == homes
    import jaxafm

    assert jaxafm.__all__ == sorted(homes)
