"""`/healthz` and `/readyz`: each component (the store root, the job queue, the render device) probed by a thread of
its own, off the request path and off the render threads, so that a probe answers from what was last seen, at once,
however loaded the renderer is; a probe that hangs (object storage that stopped answering) makes its component down
once it has run longer than the timeout, without holding the request."""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["Monitor", "Seen", "probes"]


@dataclass
class Seen:
    """What a component's last probe found: `ok` None before the first answer."""

    ok: bool | None = None
    detail: str = "not probed yet"
    at: float = 0.0  # time.time() of the answer
    since: float | None = None  # time.monotonic() when the probe in flight began


class Monitor:
    """Probes `probes` (name -> a function that returns a one-line detail, or raises when the component is down)
    every `every_s` seconds, each on a daemon thread of its own; `timeout_s`: a probe in flight longer is down."""

    def __init__(self, probes: dict[str, Callable[[], str]], every_s: float, timeout_s: float = 2.0) -> None:
        self.probes, self.every_s, self.timeout_s = probes, every_s, timeout_s
        self._seen = {name: Seen() for name in probes}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._started = False

    def start(self) -> "Monitor":
        with self._lock:
            if self._started:
                return self
            self._started = True
        for name in self.probes:
            threading.Thread(target=self._loop, args=(name,), daemon=True, name=f"lodcast-health-{name}").start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def _loop(self, name: str) -> None:
        while not self._stop.is_set():
            with self._lock:
                self._seen[name].since = time.monotonic()
            try:
                ok, detail = True, self.probes[name]()
            except Exception as exc:  # noqa: BLE001 - whatever a probe raises, its component is down
                ok, detail = False, f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
            with self._lock:
                self._seen[name] = Seen(ok, detail, time.time(), None)
            self._stop.wait(self.every_s)

    def components(self) -> dict[str, dict[str, Any]]:
        """name -> {"status": "ok" | "down" | "starting", "detail", "checked" (seconds since the epoch, or null)}."""
        now = time.monotonic()
        out = {}
        with self._lock:
            for name, s in self._seen.items():
                if s.since is not None and now - s.since > self.timeout_s:
                    status, detail = "down", f"no answer for {now - s.since:.1f} s (last: {s.detail})"
                else:
                    status, detail = {None: "starting", True: "ok", False: "down"}[s.ok], s.detail
                out[name] = {"status": status, "detail": detail, "checked": s.at or None}
        return out


def _store_root(settings: Any) -> str:
    if settings.remote:
        import fsspec

        fs, base = fsspec.core.url_to_fs(str(settings.root))
        fs.invalidate_cache(base)
        fs.info(base)  # one small request: a listing of the root would grow with its volumes, every probe
        return f"{settings.root} answers"
    root = Path(settings.root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder")
    st = os.statvfs(root)
    free = st.f_bavail * st.f_frsize
    if free < 64 * 1024**2:  # ingest and job results cannot be written: a full disk is a storage fault
        raise OSError(f"the store root's disk is full ({free} bytes free)")
    return f"{free / 1e9:.1f} GB free"


def probes(settings: Any, jobs: Callable[[], Any], engine: Any) -> dict[str, Callable[[], str]]:
    """The service's components: the store root, the job queue, the render device."""

    def queue() -> str:
        jobs().check()
        return "redis" if settings.is_redis else "sqlite"

    def device() -> str:
        return str(engine.renderer.device.info()["name"])

    return {"store_root": lambda: _store_root(settings), "queue": queue, "device": device}
