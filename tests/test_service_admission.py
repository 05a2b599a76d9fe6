"""Renders wait for a slot in the order they arrived, whichever client and volume they come from (service/app.py:
the FIFO render slots): 4 viewers orbiting 2 volumes, each with one request at a time, are served in turn, so none
starves (benchmarks/bench_many_clients.py measures it on a live server; docs/measurements/many_clients.md)."""
from __future__ import annotations

import asyncio
import json
import threading

from lodcast.service.app import create_app
from lodcast.service.settings import Settings
from lodcast.service.testing import make_volume, tiny_scene


async def _post(app, volume: str, scene: dict) -> int:
    """POST /volumes/VOLUME/render straight into the ASGI app; the response's status."""
    body = [{"type": "http.request", "body": json.dumps(scene).encode(), "more_body": False}]
    status: list[int] = []

    async def receive():
        if body:
            return body.pop()
        await asyncio.Event().wait()  # the client stays connected

    async def send(msg):
        if msg["type"] == "http.response.start":
            status.append(msg["status"])

    path = f"/volumes/{volume}/render"
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(b"content-type", b"application/json")], "client": ("127.0.0.1", 1),
             "server": ("127.0.0.1", 80)}
    await app(scope, receive, send)
    return status[0]


def test_waiting_renders_of_four_clients_on_two_volumes_start_in_arrival_order(tmp_path, monkeypatch):
    for name in ("a", "b"):
        make_volume(tmp_path, name)
    app = create_app(Settings(root=tmp_path, workers=0, token=None, render_concurrency=1, small_render_samples=0))
    engine = app.state.engine
    started: list[tuple[str, float]] = []  # (volume, azimuth) of each render, as it takes its slot
    gate = threading.Event()
    real = engine.render

    def render(path, scene, *a, **k):
        started.append((str(path).rsplit("/", 1)[-1], scene.camera.azimuth))
        if len(started) == 1:
            gate.wait(120)  # the first holds the one slot until every other request waits for it
        return real(path, scene, *a, **k)

    monkeypatch.setattr(engine, "render", render)
    arrived: list[int] = []

    class Arrivals(asyncio.Semaphore):  # the slots, counting the requests that asked for one
        async def acquire(self) -> bool:
            arrived.append(1)
            return await super().acquire()

    monkeypatch.setattr(asyncio, "Semaphore", Arrivals)
    clients = [("a", 10.0), ("b", 20.0), ("a", 30.0), ("b", 40.0), ("a", 50.0), ("b", 60.0)]

    async def until(condition) -> None:
        for _ in range(6000):  # a bound for a broken build, not a timing: each step yields to the server
            if condition():
                return
            await asyncio.sleep(0.01)
        raise AssertionError("the server did not get there")

    async def run() -> list[int]:
        first = asyncio.create_task(_post(app, "a", tiny_scene(16, camera={"azimuth": 0.0, "elevation": 10})))
        await until(lambda: len(started) == 1)
        rest = []
        for k, (volume, azimuth) in enumerate(clients):  # one by one: each waits for the slot before the next comes
            rest.append(asyncio.create_task(_post(app, volume, tiny_scene(16, camera={"azimuth": azimuth,
                                                                                      "elevation": 10}))))
            await until(lambda: len(arrived) == k + 2)
        assert len(started) == 1  # all of them wait for the one slot
        gate.set()
        return await asyncio.gather(first, *rest)

    assert asyncio.run(run()) == [200] * (1 + len(clients))
    assert started == [("a", 0.0), *clients]


def test_small_renders_take_a_free_main_slot_before_their_own(tmp_path, monkeypatch):
    """A render small by its estimate runs in a main slot while one is free and in the small slot only when none
    is: with one main slot, two small renders run together (one in each), and a third waits."""
    make_volume(tmp_path, "a")
    app = create_app(Settings(root=tmp_path, workers=0, token=None, render_concurrency=1,
                              small_render_samples=10**12))
    engine = app.state.engine
    running: list[float] = []
    gate = threading.Event()
    real = engine.render

    def render(path, scene, *a, **k):
        running.append(scene.camera.azimuth)
        gate.wait(120)
        return real(path, scene, *a, **k)

    monkeypatch.setattr(engine, "render", render)

    async def run() -> list[int]:
        tasks = [asyncio.create_task(_post(app, "a", tiny_scene(16, camera={"azimuth": az, "elevation": 10})))
                 for az in (10.0, 20.0, 30.0)]
        for _ in range(6000):  # a bound for a broken build, not a timing
            if len(running) >= 2:
                break
            await asyncio.sleep(0.01)
        for _ in range(50):  # the third stays waiting
            await asyncio.sleep(0.01)
        assert len(running) == 2, running  # one in the main slot, one in the small slot; the third waits
        gate.set()
        return await asyncio.gather(*tasks)

    assert asyncio.run(run()) == [200, 200, 200]
    assert sorted(running) == [10.0, 20.0, 30.0]
