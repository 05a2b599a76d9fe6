"""Renders wait for a slot in the order they arrived, whichever client they come from, except that a render of a
volume already being rendered lets those of other volumes pass (service/slots.py): 4 viewers orbiting 2 volumes,
each with one request at a time, are served in turn, none starves, and two viewers opening a cold volume do not
hold every slot while they read the same bricks (benchmarks/bench_many_clients.py measures it on a live server;
docs/measurements/many_clients.md)."""
from __future__ import annotations

import asyncio
import json
import threading

import pytest

from lodcast.service import slots as slots_module
from lodcast.service.app import create_app
from lodcast.service.settings import Settings
from lodcast.service.slots import Slots
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
    acquire = Slots._acquire

    async def arrive(self, volume):  # counting the requests that asked for a slot
        arrived.append(1)
        return await acquire(self, volume)

    monkeypatch.setattr(slots_module.Slots, "_acquire", arrive)
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


def test_a_volume_being_rendered_lets_the_others_pass_and_then_comes_first():
    """Two slots, both held by renders of volume b (two viewers that opened it together, reading its bricks):
    a third b render and two of a wait, b's first. The first slot freed goes to a, not to the b that arrived
    first (b still runs); once b's renders are done, its waiting one comes first, before the a still waiting
    (a runs)."""

    async def run() -> list[str]:
        slots, order, gates = Slots(2), [], {}

        async def render(name: str) -> None:
            async with slots.slot(name[0]):
                order.append(name)
                gates[name] = asyncio.Event()
                await gates[name].wait()

        async def settle() -> None:
            for _ in range(20):
                await asyncio.sleep(0)

        tasks = [asyncio.create_task(render(n)) for n in ("b1", "b2")]
        await settle()
        for n in ("b3", "a1", "a2"):  # in this order
            tasks.append(asyncio.create_task(render(n)))
            await settle()
        assert order == ["b1", "b2"] and slots.waiting == 3
        gates["b1"].set()
        await settle()
        assert order == ["b1", "b2", "a1"]  # b3 arrived first, but b2 still runs
        gates["b2"].set()
        await settle()
        assert order == ["b1", "b2", "a1", "b3"]  # b has nothing running now; a1 does
        gates["a1"].set()
        await settle()
        assert order == ["b1", "b2", "a1", "b3", "a2"] and slots.waiting == 0
        for n in ("b3", "a2"):
            gates[n].set()
        await asyncio.gather(*tasks)
        return order

    assert asyncio.run(run()) == ["b1", "b2", "a1", "b3", "a2"]


def test_a_render_that_goes_away_while_waiting_gives_up_its_turn():
    async def run() -> list[str]:
        slots, order = Slots(1), []
        hold = asyncio.Event()

        async def render(name: str, wait: asyncio.Event | None = None) -> None:
            async with slots.slot(name):
                order.append(name)
                if wait is not None:
                    await wait.wait()

        first = asyncio.create_task(render("a", hold))
        await asyncio.sleep(0)
        gone = asyncio.create_task(render("b"))
        after = asyncio.create_task(render("c"))
        for _ in range(5):
            await asyncio.sleep(0)
        gone.cancel()  # its client hung up
        await asyncio.sleep(0)
        hold.set()
        await asyncio.gather(first, after)
        with pytest.raises(asyncio.CancelledError):
            await gone
        return order

    assert asyncio.run(run()) == ["a", "c"]
    with pytest.raises(ValueError, match="size"):
        Slots(0)


def test_a_second_render_of_a_volume_waits_while_another_volume_is_in_use():
    """A free slot is not taken by a volume that holds its share while another volume is in use (a render of it
    ended less than linger_s ago: its viewer is about to ask again); alone, a volume takes every slot."""

    async def run() -> None:
        now = [0.0]
        slots, order, gates = Slots(2, linger_s=2.0, clock=lambda: now[0]), [], {}

        async def render(name: str) -> None:
            async with slots.slot(name[0]):
                order.append(name)
                gates[name] = asyncio.Event()
                await gates[name].wait()

        async def settle() -> None:
            for _ in range(20):
                await asyncio.sleep(0)

        a1 = asyncio.create_task(render("a1"))
        await settle()
        gates["a1"].set()
        await a1  # a's viewer has its image; its next request is on the way
        now[0] = 0.5
        b = [asyncio.create_task(render(n)) for n in ("b1", "b2")]
        await settle()
        assert order == ["a1", "b1"] and slots.waiting == 1  # b2 waits with a slot free: it is a's
        a2 = asyncio.create_task(render("a2"))
        await settle()
        assert order == ["a1", "b1", "a2"]
        gates["b1"].set()
        await settle()
        assert order == ["a1", "b1", "a2", "b2"]  # b's first is done: b2 finds its bricks cached
        for n in ("a2", "b2"):
            gates[n].set()
        await asyncio.gather(a2, *b)
        now[0] = 10.0  # a is no longer in use: b alone takes both slots
        b = [asyncio.create_task(render(n)) for n in ("b3", "b4")]
        await settle()
        assert order[-2:] == ["b3", "b4"] and slots.waiting == 0
        for n in ("b3", "b4"):
            gates[n].set()
        await asyncio.gather(*b)

    asyncio.run(run())
