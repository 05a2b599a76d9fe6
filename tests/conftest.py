"""Shared fixtures. Real volumes live in ../shared/data beside the checkout (CI has it, users do not)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("LODCAST_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real test volumes. Outside CI its absence skips the test with a clear reason; in CI
    (CI=true) it is an error, so that a test needing real data can never pass by not running."""
    if not (SHARED_DATA / "README.md").is_file():
        msg = f"real test volumes not found at {SHARED_DATA} (set LODCAST_SHARED_DATA or place ../shared/data beside the checkout)"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg)
        pytest.skip(msg)
    return SHARED_DATA


@pytest.fixture(scope="module")
def renderer():
    """A renderer of this test module's own (tests that count what its caches hold make one per test instead)."""
    from lodcast.renderer.frame.render import Renderer

    eng = Renderer()
    yield eng
    eng.close()


@pytest.fixture
def eng():
    """A renderer of the test's own: its caches start empty and no other test sees them."""
    from lodcast.renderer.frame.render import Renderer

    r = Renderer()
    yield r
    r.close()
