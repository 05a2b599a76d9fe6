"""Storage faults over HTTP: a transient fault of the storage under the store root (object storage unreachable,
timing out or throttling; a full disk) is 503 with Retry-After and a message naming the store, never a 500 and
never a 4xx blaming the request (lodcast.faults says which faults pass)."""
from __future__ import annotations

from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from lodcast.faults import storage_fault

__all__ = ["StorageUnavailable", "where", "unavailable", "install"]


class StorageUnavailable(ConnectionError):
    """The storage under a store cannot be used now; the request may be repeated after `retry_after` seconds."""

    status = 503  # what a progressive stream's error line says (service/progressive.py)

    def __init__(self, detail: str, retry_after: int) -> None:
        super().__init__(detail)
        self.detail, self.retry_after = detail, retry_after


def where(settings: Any, volume_id: str | None = None) -> str:
    """The store a fault is in, as a client may read it: a root URL and the volume; on a local root, no server path."""
    if settings.remote:
        return f"{str(settings.root).rstrip('/')}/{volume_id}" if volume_id else str(settings.root)
    return f"volume {volume_id!r} (the store root's disk)" if volume_id else "the store root's disk"


def unavailable(settings: Any, exc: BaseException, volume_id: str | None = None) -> StorageUnavailable | None:
    """StorageUnavailable naming the store when `exc` is a transient storage fault, else None."""
    why = storage_fault(exc)
    if why is None:
        return None
    return StorageUnavailable(f"storage: {where(settings, volume_id)} is unavailable ({why}); retry in "
                              f"{settings.retry_after_s} s", settings.retry_after_s)


def install(app: FastAPI, settings: Any) -> None:
    """Exception handlers: StorageUnavailable, and any error of the storage stack that escapes a route, as 503 when it
    is a transient fault (anything else keeps the handling it had)."""

    async def answer(request: Request, exc: Exception) -> JSONResponse:
        fault = exc if isinstance(exc, StorageUnavailable) else unavailable(settings, exc)
        if fault is None:
            raise exc
        return JSONResponse({"detail": fault.detail}, status_code=503,
                            headers={"Retry-After": str(fault.retry_after)})

    app.add_exception_handler(StorageUnavailable, answer)
    app.add_exception_handler(OSError, answer)
    for module, names in (("botocore.exceptions", ("BotoCoreError", "ClientError")), ("aiohttp", ("ClientError",))):
        try:
            mod = __import__(module, fromlist=list(names))
        except ImportError:  # a local-only install: no object storage, no such errors
            continue
        for name in names:
            app.add_exception_handler(getattr(mod, name), answer)
