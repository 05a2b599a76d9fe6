#!/usr/bin/env bash
# Smoke test of a multi-process deployment on ONE machine, loopback only: redis-server (Debian package
# redis-server), `lodcast serve` with a Redis queue and no in-process worker, two `lodcast worker`s; a turntable job
# is submitted over HTTP and its frames are checked. Every process runs in its own process group and is stopped by
# group. Exit status 0 when everything worked.
#
#   deploy/smoke.sh                 # uses `lodcast` and `python3` from PATH (or LODCAST_PYTHON)
#   LODCAST_PYTHON=.venv/bin/python deploy/smoke.sh
set -euo pipefail

PY=${LODCAST_PYTHON:-python3}
REDIS=${REDIS_SERVER:-$(command -v redis-server || echo /usr/bin/redis-server)}
[ -x "$REDIS" ] || { echo "smoke: redis-server not found (apt-get install redis-server)" >&2; exit 2; }

WORK=$(mktemp -d -t lodcast-smoke-XXXXXX)
ROOT=$WORK/root
mkdir -p "$ROOT"
free_port() { "$PY" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
RPORT=$(free_port)
HPORT=$(free_port)
URL=http://127.0.0.1:$HPORT
QUEUE=redis://127.0.0.1:$RPORT/0
PGIDS=()

start() {  # start "$@" in a new session (its own process group); remember the group
    local log=$1; shift
    setsid "$@" >"$WORK/$log" 2>&1 < /dev/null &
    PGIDS+=("$!")
}
cleanup() {
    local rc=$?
    for pg in "${PGIDS[@]}"; do kill -TERM -- "-$pg" 2>/dev/null || true; done
    sleep 1
    for pg in "${PGIDS[@]}"; do kill -KILL -- "-$pg" 2>/dev/null || true; done
    if [ "$rc" -ne 0 ]; then
        echo "smoke: FAILED (rc $rc); logs in $WORK" >&2
        tail -n 20 "$WORK"/*.log >&2 || true
    else
        rm -rf "$WORK"
    fi
}
trap cleanup EXIT

echo "smoke: redis-server on 127.0.0.1:$RPORT"
start redis.log "$REDIS" --port "$RPORT" --bind 127.0.0.1 --save "" --appendonly no --dir "$WORK"
for _ in $(seq 100); do "$PY" -c "import redis,sys; sys.exit(0 if redis.Redis(port=$RPORT).ping() else 1)" 2>/dev/null && break; sleep 0.1; done

echo "smoke: ingesting a small volume into $ROOT/blob"
"$PY" - "$ROOT" <<'PY'
import sys
import numpy as np
import lodcast
z, y, x = np.mgrid[:48, :48, :48].astype(np.float32)
v = 1000 * np.exp(-((z - 24) ** 2 + (y - 20) ** 2 + (x - 30) ** 2) / 120.0)
lodcast.ingest(v.astype(np.float32), f"{sys.argv[1]}/blob", block_size=16)
PY

export LODCAST_ROOT=$ROOT LODCAST_QUEUE=$QUEUE LODCAST_TOKEN=smoke-token
echo "smoke: lodcast serve at $URL (no in-process worker), two workers"
start serve.log "$PY" -m lodcast.service.cli serve --host 127.0.0.1 --port "$HPORT" --workers 0
start worker1.log "$PY" -m lodcast.service.cli worker
start worker2.log "$PY" -m lodcast.service.cli worker
for _ in $(seq 300); do "$PY" -c "import httpx,sys; sys.exit(0 if httpx.get('$URL/healthz').status_code == 200 else 1)" 2>/dev/null && break; sleep 0.2; done

cat > "$WORK/job.json" <<'JSON'
{"kind": "turntable", "volume": "blob", "frames": 12, "animation": "gif",
 "scene": {"camera": {"azimuth": 0, "elevation": 20}, "width": 96, "height": 96,
           "tf": {"points": [{"value": 50, "color": [0.3, 0.5, 1.0], "opacity": 0.0},
                             {"value": 900, "color": [1.0, 0.9, 0.8], "opacity": 0.7}]}}}
JSON
echo "smoke: submitting a 12-frame turntable"
"$PY" -m lodcast.service.cli submit "$WORK/job.json" --url "$URL" --wait > "$WORK/status.json"
"$PY" - "$URL" "$WORK/status.json" <<'PY'
import json, sys
import lodcast
url, status = sys.argv[1], json.load(open(sys.argv[2]))
assert status["state"] == "done", status
assert status["progress"] == {"done": 12, "total": 12}, status
c = lodcast.Client(url)
frames = c.results(status["id"])
assert len(frames) == 12 and all(f[:8] == b"\x89PNG\r\n\x1a\n" for f in frames), "frames missing or not PNG"
assert len(set(frames)) > 1, "every frame is the same: the camera did not turn"
assert c.animation(status["id"])[:3] == b"GIF"
r = c.render("blob", {"width": 64, "height": 64, "tf": {"points": [{"value": 50, "opacity": 0}, {"value": 900, "opacity": 0.7}]}})
assert r.rgba.shape == (64, 64, 4) and r.rgba[..., 3].max() > 0
print(f"smoke: job {status['id']} done: 12 PNG frames and a GIF; a direct render works")
PY
grep -q "lodcast worker" "$WORK/worker1.log" && grep -q "lodcast worker" "$WORK/worker2.log"
echo "smoke: OK"
