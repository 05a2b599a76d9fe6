"""The README's commands and snippets, run as written (issue 15: a new user copies them): every ```bash and
```python block, in order, in one folder that holds what they name (`scan.nii.gz`, `volume.raw`, a CT store
`ct.zarr`, the demo's `demo-output/ch2.zarr`, `examples/`, `.venv`), with `lodcast serve` in the background as the
README starts it, but on a free port rather than the README's 8000, which a user's ./demo.sh may hold (issue 46: the
blocks' port is rewritten). A block preceded by `<!-- not run by tests/test_readme.py: REASON -->` is skipped and
must say why; ```json blocks must be valid scenes."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from phantoms import head

import lodcast

REPO = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"(?:<!-- not run by tests/test_readme.py: (?P<why>[^>]*?) -->\n)?```(?P<lang>\w*)\n(?P<body>.*?)```",
                   re.S)


def blocks() -> list[tuple[str, str, str | None]]:
    return [(m["lang"], m["body"], m["why"]) for m in FENCE.finditer((REPO / "README.md").read_text())]


def _ct(n: int) -> np.ndarray:
    z, y, x = (np.mgrid[:n, :n, :n] - (n - 1) / 2) / (n / 2)
    r = np.sqrt(z**2 + y**2 + x**2)
    ct = np.where(r < 0.9, 40.0, -1000.0)
    ct[(r > 0.45) & (r < 0.55)] = 900.0
    return ct.astype(np.int16)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import nibabel as nib

    ws = tmp_path_factory.mktemp("readme")
    (ws / ".venv").symlink_to(Path(sys.prefix))  # the environment running the tests: ./test.sh's .venv
    (ws / "examples").symlink_to(REPO / "examples")
    nib.save(nib.Nifti1Image(head(128), np.diag([1.0, 1.0, 1.0, 1.0])), str(ws / "scan.nii.gz"))
    (np.random.default_rng(0).integers(0, 4000, (64, 128, 128)).astype(">u2")).tofile(ws / "volume.raw")
    lodcast.ingest(_ct(64), ws / "ct.zarr")
    lodcast.ingest(head(64), ws / "demo-output" / "ch2.zarr")
    return ws


def _env(ws: Path) -> dict[str, str]:
    venv_bin = (ws / ".venv" / "bin").resolve()
    return {**os.environ, "PATH": f"{venv_bin}{os.pathsep}{os.environ.get('PATH', '')}", "LODCAST_URL": "",
            "LODCAST_TOKEN": "", "HOME": os.environ.get("HOME", str(ws))}


#: the port the README's server and clients name; the test runs them on a free port instead (its own rewrite of
#: the blocks), so that ./test.sh passes while a user's ./demo.sh keeps serving on 8000
README_PORT = 8000


def _port(text: str, port: int) -> str:
    """`text` with the README's port replaced by `port` (the serve command's --port and every URL)."""
    return (text.replace(f"--port {README_PORT}", f"--port {port}")
            .replace(f"127.0.0.1:{README_PORT}", f"127.0.0.1:{port}"))


def _serve(ws: Path, body: str, port: int) -> subprocess.Popen:
    """The README's serve command (the first line of its block, comment dropped), on `port`."""
    command = _port(body.strip().splitlines()[0].split("#", 1)[0].strip(), port)
    assert command.startswith("lodcast serve ") and f"--port {port}" in command, command
    proc = subprocess.Popen(["bash", "-c", f"exec {command}"], cwd=ws, env=_env(ws), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    import httpx

    for _ in range(300):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.1)
    proc.kill()
    pytest.fail(f"{command} did not answer")


def test_every_skipped_block_says_why_and_json_blocks_are_scenes():
    found = blocks()
    assert sum(1 for lang, _, _ in found if lang in ("bash", "python")) >= 8
    for lang, body, why in found:
        if why is not None:
            assert len(why) > 20 and lang == "bash", (why, body[:80])
        if lang == "json":
            lodcast.Scene.parse(body)


def test_the_readme_runs_as_written(workspace):
    from lodcast.service.testing import free_port

    ws, server, ran, port = workspace, None, 0, free_port()
    assert f"--port {README_PORT}" in (REPO / "README.md").read_text()  # what _port rewrites
    try:
        for lang, body, why in blocks():
            if why is not None or lang not in ("bash", "python"):
                if why is not None and "lodcast serve" in body and server is None:
                    server = _serve(ws, body, port)
                continue
            body = _port(body, port)
            cmd = ["bash", "-e", "-o", "pipefail", "-c", body] if lang == "bash" else [str(ws / ".venv/bin/python"), "-c", body]
            out = subprocess.run(cmd, cwd=ws, env=_env(ws), capture_output=True, text=True, timeout=600)
            assert out.returncode == 0, f"README block failed ({out.returncode}):\n{body}\n--- stdout\n{out.stdout[-2000:]}\n--- stderr\n{out.stderr[-3000:]}"
            ran += 1
    finally:
        if server is not None:
            server.terminate()
            server.wait(timeout=30)
    assert ran >= 6
    for name in ("head.png", "bone.webp", "scan.png", "ct.npy", "ribs.png", "body-dense.png", "head-http.png", "report.json"):
        assert (ws / name).stat().st_size > 0, name
    assert len(list((ws / "frames").glob("frame_*.png"))) == json.loads((REPO / "examples/turntable.job.json").read_text())["frames"]
