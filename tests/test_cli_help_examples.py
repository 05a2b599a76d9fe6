"""Issue 46, item 3: every example that a `lodcast COMMAND --help` prints runs as printed, in a folder that holds
what the examples name: a DICOM CT series `ct_series/`, `head.nii.gz`, `scan.raw`, a store root `stores/` with the
volume the example jobs name (`ch2.zarr`), a copy of `examples/`, the demo's download already in its cache (the
MR head is not fetched from a package registry here), a redis-server for the `redis://` queues and an S3 server
(moto, on loopback) holding the bucket of `s3://bucket/volumes`.

What the test changes in a line, and why (nothing else):
- ports: `--port 8000` and `http://127.0.0.1:8000` become a free port, and a command that would serve on the
  default port (`serve` without `--port`, `demo` without `--no-serve`) gets `--port FREE`: a user's own server
  (./demo.sh) may hold 8000;
- `redis://localhost:6379/0` and `redis://queue-host:6379/0` become the test's redis-server;
- `JOB_ID` becomes the id of the job that the `submit --url` example made;
- commands that run until stopped (`serve`, `worker`, `demo` when it serves) run in the background until they are
  ready (the server answers /healthz, the worker prints its banner), are checked to be still running, and are
  stopped; the first `serve` example's server stays up for the `submit --url` and `jobs` examples (which find it,
  as their help says, through LODCAST_URL).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from phantoms import dicom_dataset, head

import lodcast
from lodcast.service.cli import build_parser
from lodcast.service.testing import RedisServer, free_port, in_ci, redis_available, s3_server

REPO = Path(__file__).resolve().parents[1]
RAW_SHAPE = (128, 256, 256)  # what the ingest example's --shape says (its file is made to fit)
COMMENT = re.compile(r"\s+#\s.*$")


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def help_examples() -> list[tuple[str, str]]:
    """(command, example line) for every example of every `lodcast COMMAND --help`, in the order printed."""
    out = []
    for name, command in _commands().items():
        text = command.format_help()
        assert "\nexamples:\n" in text, f"lodcast {name} --help shows no examples"
        out += [(name, line.strip()) for line in text.split("\nexamples:\n", 1)[1].splitlines() if line.strip()]
    return out


def _dicom_ct(folder: Path, n: int = 40) -> None:
    """A CT series in Hounsfield units (air, soft tissue, a shell of bone), one file per slice, as a scanner
    writes them: unsigned 12-bit pixels with intercept -1024."""
    from pydicom.uid import CTImageStorage, generate_uid

    folder.mkdir()
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2) / (n / 2)
    r = np.sqrt(z**2 + y**2 + x**2)
    hu = np.where(r < 0.9, 40.0, -1000.0)
    hu[(r > 0.45) & (r < 0.55)] = 900.0
    series, study = generate_uid(), generate_uid()
    for k in range(n):
        ds = dicom_dataset(CTImageStorage)
        ds.SeriesInstanceUID, ds.StudyInstanceUID = series, study
        ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = n, n, 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
        ds.PixelSpacing, ds.SliceThickness = [1.0, 1.0], 1.0
        ds.ImagePositionPatient, ds.ImageOrientationPatient = [0.0, 0.0, float(k)], [1, 0, 0, 0, 1, 0]
        ds.RescaleSlope, ds.RescaleIntercept = 1.0, -1024.0
        ds.PixelData = (hu[k] + 1024).astype(np.uint16).tobytes()
        ds.save_as(folder / f"IM{k:04d}", enforce_file_format=True)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import nibabel as nib

    ws = tmp_path_factory.mktemp("help")
    shutil.copytree(REPO / "examples", ws / "examples")
    _dicom_ct(ws / "ct_series")
    nib.save(nib.Nifti1Image(head(48), np.eye(4)), str(ws / "head.nii.gz"))
    with open(ws / "scan.raw", "wb") as f:  # zeros, sparse: the size the example's --shape and --dtype say
        f.truncate(int(np.prod(RAW_SHAPE)) * 2)
    lodcast.ingest(head(48), ws / "stores" / "ch2.zarr", progress=False)
    (ws / "cache" / "data").mkdir(parents=True)  # what the demo's download leaves (service/demo.py)
    nib.save(nib.Nifti1Image(head(48), np.eye(4)), str(ws / "cache" / "data" / "ch2.nii.gz"))
    (ws / "home").mkdir()
    return ws


def _env(ws: Path, **extra: str) -> dict[str, str]:
    from lodcast.environment import environment

    env = {k: v for k, v in os.environ.items() if not k.startswith("LODCAST_")}
    return {**env, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}",
            "LODCAST_CACHE": str(ws / "cache"),  # the demo's download, already there
            "LODCAST_CACHE_DIR": str(environment().cache_dir),  # the compiled kernels stay where they are
            **extra}


def _run(line: str, ws: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    p = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", line], cwd=ws, env=env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, f"{line}\nexit {p.returncode}\n--- stdout\n{p.stdout[-2000:]}\n--- stderr\n{p.stderr[-3000:]}"
    return p


class _Background:
    """A command that runs until stopped, in its own process group (stopped with the group: bash and its child)."""

    def __init__(self, line: str, cwd: Path, env: dict[str, str]) -> None:
        self.line, self.log = line, cwd / f"background-{time.monotonic_ns()}.log"
        with open(self.log, "wb") as out:
            self.p = subprocess.Popen(["bash", "-c", line], cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, start_new_session=True)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def stop(self) -> None:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.p.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.p.wait(15)
                return


def _until_ready(line: str, ws: Path, env: dict[str, str], ready: Callable[[str], bool]) -> _Background:
    """Start a command that runs until stopped; return it once `ready(its output)` holds, still running."""
    proc = _Background(line, ws, env)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.p.poll() is not None:
            pytest.fail(f"{line}\nexited {proc.p.returncode} before it was ready:\n{proc.text()[-3000:]}")
        if ready(proc.text()):
            return proc
        time.sleep(0.1)
    proc.stop()
    pytest.fail(f"{line}\nnot ready after 120 s:\n{proc.text()[-3000:]}")


def _answers(port: int) -> Callable[[str], bool]:
    import httpx

    def ready(_: str) -> bool:
        try:
            return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False

    return ready


def _with_port(line: str, port: int) -> str:
    """The line on `port`: its --port replaced, or --port added before its comment where it serves on the default."""
    if "--port 8000" in line:
        return line.replace("--port 8000", f"--port {port}")
    m = COMMENT.search(line)
    cut = m.start() if m else len(line)
    return f"{line[:cut]} --port {port}{line[cut:]}"


def test_every_command_shows_examples_of_itself():
    found = help_examples()
    commands = {c for c, _ in found}
    assert commands == set(_commands())
    for command, line in found:
        words = [w for w in line.split() if "=" not in w or w.startswith("-")]  # VAR=value before the command
        assert words[:2] == ["lodcast", command], line


def test_every_help_example_runs_as_printed(workspace: Path, tmp_path: Path):
    if redis_available() is None:
        msg = "redis-server not installed (Debian package redis-server): the redis:// examples cannot run"
        if in_ci():
            pytest.fail(msg)
        pytest.skip(msg)
    pytest.importorskip("moto")
    pytest.importorskip("s3fs")
    ws, ran = workspace, []
    servers: list[_Background] = []
    redis = RedisServer(tmp_path / "redis")
    env = _env(ws)
    url = job_id = None
    try:
        with s3_server():
            import fsspec

            fsspec.filesystem("s3", skip_instance_cache=True).mkdir("bucket")
            s3_env = _env(ws, **{k: os.environ[k] for k in os.environ if k.startswith("AWS_")},
                          HOME=str(ws / "home"))  # a root URL keeps its queue in ~/.lodcast/state
            for command, printed in help_examples():
                line = (printed.replace("redis://localhost:6379/0", redis.url)
                        .replace("redis://queue-host:6379/0", redis.url))
                if url is not None:
                    line = line.replace("http://127.0.0.1:8000", url)
                if command == "serve" or (command == "demo" and "--no-serve" not in line):
                    port = free_port()
                    proc = _until_ready(_with_port(line, port), ws, s3_env if "s3://" in line else env, _answers(port))
                    if url is None and command == "serve":  # kept for the submit --url and jobs examples
                        url, env = f"http://127.0.0.1:{port}", {**env, "LODCAST_URL": f"http://127.0.0.1:{port}"}
                        servers.append(proc)
                    else:
                        proc.stop()
                elif command == "worker":
                    _until_ready(line, ws, env, lambda log: "lodcast worker" in log and "redis queue" in log).stop()
                elif command == "jobs":
                    assert job_id is not None, "the jobs examples need the job of a submit --url example"
                    _run(line.replace("JOB_ID", job_id), ws, env)
                else:
                    assert "JOB_ID" not in line and ":8000" not in line, line
                    p = _run(line, ws, env if command != "submit" or "--url" in line else
                             {k: v for k, v in env.items() if k != "LODCAST_URL"})
                    if command == "submit":
                        status = json.loads(p.stdout)
                        assert status["state"] == "done", status
                        if "--url" in line:
                            job_id = status["id"]
                ran.append(printed)
    finally:
        for proc in servers:
            proc.stop()
        redis.stop()
    assert ran == [line for _, line in help_examples()]
    # what the examples made
    for store in ("chest.zarr", "head.zarr", "scan.zarr"):
        assert lodcast.open_store(ws / store).summary()["shape"], store
    assert lodcast.open_store(ws / "scan.zarr").summary()["shape"] == list(RAW_SHAPE)
    for name in ("chest.png", "bone.png", "head.jpg", "lod.png", "report.json", "report/report.md"):
        assert (ws / name).stat().st_size > 0, name
    frames = json.loads((ws / "examples" / "turntable.job.json").read_text())["frames"]
    assert len(list((ws / "frames").glob("frame_*.png"))) == frames
    assert (ws / "frames" / "turntable.gif").read_bytes()[:4] == b"GIF8"  # `jobs results` fetches the animation too
