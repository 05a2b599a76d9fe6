"""``lodcast.Client`` and ``lodcast.AsyncClient``: the service's verbs over HTTP (httpx), with typed results.

Both share one description of every request and of how to read its answer (`_Requests`, each a `_Request`) and
one retry policy (`_Api`); `Client` sends them blocking, `AsyncClient` awaiting (its verbs are coroutines, typed as
such). Statuses are `JobStatus`, volumes `VolumeSummary` (a store the server cannot read: `VolumeUnreadable`), health `Health` (service/models.py, the
same models the server's OpenAPI schema is made from); renders are `RenderResult`s as local rendering returns.
Errors raise ServiceError carrying the server's status and message.
"""
from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import sys
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Generic, TypeVar, cast

import httpx
from pydantic import BaseModel

from lodcast.errors import LodcastError
from lodcast.renderer.image.output import RenderResult
from lodcast.renderer.image.report import RenderReport
from lodcast.renderer.scene.scene import SceneLike
from lodcast.service.models import SESSION_HEADER, Health, JobStatus, VolumeListing, VolumeSummary, VolumeUnreadable

__all__ = ["Client", "AsyncClient", "ServiceError"]

FINAL = ("done", "failed", "cancelled")


class ServiceError(LodcastError, ValueError):
    """The server refused a request (4xx) or failed (5xx); ``status`` and ``detail`` are the server's."""

    def __init__(self, status: int, detail: Any, method: str = "", url: str = "") -> None:
        self.status, self.detail = status, detail
        super().__init__(f"{status} from {method} {url}: {_detail_text(detail)}")


def _detail_text(detail: Any) -> str:
    if isinstance(detail, list):
        return "; ".join(str(d.get("msg", d)) if isinstance(d, dict) else str(d) for d in detail)
    return str(detail)


def _scene_dict(scene: SceneLike) -> dict[str, Any]:
    """A scene as its JSON: a Scene, a mapping, or a JSON file's path."""
    if isinstance(scene, BaseModel):
        return scene.model_dump(mode="json")
    if isinstance(scene, (str, os.PathLike)):
        return json.loads(Path(scene).read_text())
    return dict(scene)


#: what `submit` takes as a job: a dict (any mapping) of its JSON, a job model, or a JSON file's path
_Job = Mapping[str, Any] | BaseModel | str | os.PathLike[str]


def _job_dict(job: _Job) -> dict[str, Any]:
    if isinstance(job, (str, os.PathLike)):
        return json.loads(Path(job).read_text())
    return job.model_dump(mode="json") if isinstance(job, BaseModel) else dict(job)


def _t(timeout: float | None) -> dict[str, Any]:
    """A call's own timeout, when it has one (else the client's)."""
    return {} if timeout is None else {"timeout": timeout}


def _checked(r: httpx.Response, method: str, url: str) -> httpx.Response:
    if r.status_code >= 400:
        try:
            detail = r.json().get("detail", r.text)
        except (ValueError, AttributeError):
            detail = r.text
        raise ServiceError(r.status_code, detail, method, url)
    return r


M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


def _model(cls: type[M]) -> Callable[[httpx.Response], M]:
    return lambda r: cls.model_validate(r.json())


def _models(cls: type[M]) -> Callable[[httpx.Response], list[M]]:
    return lambda r: [cls.model_validate(x) for x in r.json()]


def _listing(r: httpx.Response) -> list[VolumeSummary | VolumeUnreadable]:
    from pydantic import TypeAdapter

    return TypeAdapter(list[VolumeListing]).validate_python(r.json())


def _report(r: httpx.Response) -> RenderReport:
    return cast(RenderReport, json.loads(r.headers.get("x-lodcast-report", "{}")))


def _render_result(r: httpx.Response) -> RenderResult:
    import numpy as np

    return RenderResult(np.load(io.BytesIO(r.content), allow_pickle=False), _report(r))


def _stage(line: str, url: str) -> RenderResult:
    """One line of a progressive render's stream (service/progressive.py) as its RenderResult; an error line raises
    ServiceError."""
    import numpy as np

    obj = json.loads(line)
    if "error" in obj:
        raise ServiceError(int(obj["error"]["status"]), obj["error"]["detail"], "POST", url)
    rgba = np.load(io.BytesIO(base64.b64decode(obj["image"])), allow_pickle=False)
    return RenderResult(rgba, cast(RenderReport, obj["report"]))


def _content(r: httpx.Response) -> bytes:
    return r.content


def _nothing(r: httpx.Response) -> None:
    return None


def _upload_query(path: Path, overwrite: bool, options: dict[str, Any]) -> dict[str, Any]:
    fmt = options.pop("format", None) or {".nii": "nifti", ".gz": "nifti", ".tif": "tiff", ".tiff": "tiff"}.get(
        path.suffix.lower(), path.suffix.lower().lstrip(".") or "npy")
    params: dict[str, Any] = {"format": fmt, "overwrite": str(overwrite).lower()}
    if "shape" in options:
        params["shape"] = ",".join(str(int(s)) for s in options.pop("shape"))
    if "dtype" in options:
        params["dtype"] = str(options.pop("dtype"))
    return params


def _frame_file(dest: str | os.PathLike[str], n: int, r: httpx.Response) -> Path:
    npy = r.headers.get("content-type", "").startswith(("application/x-npy", "application/octet-stream"))
    p = Path(dest) / f"frame_{n:05d}.{'npy' if npy else 'png'}"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(r.content)
    return p


class _Bar:
    """A job's progress bar on a terminal (``show=None``) or when asked."""

    bar: Any  # a tqdm bar once shown

    def __init__(self, job_id: str, show: bool | None) -> None:
        self.job_id, self.show, self.bar = job_id, sys.stderr.isatty() if show is None else show, None

    def update(self, st: JobStatus) -> None:
        if not self.show:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=st.progress.total, desc=f"job {self.job_id[:8]}", unit="frame")
        self.bar.total, self.bar.n = st.progress.total, st.progress.done
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


#: failures of the connection, not answers of the server: _Api._delay decides whether to try again
_TRANSPORT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError, httpx.ReadError)
#: methods a retry cannot duplicate (a render has no side effect, so its POST is one of them)
_IDEMPOTENT = ("GET", "HEAD", "DELETE", "PUT")


@dataclass(frozen=True)
class _Request(Generic[T]):
    """One request and how to read its answer (`read`, given the checked response): what `Client` sends blocking
    and `AsyncClient` awaiting. `idempotent`: whether a retry may repeat it (None: by its method)."""

    method: str
    url: str
    read: Callable[[httpx.Response], T]
    idempotent: bool | None = None
    kw: dict[str, Any] = field(default_factory=dict)

    @property
    def again(self) -> bool:
        return self.method in _IDEMPOTENT if self.idempotent is None else self.idempotent


class _Requests:
    """Every request of the service's verbs, built once for both clients (each verb of `Client` and `AsyncClient`
    sends the `_Request` of the same name here)."""

    @staticmethod
    def health(timeout: float | None) -> _Request[Health]:
        return _Request("GET", "/healthz", _model(Health), kw=_t(timeout))

    @staticmethod
    def volumes(timeout: float | None) -> _Request[list[VolumeSummary | VolumeUnreadable]]:
        return _Request("GET", "/volumes", _listing, kw=_t(timeout))

    @staticmethod
    def volume(volume_id: str, timeout: float | None) -> _Request[VolumeSummary]:
        return _Request("GET", f"/volumes/{volume_id}", _model(VolumeSummary), kw=_t(timeout))

    @staticmethod
    def delete_volume(volume_id: str, timeout: float | None) -> _Request[None]:
        return _Request("DELETE", f"/volumes/{volume_id}", _nothing, kw=_t(timeout))

    @staticmethod
    def render_image(volume: str, scene: SceneLike, timeout: float | None) -> _Request[tuple[bytes, RenderReport]]:
        return _Request("POST", f"/volumes/{volume}/render", lambda r: (r.content, _report(r)), idempotent=True,
                        kw={"json": _scene_dict(scene), **_t(timeout)})

    @staticmethod
    def render(volume: str, scene: SceneLike, timeout: float | None) -> _Request[RenderResult]:
        return _Request("POST", f"/volumes/{volume}/render", _render_result, idempotent=True,
                        kw={"json": {**_scene_dict(scene), "format": "npy"}, **_t(timeout)})

    @staticmethod
    def render_progressive(volume: str, scene: SceneLike, session: str,
                           timeout: float | None) -> _Request[RenderResult]:
        """Streamed: `read` is not used, each line is one stage (`_stage`)."""
        return _Request("POST", f"/volumes/{volume}/render", _render_result, idempotent=False,
                        kw={"json": {**_scene_dict(scene), "format": "npy"}, "params": {"progressive": "true"},
                            "headers": {SESSION_HEADER: session}, **_t(timeout)})

    @staticmethod
    def submit(job: _Job, timeout: float | None) -> _Request[JobStatus]:
        return _Request("POST", "/jobs", _model(JobStatus), kw={"json": _job_dict(job), **_t(timeout)})

    @staticmethod
    def job(job_id: str, timeout: float | None = None) -> _Request[JobStatus]:
        return _Request("GET", f"/jobs/{job_id}", _model(JobStatus), kw=_t(timeout))

    @staticmethod
    def jobs(limit: int, state: str | None, timeout: float | None) -> _Request[list[JobStatus]]:
        params: dict[str, Any] = {"limit": limit, **({"state": state} if state else {})}
        return _Request("GET", "/jobs", _models(JobStatus), kw={"params": params, **_t(timeout)})

    @staticmethod
    def cancel(job_id: str, timeout: float | None) -> _Request[JobStatus]:
        return _Request("DELETE", f"/jobs/{job_id}", _model(JobStatus), kw=_t(timeout))

    @staticmethod
    def result(job_id: str, n: int, timeout: float | None = None) -> _Request[bytes]:
        return _Request("GET", f"/jobs/{job_id}/results/{n}", _content, kw=_t(timeout))

    @staticmethod
    def frame(job_id: str, n: int, dest: str | os.PathLike[str] | None) -> _Request[bytes | Path]:
        """Result `n` as `results` keeps it: its bytes, or the file it is written to in folder `dest`."""
        return _Request("GET", f"/jobs/{job_id}/results/{n}",
                        _content if dest is None else lambda r: _frame_file(dest, n, r))

    @staticmethod
    def animation(job_id: str, timeout: float | None) -> _Request[bytes]:
        return _Request("GET", f"/jobs/{job_id}/animation", _content, kw=_t(timeout))

    @staticmethod
    def ingest(source: str | os.PathLike[str], name: str, overwrite: bool, upload: IO[bytes] | AsyncIterator[bytes] | None,
               options: dict[str, Any], timeout: float | None) -> _Request[JobStatus]:
        """An ingest job: a server-side path, or (`upload`: the body, a file or an async iterator of its bytes)
        a local file sent in the request's body."""
        if upload is not None:
            return _Request("POST", f"/volumes/{name}/upload", _model(JobStatus),
                            kw={"content": upload, "params": _upload_query(Path(source), overwrite, options),
                                **_t(timeout)})
        return _Request("POST", "/volumes", _model(JobStatus),
                        kw={"json": {"name": name, "source": os.fspath(source), "overwrite": overwrite,
                                     "options": options}, **_t(timeout)})


def _results(st: JobStatus) -> range:
    """The results a job has: one per frame (an ingest job has none)."""
    return range(st.progress.total if st.kind != "ingest" else 0)


class _Api:
    """What the two clients share: the server, the token and the retry policy (`_delay`); every request they send is
    built by `_Requests`."""

    retries: int

    def __init__(self, base_url: str | None, token: str | None, retries: int) -> None:
        if retries < 0:
            raise ValueError(f"retries: must be at least 0, got {retries}")
        self.retries = int(retries)
        base_url = base_url or os.environ.get("LODCAST_URL")
        if not base_url:
            raise ValueError("base_url: no server URL given (pass one or set LODCAST_URL)")
        token = token if token is not None else os.environ.get("LODCAST_TOKEN")
        self._headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.base_url = base_url.rstrip("/")
        self.session = uuid.uuid4().hex  # this client's progressive renders: a newer one cancels the older

    def _delay(self, attempt: int, again: bool, r: httpx.Response | None, exc: Exception | None) -> float | None:
        """Seconds to wait before trying again, or None to stop here: after 0.25 s, 0.5 s, 1 s, ... (or the
        server's Retry-After) when nothing was sent, and for idempotent requests on 503 or a dropped connection."""
        if attempt >= self.retries:
            return None
        delay = 0.25 * 2**attempt
        if exc is not None:
            return delay if isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout)) or again else None
        assert r is not None
        if r.status_code != 503 or not again:
            return None
        try:
            return max(delay, min(30.0, float(r.headers.get("retry-after", 0))))
        except ValueError:
            return delay


class Client(_Api):
    """``Client("http://127.0.0.1:8000", token=None)``; the base URL defaults to ``LODCAST_URL``, the token to
    ``LODCAST_TOKEN``.

    ``timeout``: seconds per request (every call also takes its own ``timeout=``; `wait`'s is the whole wait). ``retries``: how often a request is
    tried again, after 0.25 s, 0.5 s, 1 s, ... (or the server's ``Retry-After``): when the server cannot be reached
    (nothing was sent, so any request), and for reads and renders also on 503 (busy or restarting) and on a
    dropped connection. A job submission is not repeated once it may have arrived."""

    def __init__(self, base_url: str | None = None, token: str | None = None, *, timeout: float = 300.0,
                 transport: httpx.BaseTransport | None = None, retries: int = 3) -> None:
        super().__init__(base_url, token, retries)
        self._http = httpx.Client(base_url=self.base_url, headers=self._headers, timeout=timeout, transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, req: _Request[T]) -> T:
        for attempt in range(self.retries + 1):
            try:
                r = self._http.request(req.method, req.url, **req.kw)
            except _TRANSPORT as exc:
                delay = self._delay(attempt, req.again, None, exc)
                if delay is None:
                    raise
            else:
                delay = self._delay(attempt, req.again, r, None)
                if delay is None:
                    return req.read(_checked(r, req.method, req.url))
            time.sleep(delay)
        raise AssertionError("unreachable: the last attempt returns or raises")

    # --- volumes ----------------------------------------------------------------------------------------------
    def health(self, *, timeout: float | None = None) -> Health:
        return self._send(_Requests.health(timeout))

    def volumes(self, *, timeout: float | None = None) -> list[VolumeSummary | VolumeUnreadable]:
        """Every volume's attributes; a store the server cannot read is a VolumeUnreadable (its id and error)."""
        return self._send(_Requests.volumes(timeout))

    def volume(self, volume_id: str, *, timeout: float | None = None) -> VolumeSummary:
        return self._send(_Requests.volume(volume_id, timeout))

    def delete_volume(self, volume_id: str, *, timeout: float | None = None) -> None:
        return self._send(_Requests.delete_volume(volume_id, timeout))

    # --- rendering --------------------------------------------------------------------------------------------
    def render_image(self, volume: str, scene: SceneLike, *,
                     timeout: float | None = None) -> tuple[bytes, RenderReport]:
        """The encoded image as the server sends it (PNG or .npy bytes) and the render report. `timeout`: seconds
        for this call (default: the client's)."""
        return self._send(_Requests.render_image(volume, scene, timeout))

    def render(self, volume: str, scene: SceneLike, *, timeout: float | None = None) -> RenderResult:
        """A RenderResult, as local rendering returns: float32 premultiplied RGBA (fetched as .npy) and the report."""
        return self._send(_Requests.render(volume, scene, timeout))

    def render_progressive(self, volume: str, scene: SceneLike, *, session: str | None = None,
                           timeout: float | None = None) -> Iterator[RenderResult]:
        """The stages of a progressive render, coarse to fine, as they arrive (docs/serving.md): RenderResults of
        the scene's size (float32 RGBA, fetched as .npy), the last at the scene's quality. A newer progressive
        render of the same `session` (default: this client's) ends this one's stream before its final stage;
        closing the generator hangs up, which cancels the stages still to come. Not retried."""
        req = _Requests.render_progressive(volume, scene, session or self.session, timeout)
        with self._http.stream(req.method, req.url, **req.kw) as r:
            if r.status_code >= 400:
                r.read()
                _checked(r, req.method, req.url)
            for line in r.iter_lines():
                if line.strip():
                    yield _stage(line, req.url)

    # --- jobs -------------------------------------------------------------------------------------------------
    def submit(self, job: Mapping[str, Any] | BaseModel | str | os.PathLike[str], *,
               timeout: float | None = None) -> JobStatus:
        """A job (a dict, a job model, or a JSON file's path); its status as queued."""
        return self._send(_Requests.submit(job, timeout))

    def job(self, job_id: str, *, timeout: float | None = None) -> JobStatus:
        return self._send(_Requests.job(job_id, timeout))

    def jobs(self, limit: int = 100, state: str | None = None, *, timeout: float | None = None) -> list[JobStatus]:
        return self._send(_Requests.jobs(limit, state, timeout))

    def cancel(self, job_id: str, *, timeout: float | None = None) -> JobStatus:
        return self._send(_Requests.cancel(job_id, timeout))

    def result(self, job_id: str, n: int, *, timeout: float | None = None) -> bytes:
        return self._send(_Requests.result(job_id, n, timeout))

    def animation(self, job_id: str, *, timeout: float | None = None) -> bytes:
        return self._send(_Requests.animation(job_id, timeout))

    def ingest(self, source: str | os.PathLike[str], name: str, *, overwrite: bool = False, upload: bool = False,
               wait: bool = False, timeout: float | None = None, **options: Any) -> JobStatus:
        """Ingest as a job: a server-side path under the server's import roots, or (``upload=True``) a local file
        sent in the request body (``format`` from its extension unless given). Returns the job status."""
        if upload:
            with open(source, "rb") as f:
                st = self._send(_Requests.ingest(source, name, overwrite, f, options, timeout))
        else:
            st = self._send(_Requests.ingest(source, name, overwrite, None, options, timeout))
        return self.wait(st.id, progress=False, timeout=timeout) if wait else st

    def wait(self, job_id: str, *, timeout: float | None = None, poll: float = 0.25,
             progress: bool | None = None) -> JobStatus:
        """Poll until the job is done, failed or cancelled; TimeoutError after ``timeout`` seconds."""
        bar, end = _Bar(job_id, progress), None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                st = self.job(job_id)
                bar.update(st)
                if st.state in FINAL:
                    return st
                if end is not None and time.monotonic() > end:
                    raise TimeoutError(f"job {job_id} still {st.state} after {timeout} s")
                time.sleep(poll)
        finally:
            bar.close()

    def results(self, job_id: str, dest: str | os.PathLike[str] | None = None) -> list[bytes] | list[Path]:
        """Every result of a job, in order: as bytes, or written to folder ``dest`` (then their paths)."""
        st = self.job(job_id)
        out: list[Any] = [self._send(_Requests.frame(job_id, n, dest)) for n in _results(st)]
        return out


class AsyncClient(_Api):
    """The same verbs as `Client`, awaited (``async with AsyncClient(url) as c: st = await c.submit(job)``); the
    same retries, timeouts and typed results."""

    def __init__(self, base_url: str | None = None, token: str | None = None, *, timeout: float = 300.0,
                 transport: httpx.AsyncBaseTransport | None = None, retries: int = 3) -> None:
        super().__init__(base_url, token, retries)
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=self._headers, timeout=timeout,
                                       transport=transport)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _send(self, req: _Request[T]) -> T:
        for attempt in range(self.retries + 1):
            try:
                r = await self._http.request(req.method, req.url, **req.kw)
            except _TRANSPORT as exc:
                delay = self._delay(attempt, req.again, None, exc)
                if delay is None:
                    raise
            else:
                delay = self._delay(attempt, req.again, r, None)
                if delay is None:
                    return req.read(_checked(r, req.method, req.url))
            await asyncio.sleep(delay)
        raise AssertionError("unreachable: the last attempt returns or raises")

    # --- volumes ----------------------------------------------------------------------------------------------
    async def health(self, *, timeout: float | None = None) -> Health:
        return await self._send(_Requests.health(timeout))

    async def volumes(self, *, timeout: float | None = None) -> list[VolumeSummary | VolumeUnreadable]:
        """Every volume's attributes; a store the server cannot read is a VolumeUnreadable (its id and error)."""
        return await self._send(_Requests.volumes(timeout))

    async def volume(self, volume_id: str, *, timeout: float | None = None) -> VolumeSummary:
        return await self._send(_Requests.volume(volume_id, timeout))

    async def delete_volume(self, volume_id: str, *, timeout: float | None = None) -> None:
        return await self._send(_Requests.delete_volume(volume_id, timeout))

    # --- rendering --------------------------------------------------------------------------------------------
    async def render_image(self, volume: str, scene: SceneLike, *,
                           timeout: float | None = None) -> tuple[bytes, RenderReport]:
        return await self._send(_Requests.render_image(volume, scene, timeout))

    async def render(self, volume: str, scene: SceneLike, *, timeout: float | None = None) -> RenderResult:
        return await self._send(_Requests.render(volume, scene, timeout))

    async def render_progressive(self, volume: str, scene: SceneLike, *, session: str | None = None,
                                 timeout: float | None = None) -> AsyncIterator[RenderResult]:
        """`Client.render_progressive`, awaited (``async for stage in c.render_progressive(...)``)."""
        req = _Requests.render_progressive(volume, scene, session or self.session, timeout)
        async with self._http.stream(req.method, req.url, **req.kw) as r:
            if r.status_code >= 400:
                await r.aread()
                _checked(r, req.method, req.url)
            async for line in r.aiter_lines():
                if line.strip():
                    yield _stage(line, req.url)

    # --- jobs -------------------------------------------------------------------------------------------------
    async def submit(self, job: Mapping[str, Any] | BaseModel | str | os.PathLike[str], *,
                     timeout: float | None = None) -> JobStatus:
        return await self._send(_Requests.submit(job, timeout))

    async def job(self, job_id: str, *, timeout: float | None = None) -> JobStatus:
        return await self._send(_Requests.job(job_id, timeout))

    async def jobs(self, limit: int = 100, state: str | None = None, *,
                   timeout: float | None = None) -> list[JobStatus]:
        return await self._send(_Requests.jobs(limit, state, timeout))

    async def cancel(self, job_id: str, *, timeout: float | None = None) -> JobStatus:
        return await self._send(_Requests.cancel(job_id, timeout))

    async def result(self, job_id: str, n: int, *, timeout: float | None = None) -> bytes:
        return await self._send(_Requests.result(job_id, n, timeout))

    async def animation(self, job_id: str, *, timeout: float | None = None) -> bytes:
        return await self._send(_Requests.animation(job_id, timeout))

    async def ingest(self, source: str | os.PathLike[str], name: str, *, overwrite: bool = False,
                     upload: bool = False, wait: bool = False, timeout: float | None = None,
                     **options: Any) -> JobStatus:
        body = _chunks(Path(source)) if upload else None
        st = await self._send(_Requests.ingest(source, name, overwrite, body, options, timeout))
        return await self.wait(st.id, progress=False, timeout=timeout) if wait else st

    async def wait(self, job_id: str, *, timeout: float | None = None, poll: float = 0.25,
                   progress: bool | None = None) -> JobStatus:
        bar, end = _Bar(job_id, progress), None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                st = await self.job(job_id)
                bar.update(st)
                if st.state in FINAL:
                    return st
                if end is not None and time.monotonic() > end:
                    raise TimeoutError(f"job {job_id} still {st.state} after {timeout} s")
                await asyncio.sleep(poll)
        finally:
            bar.close()

    async def results(self, job_id: str, dest: str | os.PathLike[str] | None = None) -> list[bytes] | list[Path]:
        st = await self.job(job_id)
        out: list[Any] = [await self._send(_Requests.frame(job_id, n, dest)) for n in _results(st)]
        return out


async def _chunks(path: Path, size: int = 1 << 20) -> AsyncIterator[bytes]:
    """A file as the async client streams it (httpx's AsyncClient takes no blocking file objects)."""
    with open(path, "rb") as f:
        while chunk := await asyncio.to_thread(f.read, size):
            yield chunk
