"""One engine object (lodcast.Renderer): no cache or singleton lives at module level in the package, and two
renderers in one process keep their state apart (what one reads, keeps or drops the other does not see)."""
from __future__ import annotations

import ast
import threading
from pathlib import Path

import numpy as np
import pytest

import lodcast
from lodcast.renderer.frame.render import Renderer, default_renderer

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("lodcast", "renderer", "store", "service")
#: the one module-level object the package keeps on purpose: lodcast.render's default renderer, made on first use
ALLOWED = {("renderer/frame/render.py", "_DEFAULT"), ("renderer/frame/render.py", "_DEFAULT_LOCK")}
#: what makes a module-level value a place where state accumulates
MUTABLE_CALLS = {"dict", "list", "set", "OrderedDict", "defaultdict", "deque", "ByteLru", "Spares", "BrickPool",
                 "WeakKeyDictionary", "WeakValueDictionary", "ThreadPoolExecutor", "local", "count", "Lock",
                 "RLock", "OpenStores", "Renderer", "Engine", "Device"}
CACHE_DECORATORS = {"cache", "lru_cache"}


def _name(node: ast.AST) -> str:
    while isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _module_state(path: Path, root: Path = REPO) -> list[str]:
    """Module-level mutable containers, functools caches and `global` statements in one source file."""
    rel = path.relative_to(root).as_posix()
    tree = ast.parse(path.read_text(), rel)
    found = []
    for node in tree.body:
        targets = []
        if isinstance(node, ast.Assign):
            targets, value = node.targets, node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets, value = [node.target], node.value
        for t in targets:
            name = t.id if isinstance(t, ast.Name) else ast.unparse(t)
            empty = isinstance(value, (ast.Dict, ast.List, ast.Set)) and not getattr(value, "keys", None) and \
                not getattr(value, "elts", None)
            if (empty or (isinstance(value, ast.Call) and _name(value) in MUTABLE_CALLS)) and (rel, name) not in ALLOWED:
                found.append(f"{rel}:{node.lineno} {name} = {ast.unparse(value)[:60]}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Global):
            found.append(f"{rel}:{node.lineno} global {', '.join(node.names)}")
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for d in node.decorator_list:
                if _name(d) in CACHE_DECORATORS:
                    found.append(f"{rel}:{node.lineno} @{ast.unparse(d)} {node.name}")
    return found


def test_no_module_level_state_in_the_package():
    files = [p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))]
    assert len(files) > 40
    found = [f for p in files for f in _module_state(p)]
    assert not found, "state at module level (an engine, renderer/engine.py, should own it):\n" + "\n".join(found)


def test_the_scan_finds_what_it_looks_for(tmp_path):
    """The scan above would see a cache put back (it must be able to fail)."""
    bad = tmp_path / "probe.py"
    bad.write_text("import functools\nfrom collections import OrderedDict\n_KEPT = OrderedDict()\n_SEEN = {}\n"
                   "TABLE = {'a': 1}\n@functools.lru_cache(maxsize=4)\ndef f(x):\n    global _SEEN\n    return x\n")
    found = _module_state(bad, tmp_path)
    assert sorted(f.split(" ", 1)[1].split(" =")[0] for f in found) == [
        "@functools.lru_cache(maxsize=4) f", "_KEPT", "_SEEN", "global _SEEN"]


def test_two_renderers_keep_their_state_apart(tmp_path):
    """Each renderer has its own device context, caches, opened stores and settings; rendering, clearing or
    closing one leaves the other as it was, and both give the same image. lodcast.render's default renderer is
    one more, made once."""
    v = np.random.default_rng(4).random((40, 40, 48)).astype(np.float32)
    path = tmp_path / "v.zarr"
    lodcast.ingest(v, path, block_size=8, progress=False)
    tf = {"points": [{"value": 0.3, "color": [1, 1, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 0.5, 0], "opacity": 0.4}]}
    scene = {"tf": tf, "width": 24, "height": 24, "quality": {"reduction": 6}, "format": "npy"}
    a, b = Renderer(), Renderer(device_budget_mb=0.05)
    assert a.device is not b.device and a.bricks is not b.bricks and a.stores is not b.stores
    ra = a.render(str(path), scene)
    assert len(a.selections) == 1 and len(a.device_cache) > 0 and len(b.selections) == len(b.device_cache) == 0
    rb = b.render(str(path), scene)  # its own reads, in passes under its own budget
    assert rb.report["bricks_read"] == ra.report["bricks_read"] and rb.report["passes"] > ra.report["passes"] == 1
    np.testing.assert_array_equal(ra.rgba, rb.rgba)
    assert a.stores.get(str(path)) is not b.stores.get(str(path))
    assert len(a.lod_plans) == 1 and len(a.digests) > 0
    a.close()
    assert len(a.bricks) == len(a.selections) == len(a.lod_plans) == len(a.digests) == 0
    assert len(b.selections) == 1 and len(b.bricks) > 0
    again = b.render(str(path), scene).report
    assert again["bricks_read"] == 0
    assert default_renderer() is default_renderer() and default_renderer() not in (a, b)
    assert lodcast.Renderer is Renderer


def test_renderers_render_concurrently_without_sharing(tmp_path):
    """Threads with a renderer each (a service's clients, say) get the images one renderer alone gives."""
    v = np.random.default_rng(5).random((32, 32, 32)).astype(np.float32)
    tf = {"points": [{"value": 0.2, "color": [0.2, 0.6, 1], "opacity": 0.0}, {"value": 1.0, "color": [1, 1, 1], "opacity": 0.3}]}
    scenes = [{"tf": tf, "width": 20, "height": 16, "format": "npy", "camera": {"azimuth": az, "elevation": 20}}
              for az in (0, 60, 120, 180)]
    alone = [Renderer().render(v, s).rgba for s in scenes]
    got: dict[int, np.ndarray] = {}

    def run(i: int) -> None:
        got[i] = Renderer().render(v, scenes[i]).rgba

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(scenes))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, ref in enumerate(alone):
        np.testing.assert_array_equal(got[i], ref)


def test_keywords_are_checked_and_shown():
    r = Renderer(device="cpu", device_budget_mb=64, brick_cache_mb=10, device_cache_mb=20)
    assert r.settings.device == "cpu" and r.settings.device_budget_bytes == 64_000_000
    assert r.settings.device_cache_bound == 20 * 2**20 and "device_budget_mb=64.0" in repr(r)
    for bad in ({"device_budget_mb": 0}, {"brick_cache_mb": float("nan")}, {"device_cache_mb": -3}):
        with pytest.raises(lodcast.EnvironmentInvalid, match=next(iter(bad))):
            Renderer(**bad)
