"""Issue 15, item 4: jobs from the command line cannot go nowhere — without a server a submitted job runs at once,
`jobs wait` exits non-zero on a timeout, `jobs results` fetches the frames, and looking up a job where there is no
queue says so instead of creating one in the current folder."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

import lodcast

JOB = {"kind": "turntable", "volume": "v", "frames": 3,
       "scene": {"tf": {"points": [{"value": 0, "opacity": 0.0}, {"value": 1, "opacity": 0.5}]}, "width": 16,
                 "height": 12}}


def lc(*args, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    import os

    e = {k: v for k, v in os.environ.items() if k not in ("LODCAST_URL", "LODCAST_ROOT")} | (env or {})
    return subprocess.run([sys.executable, "-m", "lodcast.service.cli", *args], cwd=cwd, capture_output=True,
                          text=True, env=e, timeout=300)


def test_local_submit_runs_and_results_come_back(tmp_path):
    lodcast.ingest(np.random.default_rng(0).random((16, 16, 16)).astype(np.float32), tmp_path / "v", block_size=8)
    (tmp_path / "job.json").write_text(json.dumps(JOB))
    p = lc("submit", "job.json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    st = json.loads(p.stdout)
    assert st["state"] == "done" and st["progress"] == {"done": 3, "total": 3}
    p = lc("jobs", "results", st["id"], "-o", "frames", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in (tmp_path / "frames").iterdir()) == [f"frame_{k:05d}.png" for k in range(3)]
    p = lc("jobs", "wait", st["id"], cwd=tmp_path)
    assert p.returncode == 0 and json.loads(p.stdout)["state"] == "done"
    p = lc("jobs", "results", st["id"], cwd=tmp_path)
    assert p.returncode == 2 and "-o" in p.stderr


def test_no_queue_here_is_a_one_line_refusal_and_creates_nothing(tmp_path):
    p = lc("jobs", "wait", "0" * 32, cwd=tmp_path)
    assert p.returncode == 2
    (line,) = p.stderr.strip().splitlines()
    assert "no local job queue" in line and "--url" in line
    assert not any(tmp_path.iterdir())


def test_wait_times_out_with_exit_1(tmp_path):
    from lodcast.service.jobs import parse_job, validate_job
    from lodcast.service.queue import JobQueue
    from lodcast.service.settings import Settings

    lodcast.ingest(np.zeros((8, 8, 8), np.float32), tmp_path / "v", block_size=8)
    jq = JobQueue(Settings(root=tmp_path))
    rec = jq.submit(validate_job(parse_job(JOB), jq.settings, jq.engine))  # queued, no worker
    p = lc("jobs", "wait", rec["id"], "--timeout", "0.3", cwd=tmp_path)
    assert p.returncode == 1 and "still queued after 0.3 s" in p.stderr
    assert json.loads(p.stdout)["state"] == "queued"


def test_results_fetch_a_turntables_animation_too(tmp_path):
    """Issue 46, item 3: `lodcast jobs results ID -o DIR` writes the turntable's animation beside its frames, from
    the local queue and from a server; a job without one gets its frames only."""
    from lodcast.service.testing import free_port, running, start_serve

    lodcast.ingest(np.random.default_rng(0).random((16, 16, 16)).astype(np.float32), tmp_path / "v", block_size=8)
    (tmp_path / "gif.json").write_text(json.dumps({**JOB, "animation": "gif", "fps": 5}))
    (tmp_path / "plain.json").write_text(json.dumps(JOB))
    frames = [f"frame_{k:05d}.png" for k in range(3)]
    p = lc("submit", "gif.json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    p = lc("jobs", "results", json.loads(p.stdout)["id"], "-o", "local", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in (tmp_path / "local").iterdir()) == [*frames, "turntable.gif"]
    assert str(Path("local") / "turntable.gif") in p.stdout.splitlines()
    assert (tmp_path / "local" / "turntable.gif").read_bytes()[:4] == b"GIF8"
    port = free_port()
    with running(start_serve(tmp_path, port, env={"LODCAST_TOKEN": ""})):
        url = {"LODCAST_URL": f"http://127.0.0.1:{port}"}
        for job, out, want in (("gif.json", "remote", [*frames, "turntable.gif"]), ("plain.json", "plain", frames)):
            p = lc("submit", job, "--wait", cwd=tmp_path, env=url)
            assert p.returncode == 0, p.stderr
            p = lc("jobs", "results", json.loads(p.stdout)["id"], "-o", out, cwd=tmp_path, env=url)
            assert p.returncode == 0, p.stderr
            assert sorted(f.name for f in (tmp_path / out).iterdir()) == want
    assert (tmp_path / "remote" / "turntable.gif").read_bytes() == (tmp_path / "local" / "turntable.gif").read_bytes()
