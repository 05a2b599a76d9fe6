"""Launch turns on one device (renderer/frame/render.py: Turns; issue 49, item 4): a small render's commands go
before any further band of a big render, big renders' bands take turns (at most `slots` on the device at once), and
a stream of small renders holds a band back for at most `yield_s`. Order is asserted, never a time."""
from __future__ import annotations

import contextlib
import threading

import numpy as np
import pytest

import lodcast
from lodcast.renderer.frame import render as R


def test_a_band_waits_while_a_small_render_is_under_way() -> None:
    turns = R.Turns(yield_s=600)
    order: list[str] = []
    band = threading.Thread(target=lambda: _band(turns, order))
    with turns.small():
        band.start()
        band.join(0.3)
        assert band.is_alive() and order == []  # held back, not run
        order.append("small")
    band.join(60)
    assert order == ["small", "band"]


@pytest.mark.parametrize("slots", [1, 2])
def test_bands_of_big_renders_take_turns_at_most_slots_at_once(slots: int) -> None:
    turns = R.Turns(slots=slots)
    inside, most, lock = [0], [0], threading.Lock()

    def one() -> None:
        for _ in range(50):
            with turns.band():
                with lock:
                    inside[0] += 1
                    most[0] = max(most[0], inside[0])
                with lock:
                    inside[0] -= 1

    threads = [threading.Thread(target=one) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert 1 <= most[0] <= slots


@pytest.mark.parametrize("slots", [1, 2])
def test_a_band_waits_while_slots_bands_are_on_the_device(slots: int) -> None:
    turns = R.Turns(slots=slots)
    order: list[str] = []
    with contextlib.ExitStack() as held:
        for _ in range(slots):
            held.enter_context(turns.band())
        late = threading.Thread(target=lambda: _band(turns, order))
        late.start()
        late.join(0.3)
        assert late.is_alive() and order == []
        order.append("freed")
    late.join(60)
    assert order == ["freed", "band"]


def test_small_renders_cannot_hold_a_band_back_for_good() -> None:
    turns = R.Turns(yield_s=0.0)
    order: list[str] = []
    with turns.small():  # never let go while the band runs: it goes after yield_s all the same
        t = threading.Thread(target=lambda: _band(turns, order))
        t.start()
        t.join(60)
        assert order == ["band"]


def test_every_band_of_a_big_render_takes_its_turn_and_the_image_is_the_same(monkeypatch) -> None:
    eng = lodcast.Renderer()
    assert isinstance(eng.turns, R.Turns)
    vol = np.random.default_rng(2).random((24, 24, 24)).astype(np.float32)
    scene = {"tf": {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0},
                               {"value": 1, "color": [1, 0.5, 0.2], "opacity": 0.6}]},
             "width": 40, "height": 56, "format": "npy"}
    whole = eng.render(vol, scene)
    seen: list[str] = []
    real = R.Turns.band

    def counted(self):  # type: ignore[no-untyped-def]
        seen.append("band")
        return real(self)

    monkeypatch.setattr(R.Turns, "band", counted)
    monkeypatch.setattr(R, "BAND_SAMPLES", 5_000)
    banded = eng.render(vol, scene)
    assert banded.report["launches"] > 3 and len(seen) == banded.report["launches"]  # every band in its turn
    np.testing.assert_array_equal(banded.rgba, whole.rgba)
    seen.clear()
    monkeypatch.setattr(R, "BAND_SAMPLES", 10**12)
    assert eng.render(vol, scene).report["launches"] == 1 and seen == []  # a small render takes no turn
    eng.close()


def _band(turns: R.Turns, order: list[str]) -> None:
    with turns.band():
        order.append("band")
