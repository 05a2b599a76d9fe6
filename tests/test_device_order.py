"""A small render is not served behind big ones on the device (issue 49, item 4).

PoCL's CPU device runs the commands of all queues in the order they came; big renders are launched in bands that take
turns on the device, and a render of one band goes before any further band (renderer/frame/render.py: Turns), so a
small render queued while three big ones are in flight runs after the bands already on the device when it came. The
test asserts the order (the small render finishes first), not a time; benchmarks/bench_small_render.py measures the
wait."""
from __future__ import annotations

import threading

from phantoms import head

import lodcast

TF = {"points": [{"value": 0, "color": [1, 1, 1], "opacity": 0.0}, {"value": 200, "color": [1, 0.8, 0.6], "opacity": 0.05}]}
BIG = {"camera": {"azimuth": 30, "elevation": 10, "distance": 2.5}, "width": 384, "height": 384, "tf": TF,
       "quality": "full", "sampling": {"step": 0.2, "early_termination": 1.0}}
SMALL = {**BIG, "width": 32, "height": 32, "sampling": {"step": 0.5}}


def test_small_render_finishes_before_three_big_ones_in_flight(tmp_path, eng, monkeypatch):
    import lodcast.renderer.frame.render as render_module

    monkeypatch.setattr(render_module, "BAND_SAMPLES", 3_000_000)  # the bands of a big render, at a test's size
    store = lodcast.ingest(head(64), tmp_path / "head.zarr")
    eng.render(store, SMALL)  # kernel built, bricks read: what follows is the device alone
    assert eng.check_cost(store, BIG, 10**12) > 8 * render_module.BAND_SAMPLES  # several bands each
    finished: list[str] = []
    started = [threading.Event() for _ in range(3)]
    lock = threading.Lock()

    def run(name: str, scene: dict, first_band: threading.Event | None = None) -> None:
        eng.render(store, scene, stop=None if first_band is None else first_band.set)
        with lock:
            finished.append(name)

    bigs = [threading.Thread(target=run, args=(f"big{i}", BIG, started[i])) for i in range(3)]
    for t in bigs:
        t.start()
    for e in started:  # each big render's first band has run: all three are in flight
        assert e.wait(120)
    small = threading.Thread(target=run, args=("small", SMALL))
    small.start()
    for t in [*bigs, small]:
        t.join(300)
    assert finished[0] == "small", finished
    assert sorted(finished) == ["big0", "big1", "big2", "small"]

