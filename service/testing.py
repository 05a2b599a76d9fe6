"""Helpers for the tests, benchmarks and smoke script: a tiny volume, a real redis-server, a real S3-compatible
server (moto's server mode, behind a counting proxy), a live `lodcast serve` / `lodcast worker` on loopback (each in
its own process group, stopped by group), and the system's headless Chromium driven through selenium (the web
viewer's tests and benchmark)."""
from __future__ import annotations

import contextlib
import http.client
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Iterator

__all__ = [
    "TINY_TF",
    "tiny_scene",
    "make_volume",
    "wait_job",
    "free_port",
    "redis_available",
    "RedisServer",
    "S3Server",
    "s3_server",
    "Proc",
    "start_serve",
    "start_worker",
    "in_ci",
    "CHROMIUM",
    "CHROMEDRIVER",
    "chromium",
    "page_wait",
    "pointer_drag",
]

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"

TINY_TF = {"points": [{"value": 0, "color": [0.2, 0.4, 1.0], "opacity": 0.0},
                      {"value": 1000, "color": [1.0, 0.9, 0.8], "opacity": 0.6}]}


def tiny_scene(size: int = 16, **extra: Any) -> dict[str, Any]:
    return {"camera": {"azimuth": 30, "elevation": 20}, "width": size, "height": size, "tf": TINY_TF,
            "sampling": {"step": 1.0}, **extra}


def make_volume(root: Path, name: str = "tiny", n: int = 24, block_size: int = 8) -> Path:
    """Two Gaussian blobs in n³ float32 voxels (values 0..1000) ingested as ROOT/NAME."""
    import numpy as np

    import lodcast

    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    c = (n - 1) / 2
    blob = 1000 * np.exp(-((z - c) ** 2 + (y - c) ** 2 + (x - c) ** 2) / (n * n / 10))
    # an off-centre second blob, so that views from different azimuths differ
    blob2 = 800 * np.exp(-((z - c) ** 2 + (y - 0.3 * n) ** 2 + (x - 0.8 * n) ** 2) / (n * n / 60))
    v = np.maximum(blob, blob2).astype(np.float32)
    lodcast.ingest(v, Path(root) / name, block_size=block_size)
    return Path(root) / name


def service_folders(base: Path, source: str, data: Any) -> tuple[Path, Path]:
    """(store root, import root) under `base`: the root holding the volume "tiny" (make_volume), the import root
    one NumPy source `source` holding `data`."""
    import numpy as np

    root, imports = Path(base) / "root", Path(base) / "imports"
    root.mkdir()
    imports.mkdir()
    make_volume(root, "tiny")
    np.save(imports / source, data)
    return root, imports


def wait_job(client: Any, job_id: str, timeout: float = 120.0) -> dict[str, Any]:
    """The status of a job once it ended, polled over HTTP (a TestClient or an httpx client); AssertionError after
    `timeout` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        st = client.get(f"/jobs/{job_id}").json()
        if st["state"] in ("done", "failed", "cancelled"):
            return st
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} still {st['state']} after {timeout} s")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def redis_available() -> str | None:
    """Path of redis-server, or None."""
    return shutil.which("redis-server") or next(
        (p for p in ("/usr/bin/redis-server", "/usr/sbin/redis-server") if os.access(p, os.X_OK)), None)


class Proc:
    """A child process in its own session (process group); ``stop()`` signals the whole group."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None, log: Path | None = None) -> None:
        self.args = args
        self.log = log
        out = open(log, "ab") if log else subprocess.DEVNULL
        self.p = subprocess.Popen(args, env={**os.environ, **(env or {})}, stdout=out, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, start_new_session=True)
        if log:
            out.close()  # type: ignore[union-attr]

    @property
    def pid(self) -> int:
        return self.p.pid

    def kill(self, sig: int = signal.SIGKILL) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.p.pid, sig)

    def stop(self, timeout: float = 15.0) -> int | None:
        if self.p.poll() is None:
            self.kill(signal.SIGTERM)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                pass
        self.kill(signal.SIGKILL)  # anything left in the group
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.p.wait(5)
        return self.p.returncode

    def tail(self, n: int = 4000) -> str:
        if self.log and self.log.exists():
            return self.log.read_text(errors="replace")[-n:]
        return ""


class RedisServer:
    """A throwaway redis-server on a loopback port, with no persistence."""

    def __init__(self, workdir: Path) -> None:
        exe = redis_available()
        if exe is None:
            raise RuntimeError("redis-server not found (Debian package redis-server)")
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        workdir.mkdir(parents=True, exist_ok=True)
        self.proc = Proc([exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                          "--dir", str(workdir)], log=workdir / "redis.log")
        import redis

        client = redis.Redis(host="127.0.0.1", port=self.port)
        for _ in range(200):
            try:
                if client.ping():
                    break
            except redis.ConnectionError:
                time.sleep(0.05)
        else:
            self.proc.stop()
            raise RuntimeError(f"redis-server did not start: {self.proc.tail()}")
        client.close()

    def stop(self) -> None:
        self.proc.stop()


@dataclass
class S3Server:
    endpoint: str  # the proxy's URL: what clients use (AWS_ENDPOINT_URL)
    requests: list = field(default_factory=list)  # (method, path, range header, response bytes)
    lock: threading.Lock = field(default_factory=threading.Lock)
    # an outage to play: None (pass requests on), "cut" (the connection closed without an answer, as a network
    # that drops it) or "slowdown" (503 SlowDown, S3's throttling answer)
    fault: str | None = None

    def reset(self) -> None:
        with self.lock:
            self.requests.clear()

    def counts(self) -> tuple[int, int]:
        """(requests, response body bytes) since the last reset."""
        with self.lock:
            return len(self.requests), sum(r[3] for r in self.requests)


def _proxy(server: S3Server, upstream_port: int) -> ThreadingHTTPServer:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args: Any) -> None:
            pass

        def _forward(self) -> None:
            n = int(self.headers.get("Content-Length") or 0)
            body = self.rfile.read(n) if n else None
            if server.fault == "cut":
                self.close_connection = True
                self.connection.shutdown(socket.SHUT_RDWR)
                return
            if server.fault == "slowdown":
                msg = b"<Error><Code>SlowDown</Code><Message>Please reduce your request rate.</Message></Error>"
                self.send_response(503, "Slow Down")
                self.send_header("Content-Length", str(len(msg) if self.command != "HEAD" else 0))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(msg)
                return
            conn = http.client.HTTPConnection("127.0.0.1", upstream_port, timeout=60)
            headers = {k: v for k, v in self.headers.items() if k.lower() != "connection"}
            conn.request(self.command, self.path, body=body, headers=headers)
            resp = conn.getresponse()
            data = resp.read()
            self.send_response(resp.status, resp.reason)
            head = self.command == "HEAD"  # its Content-Length is the object's, with no body
            for k, v in resp.getheaders():
                if k.lower() not in ("transfer-encoding", "connection") and (head or k.lower() != "content-length"):
                    self.send_header(k, v)
            if not head:
                self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            with server.lock:  # counted before the client has the answer, so a reset after it cannot race it
                server.requests.append((self.command, self.path, self.headers.get("Range"), len(data)))
            if not head:
                self.wfile.write(data)
            conn.close()

        do_GET = do_PUT = do_POST = do_HEAD = do_DELETE = _forward

    return ThreadingHTTPServer(("127.0.0.1", 0), Handler)


def _forget_s3_clients() -> None:
    with contextlib.suppress(ImportError):
        import s3fs

        s3fs.S3FileSystem.clear_instance_cache()


@contextlib.contextmanager
def s3_server() -> Iterator[S3Server]:
    """moto's S3 on loopback behind the counting proxy, with the AWS environment variables a client needs (dummy
    credentials, AWS_ENDPOINT_URL) set while it runs."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    httpd = None
    saved = {k: os.environ.get(k) for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION",
                                            "AWS_ENDPOINT_URL")}
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("moto's S3 server did not start")
                time.sleep(0.1)
        srv = S3Server("")
        httpd = _proxy(srv, port)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        srv.endpoint = f"http://127.0.0.1:{httpd.server_address[1]}"
        os.environ.update(AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing", AWS_DEFAULT_REGION="us-east-1",
                          AWS_ENDPOINT_URL=srv.endpoint)
        _forget_s3_clients()  # fsspec keeps filesystems per arguments, not per endpoint: one of an earlier server
        yield srv
    finally:
        _forget_s3_clients()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        if httpd is not None:
            httpd.shutdown()
        proc.terminate()
        proc.wait(10)


def _lodcast() -> list[str]:
    return [sys.executable, "-m", "lodcast.service.cli"]


def start_serve(root: Path, port: int, *, queue: str | None = None, env: dict[str, str] | None = None,
                log: Path | None = None, extra: list[str] | None = None, wait: float = 60.0) -> Proc:
    args = [*_lodcast(), "serve", "--root", str(root), "--port", str(port), *(["--queue", queue] if queue else []), *(extra or [])]
    proc = Proc(args, env=env, log=log)
    import httpx

    end = time.monotonic() + wait
    while time.monotonic() < end:
        if proc.p.poll() is not None:
            raise RuntimeError(f"lodcast serve exited {proc.p.returncode}: {proc.tail()}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.1)
    proc.stop()
    raise RuntimeError(f"lodcast serve did not answer within {wait} s: {proc.tail()}")


def start_worker(root: Path, *, queue: str | None = None, env: dict[str, str] | None = None, log: Path | None = None) -> Proc:
    return Proc([*_lodcast(), "worker", "--root", str(root), *(["--queue", queue] if queue else [])], env=env, log=log)


@contextlib.contextmanager
def running(*procs: Proc) -> Iterator[None]:
    try:
        yield
    finally:
        for p in procs:
            p.stop()


@contextlib.contextmanager
def chromium(downloads: Path | None = None, size: tuple[int, int] = (1280, 900)) -> Iterator[Any]:
    """Debian's headless Chromium through its chromedriver (selenium; `chromium` and `chromium-driver` from apt),
    its console log kept (driver.get_log("browser")), downloads into `downloads` when given."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={size[0]},{size[1]}"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        if downloads is not None:
            driver.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
        yield driver
    finally:
        driver.quit()


def page_wait(driver: Any, script: str, timeout: float = 60.0) -> Any:
    """Polls the page until `script` (JavaScript, with a `return`) gives a true value, and returns it; TimeoutError
    with the viewer's status line after `timeout` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = driver.execute_script(script)
        if got:
            return got
        time.sleep(0.02)
    status = driver.execute_script("const s = document.getElementById('status'); return s && s.textContent")
    raise TimeoutError(f"timed out waiting for: {script} (status: {status})")


def pointer_drag(driver: Any, element: Any, start: tuple[float, float], moves: list[tuple[int, int]],
                 pause: float = 0.05, hold: str | None = None, timeout: float = 60.0) -> None:
    """A mouse drag: press at `start` (CSS pixels from the element's top left), move by each step with `pause` s
    between, and release once the script `hold` is true (the user keeps the button down until then)."""
    from selenium.webdriver.common.action_chains import ActionChains

    rect = element.rect
    chain = ActionChains(driver, duration=0)
    chain.move_to_element_with_offset(element, int(start[0] - rect["width"] / 2), int(start[1] - rect["height"] / 2))
    chain.click_and_hold()
    for dx, dy in moves:
        chain.move_by_offset(dx, dy).pause(pause)
    chain.perform()
    if hold:
        page_wait(driver, hold, timeout)
    ActionChains(driver, duration=0).release().perform()
