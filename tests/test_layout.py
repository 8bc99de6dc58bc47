"""The package's layers: data flows model -> instrument -> identify -> position -> study, with
diagnose beside identify and position (the library), then the jobs (one per command) and the
command line over them. A module may import its own sub-package, the shared leaves and the layers
below it, never a layer above (no library module imports the jobs; the command line imports the
jobs and the leaves alone); module-level imports form no cycle. The library takes typed
arguments: no library function takes a whole command config, and no public function returns a
tuple of more than three values. Checked from the source (``ast``), not from what happens to be
imported."""

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
    "jobs": {"model", "instrument", "identify", "position", "diagnose", "study"},
    "cli": {"jobs"},
}
LIBRARY = {"model", "instrument", "identify", "position", "diagnose", "study"} | LEAVES - {"config"}


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
    if layer == "":
        return  # the package's public names may come from every layer
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


def _command_configs() -> set:
    """The names of the commands' config schemas and of the schemas they extend (a positioning
    run's and a study's common base): whole command configs."""
    from jaxafm.config.common import Strict
    from jaxafm.jobs import JOBS

    return {
        cls.__name__
        for job in JOBS.values()
        for cls in job.schema.__mro__
        if issubclass(cls, Strict) and cls is not Strict
    }


def _names(annotation) -> set:
    """Every name an annotation mentions (``Optional[RunConfig]``, ``"config.RunConfig"``, ...)."""
    if annotation is None:
        return set()
    if isinstance(annotation, ast.Constant) and isinstance(annotation.value, str):
        return _names(ast.parse(annotation.value, mode="eval").body)
    return {n.id for n in ast.walk(annotation) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(annotation) if isinstance(n, ast.Attribute)
    }


def _functions(tree: ast.Module, nested: bool = True):
    """(qualified name, node) of every function and method of a module (``nested``: and the
    functions defined inside them)."""

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield prefix + child.name, child
                if nested:
                    yield from visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, f"{prefix}{child.name}.")

    yield from visit(tree, "")


LIBRARY_MODULES = sorted((name, path) for path, name, _ in _modules() if _layer(name) in LIBRARY)


@pytest.mark.parametrize("module, path", LIBRARY_MODULES, ids=[".".join(m) for m, _ in LIBRARY_MODULES])
def test_no_library_function_takes_a_whole_config(module, path):
    """A library function takes typed arguments: none is annotated with a command's config
    schema (or its base), and none has a parameter named ``cfg`` (the jobs' name for one)."""
    whole = _command_configs()
    bad = []
    for name, fn in _functions(ast.parse(path.read_text())):
        a = fn.args
        for arg in a.posonlyargs + a.args + a.kwonlyargs + [a.vararg, a.kwarg]:
            if arg is not None and (arg.arg == "cfg" or _names(arg.annotation) & whole):
                bad.append(f"{name}({arg.arg})")
    assert not bad, f"{'.'.join(module)}: functions that take a whole config: {bad}"


#: public functions that return more than three values, and why
WIDE_RETURNS = {
    "jaxafm.instrument.images.AFMImage.extent": "matplotlib's imshow extent (left, right, bottom, top)",
}


def _returns(fn) -> list:
    """The number of values of each ``return a, b, ...`` of ``fn`` itself (not of nested
    functions), and of its ``-> tuple[...]`` annotation."""
    counts = []
    if isinstance(fn.returns, ast.Subscript) and isinstance(fn.returns.slice, ast.Tuple):
        counts.append(len(fn.returns.slice.elts))
    stack = list(fn.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            continue
        if isinstance(node, ast.Return) and isinstance(node.value, ast.Tuple):
            counts.append(len(node.value.elts))
        stack.extend(ast.iter_child_nodes(node))
    return counts


def test_no_public_function_returns_more_than_three_values():
    """Across a module boundary, more than three results travel as a typed result (an equinox
    Module or a dataclass), not a tuple whose order every caller must know."""
    bad = []
    for path, module, _ in _modules():
        for name, fn in _functions(ast.parse(path.read_text()), nested=False):
            public = not any(part.startswith("_") for part in name.split("."))
            where = ".".join(module + (name,))
            if public and max(_returns(fn), default=0) > 3 and where not in WIDE_RETURNS:
                bad.append(where)
    assert not bad, f"public functions returning more than three values: {bad}"
