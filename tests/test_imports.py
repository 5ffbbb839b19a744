"""The package's import graph: no circles (module-level and function-level imports alike) and
no module importing another's private names."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "diffrax_vi"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]):
    """`(imported module, imported names)` of every `from ... import` of the package in
    `path`, at any depth of the file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "diffrax_vi":
                yield target, [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "diffrax_vi":
                    yield alias.name, []


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        edges = set()
        for target, names in _imports(name, path, modules):
            submodules = [f"{target}.{n}" for n in names if f"{target}.{n}" in modules]
            edges.update(submodules)
            if target in modules and len(submodules) < max(len(names), 1):
                edges.add(target)
        edges.discard(name)
        graph[name] = edges
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_scan_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    graph = _graph()
    assert "diffrax_vi._solver" in graph and graph["diffrax_vi._solver"]  # the scan sees edges
    assert _cycles(graph) == []


def test_no_module_imports_another_modules_private_names():
    modules = _modules()
    found = []
    for name, path in modules.items():
        for target, names in _imports(name, path, modules):
            # a private module of the package is imported by name; a private attribute never
            private = [n for n in names if n.startswith("_") and not n.startswith("__")
                       and f"{target}.{n}" not in modules]
            if private and target != name:
                found.append((name, target, private))
    assert found == []


def _floor(module: str) -> str:
    """The floor a module stands on: its subpackage (`diffrax_vi.oga`), or the module itself
    where it sits directly in the package."""
    parts = module.split(".")
    return ".".join(parts[:2])


def test_no_import_runs_back_up_a_floor():
    """Subpackages and top-level modules, taken as wholes, import in one direction: no
    subpackage imports from a floor that imports it back (the seed policy reads the OGA, so
    the OGA may not read the seed policy's package; the ansatz is below both)."""
    floors: dict[str, set[str]] = {}
    for module, edges in _graph().items():
        if module == "diffrax_vi":  # the package's face re-exports every floor
            continue
        floors.setdefault(_floor(module), set()).update(
            _floor(e) for e in edges if _floor(e) != _floor(module) and e != "diffrax_vi"
        )
    assert "diffrax_vi.oga" in floors["diffrax_vi._seeding"]  # the scan sees floors
    assert _cycles(floors) == []


def test_the_ansatze_do_not_import_the_symbolic_package():
    """The sympy backend of the ansätze stands below them (`diffrax_vi._codegen`); the package
    of sympy-written terms and ansätze builds on the ansätze, not the other way round."""
    upward = {
        (module, edge)
        for module, edges in _graph().items()
        if module.startswith("diffrax_vi._ansatz")
        for edge in edges
        if edge.startswith("diffrax_vi.symbolic")
    }
    assert upward == set()
    assert "diffrax_vi._codegen" in _graph()["diffrax_vi._ansatz.sympy_kernels"]
