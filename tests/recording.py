"""A test seam for counting work: the scenes a renderer renders from a point on (each progressive stage is one)."""
from __future__ import annotations

from typing import Any

import pytest

import lodcast


def record_renders(monkeypatch: pytest.MonkeyPatch, renderer: Any) -> list[dict]:
    """The scenes (as JSON) `renderer` renders from now on, in order; its renders are otherwise unchanged."""
    seen: list[dict] = []
    plain = renderer.render

    def recorded(store: Any, scene: Any, **kw: Any) -> Any:
        seen.append(lodcast.Scene.parse(scene).model_dump(mode="json"))
        return plain(store, scene, **kw)

    monkeypatch.setattr(renderer, "render", recorded)
    return seen
