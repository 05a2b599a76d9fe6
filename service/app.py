"""The HTTP API (FastAPI). ``create_app(settings)`` builds everything; nothing is created at import time.

Routes (docs/design.md "Interfaces"): ``GET /healthz``, ``GET /readyz``; ``GET/POST /volumes``, ``GET/DELETE /volumes/{id}``,
``POST /volumes/{id}/upload``; ``POST /volumes/{id}/render``; ``GET/POST /jobs``, ``GET/DELETE /jobs/{id}``,
``GET /jobs/{id}/results/{n}``, ``GET /jobs/{id}/animation``; OpenAPI at ``/docs``; the web viewer's ``GET /``,
``GET /volumes/{id}/view`` and ``GET /volumes/{id}/histogram`` (service/viewer.py).
Every bad request is a 4xx whose JSON ``detail`` names the field (FastAPI's 422 list shape for bodies).
"""
from __future__ import annotations

import asyncio
import json
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import Body, Depends, FastAPI, Header, Query, Request
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field, ValidationError

import lodcast
from lodcast.errors import LodcastError, StoreCorrupt, StoreInvalid, StoreNotFound
from lodcast.renderer.scene.cost import CostError
from lodcast.renderer.scene.scene import Scene, SceneError, validation_message
from lodcast.service.asgi import BodyLimit, TokenGate, offline_docs
from lodcast.service.faults import StorageUnavailable, unavailable
from lodcast.service.faults import install as install_fault_handlers
from lodcast.service.health import Monitor
from lodcast.service.health import probes as health_probes
from lodcast.service.jobs import IngestJob, Job, validate_job
from lodcast.service.models import (
    NDJSON,
    REPORT_HEADER,
    SESSION_HEADER,
    Deleted,
    Health,
    JobStatus,
    VolumeListing,
    VolumeSummary,
    errors,
)
from lodcast.service.objectstorage import bound_object_storage, s3_limits
from lodcast.service.params import JobId, VolumeId
from lodcast.service.progressive import stream as progressive_stream
from lodcast.service.records import status_json
from lodcast.service.rendering import (
    RenderEngine,
    RequestInvalid,
    encode,
    field_error,
    finite_json,
    parse_scene,
    scene_refused,
)
from lodcast.service.results import JobFiles, frame_name, park_upload
from lodcast.service.settings import Settings
from lodcast.service.viewer import add_viewer
from lodcast.service.volumes import (
    JOB_ID,
    BadId,
    StoreUnusable,
    VolumeNotFound,
    check_volume_id,
    delete_volume,
    list_volumes,
    volume_path,
    volume_summary,
)

__all__ = ["create_app"]


EXAMPLE_SCENE = {
    "camera": {"azimuth": 30, "elevation": 20, "distance": 2.5, "fov": 30},
    "width": 256,
    "height": 256,
    "tf": {"points": [{"value": 0, "color": [0.2, 0.4, 1.0], "opacity": 0.0},
                      {"value": 1000, "color": [1.0, 0.9, 0.8], "opacity": 0.6}]},
    "format": "png",
}


class HttpError(Exception):
    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def _store_error(volume_id: str, path: Any, exc: Exception) -> "HttpError":
    """A volume whose store cannot be used: 409 when its files changed since ingest (StoreCorrupt), else 404;
    the message names the volume and the array, not the server's paths."""
    msg = " ".join(str(exc).replace(str(path) + os.sep, "").replace(str(path), "").split())
    if isinstance(exc, StoreCorrupt):
        return HttpError(409, f"volume {volume_id!r}: the store is damaged ({msg})")
    if isinstance(exc, StoreUnusable):  # its message names the volume and the attribute
        return HttpError(409, msg)
    return HttpError(404, f"volume: {volume_id!r} is not a valid store ({msg})")


class _ClientGone(Exception):
    """Raised between launch bands when the client of a render has disconnected."""


class IngestRequest(BaseModel):
    """Register a volume by ingesting a server-side file (under a configured import root) as a job."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(max_length=128, description="volume id of the new store")
    source: str = Field(min_length=1, max_length=4096)
    overwrite: bool = False
    options: dict[str, Any] = Field(default_factory=dict)


def _bytes_in(folder: Any) -> int:
    total = 0
    for p in folder.iterdir():
        try:
            total += p.stat().st_size
        except FileNotFoundError:  # ingested and removed meanwhile
            continue
    return total


def _result(files: JobFiles, name: str, media: str) -> Response | None:
    """A job's result file as the response (served from disk where the results are a local folder, else read
    from object storage), or None while it is not written."""
    local = files.local(name)
    if local is not None:
        return FileResponse(local, media_type=media, filename=name) if local.is_file() else None
    try:
        data = files.read(name)
    except FileNotFoundError:
        return None
    return Response(data, media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}"'})


def gzipped(path: Path) -> bool:
    """Whether the file starts with gzip's magic bytes (1f 8b)."""
    with open(path, "rb") as f:
        return f.read(2) == b"\x1f\x8b"


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    bound_object_storage(**s3_limits(settings))  # an outage answers 503 within seconds, not after the S3 client's retries
    engine = RenderEngine(settings)  # every render of this app and its in-process workers
    state: dict[str, Any] = {"jobs": None, "worker": None, "sem": None}
    lock = threading.Lock()

    def jobs() -> Any:
        with lock:
            if state["jobs"] is None:
                from lodcast.service.queue import JobQueue

                settings.local_root.mkdir(parents=True, exist_ok=True)
                state["jobs"] = JobQueue(settings, engine=engine)
            return state["jobs"]

    monitor = Monitor(health_probes(settings, jobs, engine), settings.health_every_s)

    @asynccontextmanager
    async def lifespan(app: FastAPI):  # type: ignore[no-untyped-def]
        monitor.start()
        worker = None
        if settings.workers > 0:
            from lodcast.service.queue import Worker

            worker = Worker(await run_in_threadpool(jobs), threads=settings.workers).start()
            state["worker"] = worker
        try:
            yield
        finally:
            monitor.stop()
            if worker is not None:
                await run_in_threadpool(worker.stop)

    app = FastAPI(
        title="lodcast",
        version=lodcast.__version__,
        description="Volume rendering of large scalar volumes with transfer-function-driven level of detail.",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    offline_docs(app)
    app.state.settings = settings
    app.state.jobs = jobs
    app.state.engine = engine
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes)

    def semaphore(samples: int) -> asyncio.Semaphore:
        # created inside the running loop (one per loop: test clients may run several); FIFO, so waiting renders
        # are served in arrival order. Renders of at most small_render_samples (estimated) have a slot of their
        # own, so that a quick one never waits for minutes behind big ones; they take a main slot while one is
        # free: when most requests are small (viewers at 256²) they would otherwise queue for the one small slot
        # with the main ones idle, behind a cold frame that is small by its estimate but reads for seconds
        loop = asyncio.get_running_loop()
        if state["sem"] is None or state["sem"][0] is not loop:
            state["sem"] = (loop, asyncio.Semaphore(settings.render_concurrency), asyncio.Semaphore(1))
        main, small = state["sem"][1], state["sem"][2]
        return small if samples <= settings.small_render_samples and main.locked() else main

    bearer = HTTPBearer(auto_error=False, description="LODCAST_TOKEN, when the service has one")

    def require_token(cred: HTTPAuthorizationCredentials | None = Depends(bearer)) -> None:  # noqa: B008
        """Marks a route as protected and declares the bearer scheme in OpenAPI; the token itself is checked once,
        by TokenGate (service/asgi.py), before the request's body is read."""

    # docs/design.md, Limits: with LODCAST_TOKEN set every route but /healthz (and the docs) needs the token, reads too
    auth = [Depends(require_token)]

    def protected(scope: dict) -> bool:
        """Whether the route the request goes to declares the token dependency (`auth`): TokenGate checks the token
        of those before their body is read (the dependency itself runs after FastAPI parsed the body)."""
        from starlette.routing import Match

        for route in app.router.routes:
            if route.matches(scope)[0] == Match.FULL:
                return any(getattr(d, "dependency", None) is require_token for d in getattr(route, "dependencies", ()))
        return False

    app.add_middleware(TokenGate, token=settings.token, protected=protected)  # outside BodyLimit: 401 before 413

    # --- errors -------------------------------------------------------------------------------------------------
    def failure(volume_id: str, path: Any, exc: Exception) -> Exception:
        """A store that cannot be used now (503, a storage fault) or at all (409, 404: _store_error)."""
        return unavailable(settings, exc, volume_id) or _store_error(volume_id, path, exc)

    install_fault_handlers(app, settings)

    @app.exception_handler(HttpError)
    async def _http_error(request: Request, exc: HttpError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)

    @app.exception_handler(405)
    async def _wrong_method(request: Request, exc: Exception) -> JSONResponse:
        # each route object holds one method, so Starlette's Allow named only the first route of the path
        from starlette.routing import Match

        allowed = sorted({m for r in request.app.router.routes if r.matches(request.scope)[0] != Match.NONE
                          for m in (getattr(r, "methods", None) or ())} - {"HEAD"} or {"GET"})
        return JSONResponse({"detail": f"method: {request.method} is not allowed on {request.url.path} "
                                       f"(allowed: {', '.join(allowed)})"},
                            status_code=405, headers={"Allow": ", ".join(allowed)})

    @app.exception_handler(RequestValidationError)
    async def _unparsable(request: Request, exc: RequestValidationError) -> JSONResponse:
        # pydantic's errors carry the offending input: never echo a request body (or part of it) back; each
        # message starts with the field's dotted path, as the renderer's own checks do
        out = []
        for e in exc.errors():
            loc = [p if isinstance(p, int) else str(p) for p in e.get("loc", ())]
            if e.get("type") == "json_invalid":  # its loc is ("body", the character's offset): no field to name
                error = (e.get("ctx") or {}).get("error")
                out.append({"loc": ["body"], "msg": f"body: not valid JSON (at character {loc[-1]}"
                                                    f"{': ' + str(error) if error else ''})", "type": "json_invalid"})
                continue
            out.append(field_error(loc, str(e.get("msg", "invalid")), str(e.get("type", "value_error"))))
        return JSONResponse({"detail": out}, status_code=422)

    @app.exception_handler(RequestInvalid)
    async def _invalid(request: Request, exc: RequestInvalid) -> JSONResponse:
        return JSONResponse({"detail": exc.errors}, status_code=422)

    @app.exception_handler(VolumeNotFound)
    async def _no_volume(request: Request, exc: VolumeNotFound) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=404)

    @app.exception_handler(BadId)
    async def _bad_id(request: Request, exc: BadId) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=400)

    @app.exception_handler(LodcastError)
    async def _lodcast_error(request: Request, exc: LodcastError) -> JSONResponse:
        if isinstance(exc, RuntimeError):  # the renderer's DeviceError: no usable device, kernel build failed
            return JSONResponse({"detail": "render device: " + " ".join(str(exc).split())[:2000]}, status_code=503)
        code = 404 if isinstance(exc, (StoreNotFound, FileNotFoundError)) else 409 if isinstance(exc, StoreInvalid) else 400
        return JSONResponse({"detail": " ".join(str(exc).split()) or type(exc).__name__}, status_code=code)

    def _queue_down(request: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": f"queue: unavailable ({' '.join(str(exc).split())[:500]})"}, status_code=503)

    app.add_exception_handler(sqlite3.OperationalError, _queue_down)
    try:
        import redis.exceptions

        app.add_exception_handler(redis.exceptions.ConnectionError, _queue_down)
        app.add_exception_handler(redis.exceptions.TimeoutError, _queue_down)
    except ImportError:  # pragma: no cover - redis is a dependency
        pass

    # --- health / volumes ---------------------------------------------------------------------------------------
    @app.get("/healthz", tags=["service"], summary="Liveness, and each component (store root, queue, device)",
             response_model=Health)
    async def healthz() -> dict[str, Any]:
        """What each component's last probe found (service/health.py: probed off the request path, so this answers
        at once however busy the renderer is); `degraded` when one is down."""
        parts = monitor.start().components()
        return {"status": "degraded" if any(c["status"] == "down" for c in parts.values()) else "ok",
                "version": lodcast.__version__, "queue": "redis" if settings.is_redis else "sqlite",
                "components": parts}

    @app.get("/readyz", tags=["service"], summary="Readiness: 503 naming each component that is down",
             response_model=Health, responses=errors(503))
    async def readyz() -> Any:
        parts = monitor.start().components()
        down = [f"{name}: {c['status']} ({c['detail']})" for name, c in parts.items() if c["status"] != "ok"]
        if down:
            return JSONResponse({"detail": "; ".join(down)}, status_code=503,
                                headers={"Retry-After": str(settings.retry_after_s)})
        return {"status": "ok", "version": lodcast.__version__, "queue": "redis" if settings.is_redis else "sqlite",
                "components": parts}

    @app.get("/presets", tags=["service"], dependencies=auth, summary="The named transfer functions",
             response_model=dict[str, dict[str, Any]], responses=errors(401))
    def get_presets() -> dict[str, Any]:
        """The named transfer functions a scene may give as `"tf": NAME`."""
        from lodcast.renderer.scene.presets import catalogue

        return catalogue()

    @app.get("/volumes", tags=["volumes"], dependencies=auth, summary="Every volume under the store root",
             response_model=list[VolumeListing], responses=errors(401))
    def get_volumes() -> list[dict[str, Any]]:
        """Every store under the root: its attributes, or, for one that cannot be read, its id and an `error`
        (one damaged store never hides the others)."""
        out = []
        for vid in list_volumes(settings.root):
            try:
                out.append(summary_of(vid))
            except VolumeNotFound:
                continue  # deleted since the listing
            except HttpError as exc:
                out.append({"id": vid, "error": exc.detail})
            except StorageUnavailable:
                raise  # the storage, not this store: the listing as a whole is to be asked again
            except Exception as exc:  # noqa: BLE001 - whatever one store does, the others are listed
                fault = unavailable(settings, exc, vid)
                if fault is not None:
                    raise fault from None
                out.append({"id": vid, "error": f"volume {vid!r}: the store cannot be read "
                                                f"({type(exc).__name__}: {' '.join(str(exc).split())[:500]})"})
        return out

    def summary_of(vid: str) -> dict[str, Any]:
        """A volume's summary as GET /volumes/{id} returns it; HttpError (409, 404) naming what is wrong."""
        try:
            summary = finite_json(volume_summary(settings.root, vid))
        except StoreInvalid as exc:
            raise failure(vid, volume_path(settings.root, vid, must_exist=False), exc) from None
        except Exception as exc:
            raise (unavailable(settings, exc, vid) or exc) from None
        try:
            VolumeSummary.model_validate(summary)  # what the response model will check, checked here
        except ValidationError as exc:
            raise HttpError(409, f"volume {vid!r}: the store's attributes are not what this lodcast writes "
                                 f"({validation_message(exc)}); re-ingest it") from None
        return summary

    @app.post("/volumes", status_code=202, tags=["volumes"], dependencies=auth,
              summary="Ingest a server-side file (under an import root) as a new volume: an ingest job",
              response_model=JobStatus, responses=errors(400, 401, 413, 422, 503))
    def post_volume(req: IngestRequest) -> dict[str, Any]:
        job = IngestJob(kind="ingest", source=req.source, name=req.name, overwrite=req.overwrite, options=req.options)
        return status_json(jobs().submit(validate_job(job, settings, engine)))

    @app.post("/volumes/{volume_id}/upload", status_code=202, tags=["volumes"], dependencies=auth,
              summary="Upload one volume file as the request body: an ingest job",
              response_model=JobStatus, responses=errors(400, 401, 413, 422, 503),
              openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
                  "schema": {"type": "string", "format": "binary"}}}}})
    async def upload_volume(
        volume_id: VolumeId,
        request: Request,
        format: Annotated[Literal["npy", "nrrd", "nifti", "tiff", "raw"], Query(description="source format")] = "npy",
        overwrite: bool = False,
        shape: Annotated[str | None, Query(max_length=100, description="raw only: z,y,x")] = None,
        dtype: Annotated[str | None, Query(max_length=20, description="raw only")] = None,
    ) -> dict[str, Any]:
        check_volume_id(volume_id, "volume")  # before the job model (a 129-character id was a 500)
        options: dict[str, Any] = {"format": format}
        if format == "raw":
            try:
                dims = tuple(int(p) for p in (shape or "").split(","))
                if len(dims) != 3 or min(dims) < 1:
                    raise ValueError
            except ValueError:
                raise RequestInvalid.one(("query", "shape"), "raw uploads need shape=z,y,x (three positive integers)") from None
            if not dtype:
                raise RequestInvalid.one(("query", "dtype"), "raw uploads need a dtype")
            options.update(shape=dims, dtype=dtype)
        uploads = settings.uploads_dir
        uploads.mkdir(parents=True, exist_ok=True)
        ext = {"nifti": "nii", "tiff": "tif"}.get(format, format)
        dest = uploads / f"{uuid.uuid4().hex}.{ext}"
        job = IngestJob(kind="ingest", source=str(dest), name=volume_id, overwrite=overwrite, options=options)
        job = validate_job(job, settings, engine, upload=dest)
        declared = request.headers.get("content-length")
        if declared and declared.isdigit() and int(declared) > settings.max_upload_bytes:
            raise HttpError(413, f"body: upload of {declared} bytes exceeds the limit of {settings.max_upload_bytes}")
        room = settings.max_uploads_bytes - await run_in_threadpool(_bytes_in, uploads)
        full = HttpError(503, f"uploads: the server's space for uploads waiting to be ingested is full "
                              f"(LODCAST_MAX_UPLOADS_BYTES = {settings.max_uploads_bytes}); retry later",
                         {"Retry-After": "30"})
        if declared and declared.isdigit() and int(declared) > room:
            raise full
        size = 0
        try:
            with open(dest, "wb") as f:
                async for chunk in request.stream():
                    size += len(chunk)
                    if size > settings.max_upload_bytes:
                        raise HttpError(413, f"body: upload exceeds the limit of {settings.max_upload_bytes} bytes")
                    if size > room:
                        raise full
                    f.write(chunk)
            if size == 0:
                raise RequestInvalid.one(("body",), "body: the upload is empty")
            if format == "nifti" and gzipped(dest):  # nibabel reads a NIfTI by its name: .nii.gz is gzip
                zipped = dest.with_name(dest.name + ".gz")
                os.replace(dest, zipped)
                dest = zipped
                job = job.model_copy(update={"source": str(dest)})
            parked: Path | str = dest
            if settings.remote:  # the worker that ingests it may be on another host: parked beside the volumes
                parked = f"{settings.root}/.uploads/{dest.name}"
                await run_in_threadpool(park_upload, dest, parked)
                job = job.model_copy(update={"source": parked})
        except BaseException:
            dest.unlink(missing_ok=True)
            raise
        if settings.remote:
            dest.unlink(missing_ok=True)
        return status_json(await run_in_threadpool(jobs().submit, job, upload=parked))

    @app.get("/volumes/{volume_id}", tags=["volumes"], dependencies=auth, summary="One volume's attributes",
             response_model=VolumeSummary, responses=errors(400, 401, 404, 409))
    def get_volume(volume_id: VolumeId) -> dict[str, Any]:
        return summary_of(volume_id)

    @app.delete("/volumes/{volume_id}", tags=["volumes"], dependencies=auth, summary="Delete a volume's store",
                response_model=Deleted, responses=errors(400, 401, 404))
    def del_volume(volume_id: VolumeId) -> dict[str, Any]:
        path = volume_path(settings.root, volume_id)
        engine.forget(path)
        delete_volume(settings.root, volume_id)
        return {"deleted": volume_id}

    async def rendered(request: Request, volume_id: str, path: Any, samples: int,
                       call: Callable[[Callable[[], None]], Any], cancel: threading.Event | None = None) -> Any:
        """`call(stop)` on a worker thread, in a render slot: `stop` (between launch bands) raises _ClientGone once
        the client hangs up or `cancel` is set, HttpError past the render timeout; the renderer's refusals raise
        the HTTP errors that name them."""
        async with semaphore(samples):
            gone, t0 = cancel or threading.Event(), time.monotonic()

            def stop() -> None:  # between launch bands (renderer/frame/render.py: launch)
                if gone.is_set():
                    raise _ClientGone
                if time.monotonic() - t0 > settings.render_timeout_s:
                    raise HttpError(503, f"render: stopped after {settings.render_timeout_s:g} s "
                                         f"(LODCAST_RENDER_TIMEOUT_S); a larger sampling.step or fewer pixels "
                                         f"renders faster")

            async def watch() -> None:  # a client that hangs up cancels its render
                while not await request.is_disconnected():
                    await asyncio.sleep(0.2)
                gone.set()

            watcher = asyncio.create_task(watch())
            try:
                return await run_in_threadpool(call, stop)
            except (StoreNotFound, StoreInvalid) as exc:
                raise failure(volume_id, path, exc) from None
            except SceneError as exc:  # one the cost check could not see (a step too small for this volume)
                raise scene_refused(exc) from None
            except (ValueError, ArithmeticError) as exc:
                raise HttpError(400, f"scene: {' '.join(str(exc).split())}") from None
            except Exception as exc:
                raise (unavailable(settings, exc, volume_id) or exc) from None
            finally:
                watcher.cancel()

    @app.post(
        "/volumes/{volume_id}/render",
        tags=["render"],
        dependencies=auth,
        response_class=Response,
        summary="Render one image of a volume, or its progressive stages",
        responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}},
                                     "application/x-npy": {"schema": {"type": "string", "format": "binary"}},
                                     NDJSON: {"schema": {"type": "string"}}},
                         "description": "the image (PNG, or premultiplied float32 RGBA as .npy); the render report "
                                        "as JSON in the X-Lodcast-Report header. With progressive=true, one JSON "
                                        "line per stage, coarse to fine: {stage, final, report, image (base64 in "
                                        "the scene's format)}",
                         "headers": REPORT_HEADER},
                   **errors(400, 401, 404, 409, 413, 422, 503)},
    )
    async def render(volume_id: VolumeId, request: Request,
                     scene: Annotated[Scene, Body(description="what to render: camera, size, transfer function(s), "
                                                              "quality, sampling, shading, clipping, mode, format",
                                                  examples=[EXAMPLE_SCENE])],
                     progressive: Annotated[bool, Query(description="stream the render's stages, coarse to fine, "
                                                                    "as NDJSON (docs/serving.md)")] = False,
                     stages: Annotated[int | None, Query(ge=1, le=64, description="progressive: render at most this "
                                                         "many stages, coarsest first (a viewer's preview while the "
                                                         "user drags asks for 1); default all")] = None,
                     session: Annotated[str | None, Header(alias=SESSION_HEADER.lower(), max_length=128,
                                                           description="progressive: a newer stream of the same "
                                                                       "session cancels this one's stages to come")]
                     = None) -> Response:
        try:
            path = await run_in_threadpool(engine.locate, settings.root, volume_id)
        except Exception as exc:
            raise (unavailable(settings, exc, volume_id) or exc) from None
        sc = parse_scene(scene, settings)
        eng = engine
        started = time.perf_counter()
        try:  # before waiting for a render slot: a request that may not run is told so at once
            samples = await run_in_threadpool(eng.check_cost, path, sc, settings.max_samples)
        except CostError as exc:
            raise HttpError(413, " ".join(str(exc).split())) from None
        except SceneError as exc:  # the scene's view of this volume is degenerate (renderer/scene/camera.py: frame)
            raise scene_refused(exc) from None
        except (StoreNotFound, StoreInvalid) as exc:
            raise failure(volume_id, path, exc) from None
        except Exception as exc:
            raise (unavailable(settings, exc, volume_id) or exc) from None
        if progressive:
            return await progressive_response(request, volume_id, path, sc, samples, session, started, stages)
        try:
            result = await rendered(request, volume_id, path, samples,
                                    lambda stop: eng.render(path, sc, settings.max_samples, stop))
        except _ClientGone:
            return Response(status_code=499)  # nobody is listening; the status is for the access log
        data, media = await run_in_threadpool(encode, result, sc)
        report = json.dumps(finite_json(dict(result.report)), separators=(",", ":"), default=str)
        return Response(content=data, media_type=media, headers={"X-Lodcast-Report": report})

    async def progressive_response(request: Request, volume_id: str, path: Any, sc: Scene, samples: int,
                                   session: str | None, started: float, most: int | None) -> Response:
        """service/progressive.py: the first stage rendered here (its refusals are the plain route's), the others
        as the client reads the stream; `most` of them at most (a preview that wants the first stage alone leaves
        no later stage running after it hangs up)."""
        cancel = engine.sessions.begin(session)  # the session's older stream renders no more stages

        def first(stop: Callable[[], None]) -> tuple[Any, Any]:
            prog = engine.progressive(path, sc, started)
            return prog, prog.render(0, settings.max_samples, stop)

        try:
            prog, result = await rendered(request, volume_id, path, samples, first)
        except BaseException as exc:
            engine.sessions.end(session, cancel)
            if isinstance(exc, _ClientGone):
                return Response(status_code=499)
            raise

        async def stage(k: int) -> Any:
            return await rendered(request, volume_id, path, samples,
                                  lambda stop: prog.render(k, settings.max_samples, stop), cancel)

        lines = progressive_stream(result, min(len(prog.stages), most or len(prog.stages)), sc, stage, cancel,
                                   lambda: engine.sessions.end(session, cancel))
        return StreamingResponse(lines, media_type=NDJSON)

    # --- jobs ---------------------------------------------------------------------------------------------------
    def get_record(job_id: str) -> dict[str, Any]:
        if not JOB_ID.match(job_id):
            raise HttpError(404, f"id: no job {job_id[:64]!r} (job ids are 32 hex digits)")
        rec = jobs().get(job_id)
        if rec is None:
            raise HttpError(404, f"id: no job {job_id!r}")
        return rec

    @app.post("/jobs", status_code=202, tags=["jobs"], dependencies=auth, summary="Submit a batch job",
              response_model=JobStatus, responses=errors(400, 401, 404, 413, 422, 503))
    def post_job(job: Annotated[Job, Body(discriminator="kind")]) -> dict[str, Any]:
        return status_json(jobs().submit(validate_job(job, settings, engine)))

    @app.get("/jobs", tags=["jobs"], dependencies=auth, summary="The newest jobs, optionally in one state",
             response_model=list[JobStatus], responses=errors(401, 422, 503))
    def get_jobs(
        limit: Annotated[int, Query(ge=1, le=10_000)] = 100,
        state_: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query(alias="state")] = None,
    ) -> list[dict[str, Any]]:
        return [status_json(r) for r in jobs().list(limit=limit, states=(state_,) if state_ else None)]

    @app.get("/jobs/{job_id}", tags=["jobs"], dependencies=auth, summary="A job's state and progress",
             response_model=JobStatus, responses=errors(401, 404, 503))
    def get_job(job_id: JobId) -> dict[str, Any]:
        return status_json(get_record(job_id))

    @app.delete("/jobs/{job_id}", tags=["jobs"], dependencies=auth,
                summary="Cancel a job (a running one stops before its next frame)",
                response_model=JobStatus, responses=errors(401, 404, 503))
    def cancel_job(job_id: JobId) -> dict[str, Any]:
        get_record(job_id)
        return status_json(jobs().cancel(job_id) or get_record(job_id))

    @app.get("/jobs/{job_id}/results/{n}", tags=["jobs"], dependencies=auth, response_class=FileResponse,
             summary="Frame n of a job (0-based)",
             responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}},
                                          "application/x-npy": {"schema": {"type": "string", "format": "binary"}}},
                              "description": "the frame"}, **errors(401, 404, 422, 503)})
    def get_result(job_id: JobId, n: Annotated[int, PathParam(ge=0, le=10_000_000)]) -> Response:
        rec = get_record(job_id)
        if n >= max(int(rec["total"] or 0), 0) or rec["kind"] == "ingest":
            raise HttpError(404, f"n: job {job_id} has no result {n} (it has {0 if rec['kind'] == 'ingest' else rec['total']})")
        files = jobs().files(job_id)
        for ext, media in (("png", "image/png"), ("npy", "application/x-npy")):
            found = _result(files, frame_name(n, ext), media)
            if found is not None:
                return found
        raise HttpError(404, f"n: result {n} of job {job_id} is not written yet (state {rec['state']})")

    @app.get("/jobs/{job_id}/animation", tags=["jobs"], dependencies=auth, response_class=FileResponse,
             summary="A turntable's animation (GIF or MP4), once written",
             responses={200: {"content": {"image/gif": {"schema": {"type": "string", "format": "binary"}},
                                          "video/mp4": {"schema": {"type": "string", "format": "binary"}}},
                              "description": "the animation"}, **errors(401, 404, 503)})
    def get_animation(job_id: JobId) -> Response:
        rec = get_record(job_id)
        files = jobs().files(job_id)
        for fmt, media in (("gif", "image/gif"), ("mp4", "video/mp4")):
            found = _result(files, f"turntable.{fmt}", media)
            if found is not None:
                return found
        raise HttpError(404, f"animation: job {job_id} has no animation (state {rec['state']})")

    # --- the web viewer -----------------------------------------------------------------------------------------
    def opened(volume_id: str) -> Any:
        """A volume's opened store; the HTTP errors of one that cannot be used (as the render route's)."""
        try:
            path = engine.locate(settings.root, volume_id)
        except Exception as exc:
            raise (unavailable(settings, exc, volume_id) or exc) from None
        try:
            return engine.store(path)
        except (StoreNotFound, StoreInvalid) as exc:
            raise failure(volume_id, path, exc) from None
        except Exception as exc:
            raise (unavailable(settings, exc, volume_id) or exc) from None

    add_viewer(app, auth=auth, opened=opened, renderer=lambda: engine.renderer)
    return app
