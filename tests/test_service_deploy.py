"""deploy/: the loopback smoke script runs (redis-server, lodcast serve, two workers, a turntable over HTTP), and the
compose file and systemd units say what they must."""
from __future__ import annotations

import configparser
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lodcast.service.testing import in_ci, redis_available

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def test_smoke_script():
    if redis_available() is None:
        msg = "redis-server not installed (Debian package redis-server): deploy/smoke.sh cannot run"
        if in_ci():
            pytest.fail(msg)
        pytest.skip(msg)
    env = {k: v for k, v in os.environ.items() if not k.startswith("LODCAST_")}
    r = subprocess.run(["bash", str(DEPLOY / "smoke.sh")], env={**env, "LODCAST_PYTHON": sys.executable},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "smoke: OK" in r.stdout


def test_systemd_units_stop_by_cgroup():
    for name in ("lodcast-api.service", "lodcast-worker@.service"):
        unit = configparser.ConfigParser(strict=False, interpolation=None)
        unit.optionxform = str  # type: ignore[assignment]
        unit.read(DEPLOY / "systemd" / name)
        svc = unit["Service"]
        assert svc["KillMode"] == "control-group" and svc["KillSignal"] == "SIGTERM"
        assert svc["EnvironmentFile"] == "/etc/lodcast/lodcast.env"
    env = (DEPLOY / "systemd" / "lodcast.env").read_text()
    for key in ("LODCAST_ROOT=", "LODCAST_QUEUE=redis://", "LODCAST_TOKEN=", "LODCAST_WORKERS=0"):
        assert key in env


def test_compose_file():
    yaml = pytest.importorskip("yaml", reason="PyYAML not installed")
    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = doc["services"]
    assert {"redis", "api", "worker"} <= set(services)
    assert services["worker"]["command"] == ["lodcast", "worker"]
    assert services["api"]["environment"]["LODCAST_QUEUE"].startswith("redis://")
    assert services["api"]["environment"]["LODCAST_WORKERS"] == "0"
