"""Object storage that fails fast: bounded connect and read timeouts and a bounded number of tries for the S3 client
(s3fs over botocore), so that the first request of an outage is answered 503 (service/faults.py) within seconds. Left
alone, botocore's retries run inside s3fs' own, and a dropped connection surfaces only after both have run out."""
from __future__ import annotations

from typing import Any

__all__ = ["s3_limits", "bound_object_storage"]


def s3_limits(settings: Any) -> dict[str, Any]:
    """The settings `bound_object_storage` takes, as keywords (they cross to an ingest child process as they are)."""
    return {"connect_timeout_s": settings.s3_connect_timeout_s, "read_timeout_s": settings.s3_read_timeout_s,
            "retries": settings.s3_retries}


def bound_object_storage(connect_timeout_s: float, read_timeout_s: float, retries: int) -> None:
    """Make every S3 filesystem this process opens from now on give up after `retries` retries (botocore's standard
    mode: a short random backoff) of `connect_timeout_s` / `read_timeout_s` each. Set as fsspec's defaults for the s3 protocol, because filesystems are
    made from URLs all over lodcast (stores, results, uploads); what the deployment configured for fsspec itself (its
    config file, FSSPEC_S3_* variables) wins."""
    import fsspec.config

    client = fsspec.config.conf.setdefault("s3", {}).setdefault("config_kwargs", {})
    client.setdefault("connect_timeout", connect_timeout_s)
    client.setdefault("read_timeout", read_timeout_s)
    client.setdefault("retries", {"max_attempts": retries + 1, "mode": "standard"})
    try:
        import s3fs
    except ImportError:  # a local-only install: no object storage
        return
    # s3fs retries dropped connections and read timeouts around botocore's own tries, which multiplies them: botocore
    # keeps the count, s3fs tries once (it takes its count only as a class attribute)
    s3fs.S3FileSystem.retries = 1
