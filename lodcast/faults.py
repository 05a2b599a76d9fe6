"""Storage faults that heal: what tells a transient failure of the storage under a store (object storage unreachable,
timing out or throttling; a full disk) from a permanent one (no such object, a damaged file, a bad request).

A transient fault is answered 503 with Retry-After by the service and retried by jobs; anything else keeps its own
meaning. The exception is judged with everything it was raised from (``__cause__``, ``__context__``), because the
libraries between lodcast and the network wrap one another: zarr's open in lodcast's StoreInvalid, botocore's
connection errors in s3fs' OSError, aiohttp's in botocore's.
"""
from __future__ import annotations

import errno

__all__ = ["storage_fault", "TRANSIENT_ERRNOS", "THROTTLE_CODES"]

#: errno values of faults that pass: the disk full or over quota, a connection refused, reset, timed out or
#: unreachable; s3fs turns S3's 503 (SlowDown, ServiceUnavailable) into EBUSY
TRANSIENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EBUSY, errno.EAGAIN, errno.ETIMEDOUT,
                              errno.ECONNREFUSED, errno.ECONNRESET, errno.ECONNABORTED, errno.EPIPE,
                              errno.EHOSTUNREACH, errno.ENETUNREACH, errno.ENETDOWN})

#: error codes of object storage that say "not now" (S3's and its look-alikes')
THROTTLE_CODES = frozenset({"SlowDown", "Throttling", "ThrottlingException", "RequestLimitExceeded",
                            "ServiceUnavailable", "RequestTimeout", "InternalError", "500", "503"})

# connection and timeout errors of the HTTP stack under s3fs, by (module prefix, class name): checked by name so
# that this module imports neither botocore nor aiohttp (a local-only install has neither)
_NETWORK = frozenset({"EndpointConnectionError", "ConnectionClosedError", "ConnectTimeoutError", "ReadTimeoutError",
                      "ConnectionError", "HTTPClientError", "ProxyConnectionError", "ClientConnectionError",
                      "ClientConnectorError", "ServerDisconnectedError", "ServerTimeoutError", "ClientOSError",
                      "ClientPayloadError", "FSTimeoutError"})
_LIBRARIES = ("botocore.", "aiobotocore.", "aiohttp.", "urllib3.", "fsspec.", "s3fs.")


def _one(exc: BaseException) -> str | None:
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return "no space left on the device"
    if isinstance(exc, OSError) and exc.errno == errno.EDQUOT:
        return "disk quota exceeded"
    if isinstance(exc, (TimeoutError, ConnectionError)):
        return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    if isinstance(exc, OSError) and exc.errno in TRANSIENT_ERRNOS:
        return str(exc.strerror or exc)
    kind = type(exc)
    if kind.__module__.startswith(_LIBRARIES) and any(c.__name__ in _NETWORK for c in kind.__mro__):
        return f"{kind.__name__}: {exc}"
    code = getattr(exc, "response", None)
    if isinstance(code, dict):  # botocore's ClientError
        err = code.get("Error") or {}
        if str(err.get("Code", "")) in THROTTLE_CODES:
            return f"{err.get('Code')}: {err.get('Message', '')}".rstrip(": ")
    return None


def storage_fault(exc: BaseException) -> str | None:
    """A one-line reason when `exc` (or what it was raised from) is a transient storage fault, else None."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        why = _one(cur)
        if why is not None:
            return " ".join(why.split())[:300]
        cur = cur.__cause__ or cur.__context__
    return None
