"""``lodcast.Client``: the service's verbs over HTTP (httpx). Errors raise ServiceError carrying the server's message."""
from __future__ import annotations

import io
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from lodcast.errors import LodcastError

__all__ = ["Client", "ServiceError"]


class ServiceError(LodcastError, ValueError):
    """The server refused a request (4xx) or failed (5xx); ``status`` and ``detail`` are the server's."""

    def __init__(self, status: int, detail: Any, method: str = "", url: str = "") -> None:
        self.status, self.detail = status, detail
        super().__init__(f"{status} from {method} {url}: {_detail_text(detail)}")


def _detail_text(detail: Any) -> str:
    if isinstance(detail, list):
        return "; ".join(str(d.get("msg", d)) if isinstance(d, dict) else str(d) for d in detail)
    return str(detail)


def _scene_dict(scene: Any) -> dict[str, Any]:
    if hasattr(scene, "model_dump"):
        return scene.model_dump(mode="json")
    if isinstance(scene, (str, Path)):
        return json.loads(Path(scene).read_text())
    return dict(scene)


def _result(rgba: Any, report: dict[str, Any]) -> Any:
    try:
        from lodcast.renderer.render import RenderResult
    except ImportError:  # pragma: no cover - the renderer is part of the package
        from types import SimpleNamespace

        return SimpleNamespace(rgba=rgba, report=report)
    try:
        return RenderResult(rgba=rgba, report=report)
    except TypeError:
        return RenderResult(rgba, report)


#: methods a retry cannot duplicate (a render has no side effect, so its POST is one of them)
_IDEMPOTENT = ("GET", "HEAD", "DELETE", "PUT")


class Client:
    """``Client("http://127.0.0.1:8000", token=None)``; the base URL defaults to ``LODCAST_URL``.

    ``timeout``: seconds per request (each call also takes ``timeout=``). ``retries``: how often a request is
    tried again, after 0.25 s, 0.5 s, 1 s, ... (or the server's ``Retry-After``): when the server cannot be reached
    (nothing was sent, so any request), and for reads and renders also on 503 (busy or restarting) and on a
    dropped connection. A job submission is not repeated once it may have arrived."""

    def __init__(self, base_url: str | None = None, token: str | None = None, *, timeout: float = 300.0,
                 transport: httpx.BaseTransport | None = None, retries: int = 3) -> None:
        if retries < 0:
            raise ValueError(f"retries: must be at least 0, got {retries}")
        self.retries = int(retries)
        base_url = base_url or os.environ.get("LODCAST_URL")
        if not base_url:
            raise ValueError("base_url: no server URL given (pass one or set LODCAST_URL)")
        token = token if token is not None else os.environ.get("LODCAST_TOKEN")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, method: str, url: str, *, idempotent: bool | None = None, **kw: Any) -> httpx.Response:
        again = method in _IDEMPOTENT if idempotent is None else idempotent
        for attempt in range(self.retries + 1):
            last = attempt == self.retries
            delay = 0.25 * 2**attempt
            try:
                r = self._http.request(method, url, **kw)
            except (httpx.ConnectError, httpx.ConnectTimeout):
                if last:
                    raise
            except (httpx.RemoteProtocolError, httpx.ReadError):
                if last or not again:
                    raise
            else:
                if r.status_code != 503 or last or not again:
                    break
                try:
                    delay = max(delay, min(30.0, float(r.headers.get("retry-after", 0))))
                except ValueError:
                    pass
            time.sleep(delay)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except (ValueError, AttributeError):
                detail = r.text
            raise ServiceError(r.status_code, detail, method, url)
        return r

    # --- volumes ----------------------------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        return self._request("GET", "/healthz").json()

    def volumes(self) -> list[dict[str, Any]]:
        return self._request("GET", "/volumes").json()

    def volume(self, volume_id: str) -> dict[str, Any]:
        return self._request("GET", f"/volumes/{volume_id}").json()

    def ingest(self, source: str | os.PathLike[str], name: str, *, overwrite: bool = False, upload: bool = False,
               wait: bool = False, **options: Any) -> dict[str, Any]:
        """Ingest as a job: a server-side path under the server's import roots, or (``upload=True``) a local file
        sent in the request body (``format`` from its extension unless given). Returns the job status."""
        if upload:
            path = Path(source)
            fmt = options.pop("format", None) or {".nii": "nifti", ".gz": "nifti", ".tif": "tiff", ".tiff": "tiff"}.get(
                path.suffix.lower(), path.suffix.lower().lstrip(".") or "npy")
            params: dict[str, Any] = {"format": fmt, "overwrite": str(overwrite).lower()}
            if "shape" in options:
                params["shape"] = ",".join(str(int(s)) for s in options.pop("shape"))
            if "dtype" in options:
                params["dtype"] = str(options.pop("dtype"))
            with open(path, "rb") as f:
                status = self._request("POST", f"/volumes/{name}/upload", params=params, content=f).json()
        else:
            body = {"name": name, "source": os.fspath(source), "overwrite": overwrite, "options": options}
            status = self._request("POST", "/volumes", json=body).json()
        return self.wait(status["id"], progress=False) if wait else status

    def delete_volume(self, volume_id: str) -> None:
        self._request("DELETE", f"/volumes/{volume_id}")

    # --- rendering --------------------------------------------------------------------------------------------
    def render_image(self, volume: str, scene: Any, *, timeout: float | None = None) -> tuple[bytes, dict[str, Any]]:
        """The encoded image as the server sends it (PNG or .npy bytes) and the render report. `timeout`: seconds
        for this call (default: the client's)."""
        kw = {} if timeout is None else {"timeout": timeout}
        r = self._request("POST", f"/volumes/{volume}/render", json=_scene_dict(scene), idempotent=True, **kw)
        return r.content, json.loads(r.headers.get("x-lodcast-report", "{}"))

    def render(self, volume: str, scene: Any, *, timeout: float | None = None) -> Any:
        """A RenderResult, as local rendering returns: float32 premultiplied RGBA (fetched as .npy) and the report."""
        import numpy as np

        body = {**_scene_dict(scene), "format": "npy"}
        data, report = self.render_image(volume, body, timeout=timeout)
        return _result(np.load(io.BytesIO(data), allow_pickle=False), report)

    # --- jobs -------------------------------------------------------------------------------------------------
    def submit(self, job: dict[str, Any] | str | os.PathLike[str]) -> dict[str, Any]:
        if isinstance(job, (str, Path)):
            job = json.loads(Path(job).read_text())
        return self._request("POST", "/jobs", json=job).json()

    def job(self, job_id: str) -> dict[str, Any]:
        return self._request("GET", f"/jobs/{job_id}").json()

    def jobs(self, limit: int = 100, state: str | None = None) -> list[dict[str, Any]]:
        params: dict[str, Any] = {"limit": limit}
        if state:
            params["state"] = state
        return self._request("GET", "/jobs", params=params).json()

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self._request("DELETE", f"/jobs/{job_id}").json()

    def wait(self, job_id: str, *, timeout: float | None = None, poll: float = 0.25, progress: bool | None = None) -> dict[str, Any]:
        """Poll until the job is done, failed or cancelled (or ``timeout`` seconds pass); a progress bar on a
        terminal (``progress=None``) or when asked."""
        show = sys.stderr.isatty() if progress is None else progress
        bar = None
        end = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                st = self.job(job_id)
                if show:
                    if bar is None:
                        from tqdm import tqdm

                        bar = tqdm(total=st["progress"]["total"], desc=f"job {job_id[:8]}", unit="frame")
                    bar.total = st["progress"]["total"]
                    bar.n = st["progress"]["done"]
                    bar.refresh()
                if st["state"] in ("done", "failed", "cancelled"):
                    return st
                if end is not None and time.monotonic() > end:
                    raise TimeoutError(f"job {job_id} still {st['state']} after {timeout} s")
                time.sleep(poll)
        finally:
            if bar is not None:
                bar.close()

    def result(self, job_id: str, n: int) -> bytes:
        return self._request("GET", f"/jobs/{job_id}/results/{n}").content

    def results(self, job_id: str, dest: str | os.PathLike[str] | None = None) -> list[bytes] | list[Path]:
        """Every result of a job, in order: as bytes, or written to folder ``dest`` (then their paths)."""
        st = self.job(job_id)
        out: list[Any] = []
        for n in range(st["progress"]["total"] if st["kind"] != "ingest" else 0):
            r = self._request("GET", f"/jobs/{job_id}/results/{n}")
            if dest is None:
                out.append(r.content)
            else:
                ext = "npy" if r.headers.get("content-type", "").startswith(("application/x-npy", "application/octet-stream")) else "png"
                p = Path(dest) / f"frame_{n:05d}.{ext}"
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(r.content)
                out.append(p)
        return out

    def animation(self, job_id: str) -> bytes:
        return self._request("GET", f"/jobs/{job_id}/animation").content
