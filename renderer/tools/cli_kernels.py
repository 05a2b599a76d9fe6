"""`lodcast kernels STORE... [--scene scene.json ...]`: build ahead the kernel programs the usual scenes of each
store need (renderer/frame/ahead.py), so that no user's first picture waits for a compiler; one line per program
with where it came from ("built" from source, "disk" from the cache of an earlier process, "memory") and its time."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Callable

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction, func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    p = sub.add_parser("kernels", help="build the kernel programs a store's usual scenes need, before anyone asks "
                       "for a picture (after an ingest, or in a deployment's start-up)")
    p.add_argument("stores", nargs="+", metavar="STORE", help="lodcast stores (folders written by `lodcast ingest`)")
    p.add_argument("--scene", action="append", default=[], metavar="FILE",
                   help="a scene JSON file whose program to build too (repeatable); default: full resolution, "
                        "lossless and 30:1 (nearest block and interblock), unlit and lit")
    p.set_defaults(func=func)
    return p


def run(args: argparse.Namespace) -> int:
    from lodcast.renderer.frame.ahead import AHEAD, AheadBuild
    from lodcast.renderer.frame.render import default_renderer
    from lodcast.renderer.scene.scene import Scene, SceneError
    from lodcast.store.store import open_store

    stores = [open_store(s) for s in args.stores]  # StoreNotFound / StoreInvalid name the path, before any build
    extra = []
    for f in args.scene:
        try:
            extra.append(Scene.parse(json.loads(Path(f).read_text())).model_dump(mode="json", exclude_unset=True))
        except (OSError, json.JSONDecodeError) as exc:
            raise SceneError(f"--scene {f!r}: {exc}") from None
    eng = default_renderer()
    for name, store in zip(args.stores, stores):
        def said(b: AheadBuild, name: str = name) -> None:
            print(f"{name}: {b.source:6s} {b.ms / 1e3:6.1f} s  {' '.join(b.options)}", flush=True)

        eng.build_ahead(store, (*AHEAD, *extra), progress=said)
    return 0
