"""`lodcast ingest SRC s3://…` whose object storage is unreachable (issue 49, item 2): exit 2 with one line naming the
store, no traceback, and no local copy left behind. moto's S3 on loopback behind the test proxy, cut; and an
endpoint whose port nothing listens on.

The S3 client in the CLI is told to try once (fsspec's FSSPEC_S3 variable), so that each case takes a moment
instead of the libraries' retries; the exit code and the line do not depend on it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto")

from lodcast.service.testing import free_port, s3_server  # noqa: E402

BUCKET = "lodcast-cli-faults"
ONE_TRY = json.dumps({"config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 2, "read_timeout": 5}})


def _ingest(src: Path, dest: str, tmp: Path, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lodcast.service.cli", "ingest", str(src), dest],
                          env={**os.environ, "FSSPEC_S3": ONE_TRY, "LODCAST_TMP": str(tmp), **env},
                          capture_output=True, text=True, timeout=120)


def _one_line_naming(done: subprocess.CompletedProcess, dest: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("lodcast ingest: error: ") and dest in lines[0] and "unavailable" in lines[0], lines[0]


@pytest.fixture
def source(tmp_path: Path) -> Path:
    src = tmp_path / "vol.npy"
    np.save(src, np.arange(16 * 16 * 16, dtype=np.uint16).reshape(16, 16, 16))
    return src


def test_an_ingest_whose_object_storage_is_cut_exits_2_naming_the_store(source: Path, tmp_path: Path):
    import fsspec

    tmp = tmp_path / "copies"
    tmp.mkdir()
    dest = f"s3://{BUCKET}/cut.zarr"
    with s3_server() as srv:
        fsspec.filesystem("s3", skip_instance_cache=True).mkdir(BUCKET)
        srv.fault = "cut"  # every connection dropped without an answer
        try:
            done = _ingest(source, dest, tmp)
        finally:
            srv.fault = None
        _one_line_naming(done, dest)
        assert not fsspec.filesystem("s3", skip_instance_cache=True).exists(dest)
    assert list(tmp.iterdir()) == []  # the local copy of the store went with the failure


def test_an_ingest_whose_endpoint_is_gone_exits_2_naming_the_store(source: Path, tmp_path: Path):
    dest = f"s3://{BUCKET}/gone.zarr"
    done = _ingest(source, dest, tmp_path, AWS_ENDPOINT_URL=f"http://127.0.0.1:{free_port()}",
                   AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing", AWS_DEFAULT_REGION="us-east-1")
    _one_line_naming(done, dest)
    assert "Traceback" not in done.stderr
