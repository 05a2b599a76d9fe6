"""The Python client's retries (issue 10, the client): against a real loopback HTTP server that answers 503 a
given number of times, and against a port where nothing listens."""
from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from lodcast.service.client import Client, ServiceError
from lodcast.service.testing import free_port

HEALTH = {"status": "ok", "version": "9.9", "queue": "sqlite", "components": {}}


class _Flaky:
    """Answers 503 (Retry-After: 0) to the first `fail` requests, then 200 with a JSON body; records methods."""

    def __init__(self, fail: int):
        self.fail, self.seen = fail, []
        outer = self

        class H(BaseHTTPRequestHandler):
            def log_message(self, *a) -> None:
                pass

            def _answer(self) -> None:
                n = int(self.headers.get("Content-Length") or 0)
                if n:
                    self.rfile.read(n)
                outer.seen.append(self.command)
                busy = len(outer.seen) <= outer.fail
                body = json.dumps({"detail": "busy"} if busy else HEALTH).encode()
                self.send_response(503 if busy else 200)
                if busy:
                    self.send_header("Retry-After", "0")
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            do_GET = do_POST = _answer

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), H)
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def close(self) -> None:
        self.httpd.shutdown()


@pytest.fixture
def flaky(request):
    srv = _Flaky(request.param)
    yield srv
    srv.close()


@pytest.mark.parametrize("flaky", [2], indirect=True)
def test_reads_are_retried_on_503(flaky):
    with Client(flaky.url, retries=3) as c:
        t = time.monotonic()
        assert c.health().model_dump() == HEALTH
        assert flaky.seen == ["GET"] * 3
        assert time.monotonic() - t >= 0.25 + 0.5 - 0.05  # backoff 0.25 s, then 0.5 s


@pytest.mark.parametrize("flaky", [5], indirect=True)
def test_retries_end_with_the_servers_error(flaky):
    with Client(flaky.url, retries=2) as c:
        with pytest.raises(ServiceError) as e:
            c.volumes()
    assert e.value.status == 503 and "busy" in str(e.value) and len(flaky.seen) == 3


@pytest.mark.parametrize("flaky", [1], indirect=True)
def test_a_job_submission_is_not_repeated_on_503(flaky):
    with Client(flaky.url, retries=3) as c:
        with pytest.raises(ServiceError):
            c.submit({"kind": "turntable"})
    assert flaky.seen == ["POST"]


@pytest.mark.parametrize("flaky", [1], indirect=True)
def test_renders_are_retried_since_they_change_nothing(flaky):
    with Client(flaky.url, retries=1) as c:
        data, report = c.render_image("v", {"width": 8, "height": 8, "tf": "ct-bone"}, timeout=5)
    assert flaky.seen == ["POST", "POST"] and json.loads(data) == HEALTH


@pytest.mark.parametrize("flaky", [2], indirect=True)
def test_the_async_client_retries_the_same_way(flaky):
    import asyncio

    from lodcast.service.client import AsyncClient

    async def main() -> tuple:
        async with AsyncClient(flaky.url, retries=3) as c:
            t = time.monotonic()
            health = await c.health()
            return health, time.monotonic() - t

    health, took = asyncio.run(main())
    assert health.model_dump() == HEALTH and flaky.seen == ["GET"] * 3 and took >= 0.25 + 0.5 - 0.05


def test_an_unreachable_server_is_tried_again_then_raises():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    with Client(url, retries=2) as c:
        t = time.monotonic()
        with pytest.raises(httpx.ConnectError):
            c.health()
        assert time.monotonic() - t >= 0.25 + 0.5 - 0.05
    with pytest.raises(ValueError, match="retries"):
        Client(url, retries=-1)


def test_every_call_takes_its_own_timeout():
    """A server that accepts and never answers: each call gives up after its own timeout, not the client's 300 s."""
    import socket

    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(8)
        with Client(f"http://127.0.0.1:{srv.getsockname()[1]}", retries=0) as c:
            for call in (lambda: c.health(timeout=0.3), lambda: c.volumes(timeout=0.3), lambda: c.job("0" * 32, timeout=0.3),
                         lambda: c.submit({"kind": "turntable"}, timeout=0.3), lambda: c.result("0" * 32, 0, timeout=0.3)):
                t = time.monotonic()
                with pytest.raises(httpx.ReadTimeout):
                    call()
                assert 0.25 < time.monotonic() - t < 3.0
