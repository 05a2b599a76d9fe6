"""The package's layers, read from the source (every import, inside functions and under TYPE_CHECKING too): the
store never imports the renderer or the service, the renderer never imports the service, the modules below both
(lodcast/opencl.py, environment.py, errors.py, malloc.py) import neither, and no two renderer modules import each
other, directly or round a longer loop."""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FOLDERS = {"lodcast": "lodcast", "store": "lodcast.store", "renderer": "lodcast.renderer", "service": "lodcast.service"}


def _modules(root: Path = REPO) -> dict[str, Path]:
    out = {}
    for folder, package in FOLDERS.items():
        for path in (root / folder).rglob("*.py"):
            parts = [p for p in path.relative_to(root / folder).with_suffix("").parts if p != "__init__"]
            out[".".join([package, *parts])] = path
    return out


def _imports(path: Path, known: set[str]) -> set[str]:
    """The lodcast modules `path` imports anywhere in it (`from a.b import c` counts a.b.c when that is a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lodcast"):
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in known}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("lodcast")}
    return found


def _graph(root: Path = REPO) -> dict[str, set[str]]:
    mods = _modules(root)
    return {m: _imports(p, set(mods)) for m, p in mods.items()}


def _cycles(graph: dict[str, set[str]], within: str) -> list[list[str]]:
    """The strongly connected components of more than one module among those under `within` (Tarjan)."""
    nodes = [m for m in graph if m.startswith(within)]
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in graph or not w.startswith(within):
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in nodes:
        if v not in index:
            visit(v)
    return out


def _reaching(graph: dict[str, set[str]], below: tuple[str, ...], above: tuple[str, ...]) -> list[str]:
    return sorted(f"{m} imports {t}" for m, ts in graph.items() if m.startswith(below)
                  for t in ts if t.startswith(above))


def test_store_never_imports_the_renderer_or_the_service():
    graph = _graph()
    assert len([m for m in graph if m.startswith("lodcast.renderer.")]) > 40
    assert not _reaching(graph, ("lodcast.store",), ("lodcast.renderer", "lodcast.service"))


def test_the_renderer_never_imports_the_service():
    assert not _reaching(_graph(), ("lodcast.renderer",), ("lodcast.service",))


def test_the_bottom_modules_import_neither_layer():
    bottom = ("lodcast.opencl", "lodcast.environment", "lodcast.errors", "lodcast.malloc")
    assert not _reaching(_graph(), bottom, ("lodcast.store", "lodcast.renderer", "lodcast.service"))


def test_no_import_cycle_inside_the_renderer():
    assert _cycles(_graph(), "lodcast.renderer.") == []


def test_the_checks_see_a_cycle_and_a_lazy_import(tmp_path):
    """The same walk over a planted tree: a loop closed by an import inside a function, and a store module that
    imports the renderer lazily, are both reported."""
    for folder in FOLDERS:
        (tmp_path / folder).mkdir()
    (tmp_path / "renderer" / "a.py").write_text("from lodcast.renderer import b\n")
    (tmp_path / "renderer" / "b.py").write_text("def f():\n    from lodcast.renderer.a import x\n")
    (tmp_path / "store" / "s.py").write_text("def g():\n    import lodcast.renderer.a\n")
    graph = _graph(tmp_path)
    assert _cycles(graph, "lodcast.renderer.") == [["lodcast.renderer.a", "lodcast.renderer.b"]]
    assert _reaching(graph, ("lodcast.store",), ("lodcast.renderer",)) == ["lodcast.store.s imports lodcast.renderer.a"]
