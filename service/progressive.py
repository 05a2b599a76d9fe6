"""Progressive renders over HTTP: ``POST /volumes/{id}/render?progressive=true`` answers `application/x-ndjson`, one
line per stage, ``{"stage", "final", "report", "image"}`` (the image base64 in the scene's format, every stage the
scene's size, the last the plain render's image), coarse to fine (renderer/frame/progressive.py).

The first stage renders before the response starts, so that what the plain route refuses (a damaged store, a scene
this volume cannot take) is refused with the same status; a later stage that fails ends the stream with one line
``{"error": {"status", "detail"}}``. A stream ends early, without its final stage, when its client hangs up or
when a newer progressive request names the same ``X-Lodcast-Session``: `Sessions` (one per service process, kept
by its RenderEngine) cancels the stages still to come of the older one, and the stage it is rendering stops between
launch bands and is not sent.
"""
from __future__ import annotations

import base64
import json
import threading
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

from lodcast.renderer.image.output import RenderResult
from lodcast.service.rendering import RequestInvalid, encode, finite_json

__all__ = ["Sessions", "stage_line", "error_line", "stream"]


class Sessions:
    """The progressive stream under way per session (the `X-Lodcast-Session` header), each as the event that
    cancels it: a stream's entry goes when it ends, so this holds no more than the streams running."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._live: dict[str, threading.Event] = {}

    def begin(self, session: str | None) -> threading.Event:
        """A new stream's cancel event; a stream of the same session still running is cancelled."""
        cancel = threading.Event()
        if session:
            with self._lock:
                older = self._live.get(session)
                self._live[session] = cancel
            if older is not None:
                older.set()
        return cancel

    def end(self, session: str | None, cancel: threading.Event) -> None:
        """The stream of `cancel` is over (its session's entry goes unless a newer stream holds it)."""
        if session:
            with self._lock:
                if self._live.get(session) is cancel:
                    del self._live[session]

    def __len__(self) -> int:
        with self._lock:
            return len(self._live)


def stage_line(result: RenderResult, scene: Any) -> bytes:
    """One stage as its line: number, whether final, report, and the image in the scene's format, base64."""
    data, _ = encode(result, scene)
    report = dict(result.report)
    line = {"stage": report["stage"], "final": report["final"], "report": finite_json(report),
            "image": base64.b64encode(data).decode("ascii")}
    return json.dumps(line, separators=(",", ":"), default=str).encode() + b"\n"


def error_line(status: int, detail: Any) -> bytes:
    return json.dumps({"error": {"status": status, "detail": detail}}, separators=(",", ":"), default=str).encode() + b"\n"


async def stream(first: RenderResult, stages: int, scene: Any, render: Callable[[int], Awaitable[RenderResult]],
                 cancel: threading.Event, done: Callable[[], None]) -> AsyncIterator[bytes]:
    """The lines of a progressive response: `first` (stage 0, rendered already), then stages 1 … stages − 1,
    each by `render(k)` (on a worker thread, in a render slot; it raises once `cancel` is set). Ends quietly when
    `cancel` is set; `done()` when it ends, however it ends. An error of a later stage (an exception with `status`
    and `detail`, or RequestInvalid) is the last line; any other propagates."""
    from fastapi.concurrency import run_in_threadpool

    try:
        yield await run_in_threadpool(stage_line, first, scene)
        for k in range(1, stages):
            if cancel.is_set():
                return
            try:
                result = await render(k)
            except Exception as exc:
                if cancel.is_set():
                    return
                if isinstance(exc, RequestInvalid):
                    yield error_line(422, exc.errors)
                    return
                status = getattr(exc, "status", None)
                if not isinstance(status, int):
                    raise
                yield error_line(status, getattr(exc, "detail", str(exc)))
                return
            if cancel.is_set():  # superseded while it rendered: its picture is not wanted any more
                return
            yield await run_in_threadpool(stage_line, result, scene)
    finally:
        cancel.set()  # a dropped connection cancels the stream here: nothing more of it may render
        done()
