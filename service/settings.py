"""Service settings: environment variables (prefix ``LODCAST_``) or keyword arguments; nothing is read at import time."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from lodcast.store.remote import is_url

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Everything the HTTP service, the job queue and the workers need to agree on.

    ``root`` is the store root: volumes are stores directly under it (their id is the folder name). It is a folder
    or an fsspec URL (``s3://bucket/prefix``: stores on object storage, read with shard-level range requests and
    published atomically by ingest). The embedded SQLite queue and uploads live in hidden folders (``.lodcast/``,
    ``.uploads/``) of the state folder: ``state_root`` (LODCAST_STATE_ROOT), else the root itself when it is a
    folder. Job results go to ``.jobs/`` of the state folder, or of the root when it is a URL (``results``).
    """

    model_config = SettingsConfigDict(env_prefix="LODCAST_", extra="ignore")

    root: Path | str = Field(default=Path("."), description="store root: a folder, or an fsspec URL such as "
                             "s3://bucket/prefix (LODCAST_ROOT)")
    state_root: Path | None = Field(default=None, description="local folder for job results, the embedded SQLite "
                                    "queue and uploads (LODCAST_STATE_ROOT); default: the root when it is a folder, else "
                               "~/.lodcast/state/<the root's hash>")
    token: str | None = Field(default=None, description="bearer token every route but /healthz and the docs requires (LODCAST_TOKEN)")
    queue: str | None = Field(
        default=None,
        description="job queue: None or 'sqlite' for the embedded SQLite queue under ROOT/.lodcast, "
        "'sqlite:///path/queue.db', or 'redis://host:port/db' (LODCAST_QUEUE)",
    )
    queue_name: str = Field(default="lodcast", description="queue / key prefix, so that several services can share one Redis")
    import_roots: Annotated[list[Path], NoDecode] = Field(
        default_factory=list,
        description="server-side folders POST /volumes may ingest from (env: a JSON list or os.pathsep-separated paths)",
    )

    # caps on what one request may ask for
    max_width: int = Field(default=4096, ge=1)
    max_height: int = Field(default=4096, ge=1)
    max_frames: int = Field(default=3600, ge=1)
    max_scenes: int = Field(default=1000, ge=1, description="most scenes / TFs / volumes in one job")
    min_step: float = Field(default=0.05, gt=0, description="smallest sampling step (voxels of the finest level)")
    max_upload_bytes: int = Field(default=2 * 1024**3, ge=0)
    max_uploads_bytes: int = Field(default=8 * 1024**3, ge=0, description="quota of ROOT/.uploads: uploads waiting "
                                   "for their ingest job, all together; beyond it an upload is refused with 503 "
                                   "(LODCAST_MAX_UPLOADS_BYTES)")
    upload_grace_s: float = Field(default=600.0, gt=0, description="an uploaded file that no queued or running job "
                                  "reads (its job cancelled, failed or never submitted) is deleted once it is this "
                                  "old")
    max_body_bytes: int = Field(default=16 * 1024**2, ge=1024, description="largest JSON request body (uploads: "
                                "max_upload_bytes) (LODCAST_MAX_BODY_BYTES)")
    max_voxels: int = Field(default=2**33, ge=1, description="largest volume an ingest job accepts, checked on the "
                            "source's declared shape before anything is read: a small compressed upload may declare "
                            "a huge volume (LODCAST_MAX_VOXELS)")
    max_ingest_memory_mb: float = Field(default=4000.0, gt=0, description="most memory (10⁶ bytes) one ingest "
                                        "job may need, estimated from the source's declared slice size Y x X "
                                        "(LODCAST_MAX_INGEST_MEMORY_MB)")
    max_samples: int = Field(default=2_000_000_000, ge=1, description="most samples (rays x samples per ray, estimated "
                             "before rendering) one render may take (LODCAST_MAX_SAMPLES)")
    max_job_samples: int = Field(default=10**12, ge=1, description="most samples one job may take in all (each "
                                 "frame estimated as for LODCAST_MAX_SAMPLES, summed at submission; above it the "
                                 "job is refused with 422 naming frames or scenes) (LODCAST_MAX_JOB_SAMPLES)")
    device_budget_mb: float | None = Field(default=None, gt=0, description="most device memory (10⁶ bytes) one "
                                           "render's volume data may use; larger ones render in passes "
                                           "(LODCAST_DEVICE_BUDGET_MB; default: one device allocation)")

    open_stores: int | None = Field(default=None, ge=1, description="stores the service keeps opened, least "
                                    "recently used closed first (LODCAST_OPEN_STORES; default 32)")

    # concurrency
    render_concurrency: int = Field(default=2, ge=1, description="renders running at once; others wait in FIFO order")
    small_render_samples: int = Field(default=50_000_000, ge=0, description="renders estimated at no more samples "
                                      "have a render slot of their own beside render_concurrency")
    render_timeout_s: float = Field(default=120.0, gt=0, description="a render still running after this many seconds "
                                    "is stopped between launch bands (LODCAST_RENDER_TIMEOUT_S)")
    workers: int = Field(default=1, ge=0, description="in-process job workers of `lodcast serve` (0: none)")
    job_helpers: int = Field(default=3, ge=0, description="a running job asks this many idle workers (here or on "
                             "other hosts sharing the queue) to render its frames beside it, each frame once "
                             "(LODCAST_JOB_HELPERS)")

    # crash safety
    retry_after_s: int = Field(default=5, ge=1, description="Retry-After of a 503 for a storage fault (object "
                               "storage unreachable or throttling, a full disk), in seconds")
    store_check_s: float = Field(default=2.0, ge=0, description="a volume on object storage found and opened is "
                                 "trusted this long before its existence and root metadata are asked again (0: every "
                                 "request)")
    storage_retries: int = Field(default=5, ge=0, description="times a job whose storage has a transient fault is "
                                 "resumed before it fails with the error (LODCAST_STORAGE_RETRIES)")
    storage_backoff_s: float = Field(default=2.0, gt=0, description="first wait before a job resumes after a storage "
                                     "fault; doubled each time, at most 60 s")
    s3_connect_timeout_s: float = Field(default=3.0, gt=0, description="object storage: seconds to wait for a "
                                        "connection before the try fails (LODCAST_S3_CONNECT_TIMEOUT_S)")
    s3_read_timeout_s: float = Field(default=10.0, gt=0, description="object storage: seconds to wait for the next "
                                     "bytes of an answer (LODCAST_S3_READ_TIMEOUT_S)")
    s3_retries: int = Field(default=2, ge=0, description="object storage: retries of a request that found no "
                            "answer, before the fault is answered 503 (LODCAST_S3_RETRIES)")
    health_every_s: float = Field(default=1.0, gt=0, description="how often /healthz's components (store root, "
                                  "queue, device) are probed, off the request path")
    heartbeat_s: float = Field(default=2.0, gt=0, description="how often a running job refreshes its heartbeat")
    stale_after_s: float = Field(default=15.0, gt=0, description="a running job whose heartbeat is older is re-enqueued")
    reap_every_s: float = Field(default=5.0, gt=0, description="how often stale jobs are looked for")
    poll_s: float = Field(default=0.2, gt=0, description="how often an idle worker polls the SQLite queue")
    frame_delay_s: float = Field(default=0.0, ge=0, description="pause after each job frame (tests and demos only)")
    keep_jobs_s: float = Field(default=7 * 86400, ge=0, description="finished, failed and cancelled jobs (record "
                               "and results) are deleted this long after they end; 0 keeps them forever")
    expire_every_s: float = Field(default=60.0, gt=0, description="how often the reaper deletes expired jobs")

    @field_validator("root", mode="after")
    @classmethod
    def _absolute(cls, v: Path | str) -> Path | str:
        text = os.fspath(v)
        if is_url(text):  # a URL: kept as given, without a trailing slash (ids are appended with one)
            if text.startswith("file://"):
                return Path(text[len("file://"):]).expanduser().resolve()
            return text.rstrip("/")
        return Path(text).expanduser().resolve()

    @field_validator("state_root", mode="after")
    @classmethod
    def _absolute_state(cls, v: Path | None) -> Path | None:
        return None if v is None else Path(v).expanduser().resolve()

    @field_validator("max_samples", "max_voxels", "max_job_samples", mode="before")
    @classmethod
    def _count(cls, v: object) -> object:
        return int(float(v)) if isinstance(v, str) and v.strip() else v  # "2e9" reads as 2000000000

    @field_validator("import_roots", mode="before")
    @classmethod
    def _split_roots(cls, v: object) -> object:
        if isinstance(v, str):
            text = v.strip()
            if text.startswith("["):
                return json.loads(text)
            return [p for p in text.split(os.pathsep) if p]
        return v

    @field_validator("import_roots", mode="after")
    @classmethod
    def _absolute_list(cls, v: list[Path]) -> list[Path]:
        return [Path(p).expanduser().resolve() for p in v]

    # --- derived paths --------------------------------------------------------------------------------------
    @property
    def remote(self) -> bool:
        """Whether the store root is a URL (object storage) rather than a folder."""
        return isinstance(self.root, str)

    @property
    def local_root(self) -> Path:
        """The folder holding the service's own files: ``state_root``, else the root folder, else a folder per root URL
        under ~/.lodcast/state (so that a restarted service finds its jobs again)."""
        if self.state_root is not None:
            return self.state_root
        if isinstance(self.root, Path):
            return self.root
        return Path.home() / ".lodcast" / "state" / hashlib.sha1(self.root.encode()).hexdigest()[:16]

    @property
    def state_dir(self) -> Path:
        return self.local_root / ".lodcast"

    @property
    def jobs_dir(self) -> Path:
        return self.local_root / ".jobs"

    @property
    def results(self) -> Path | str:
        """Where job results go (service/results.py): the state folder's .jobs/, or ROOT/.jobs on object storage
        when the root is a URL, shared by every host that shares the queue."""
        return f"{self.root}/.jobs" if isinstance(self.root, str) else self.jobs_dir

    @property
    def uploads_dir(self) -> Path:
        """Uploaded files waiting for their ingest job."""
        return self.local_root / ".uploads"

    @property
    def is_redis(self) -> bool:
        return bool(self.queue) and str(self.queue).startswith(("redis://", "rediss://", "unix://"))

    def sqlite_path(self) -> Path:
        q = self.queue or ""
        if q.startswith("sqlite://") and len(q) > len("sqlite://"):
            return Path(q[len("sqlite://") :])  # sqlite:///abs/path.db
        return self.state_dir / "queue.db"
