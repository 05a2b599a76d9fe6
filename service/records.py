"""Job records kept beside the queue: state, progress, heartbeat, owner, timings, error.

huey moves task messages; it does not know whether a job's worker died. The record does: every state change is a
compare-and-set (``update(..., expect=...)``), so that exactly one worker owns a running job, a cancelled job stays
cancelled, and a job completes exactly once. Two back ends with one interface: a SQLite table (one machine) and a
Redis hash per job plus a sorted set of ids (several hosts).
"""
from __future__ import annotations

import builtins
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["FIELDS", "ACTIVE", "FINAL", "Records", "SqliteRecords", "RedisRecords", "open_records"]

#: field -> type; every record has all of them. Times are Unix seconds (float) or None.
FIELDS: dict[str, type] = {
    "id": str,
    "kind": str,
    "spec": str,  # the job as submitted, JSON
    "state": str,
    "done": int,
    "total": int,
    "error": str,
    "created": float,
    "started": float,
    "finished": float,
    "heartbeat": float,
    "enqueued": float,
    "owner": str,
    "attempts": int,
    "completions": int,
}
ACTIVE = ("queued", "running")
FINAL = ("done", "failed", "cancelled")


def _blank(rec: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {k: None for k in FIELDS}
    out.update({"done": 0, "total": 0, "attempts": 0, "completions": 0})
    out.update(rec)
    return out


class Records:
    """Interface. ``expect`` maps a field to the tuple of values it must hold for the update to apply."""

    def create(self, rec: dict[str, Any]) -> None:
        raise NotImplementedError

    def get(self, job_id: str) -> dict[str, Any] | None:
        raise NotImplementedError

    def list(self, limit: int = 100, states: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
        raise NotImplementedError

    def update(self, job_id: str, fields: dict[str, Any], expect: dict[str, tuple] | None = None) -> bool:
        raise NotImplementedError

    def finished_before(self, cutoff: float, limit: int = 1000) -> builtins.list[str]:
        """Ids of jobs in a final state that finished before `cutoff` (Unix seconds)."""
        raise NotImplementedError

    def delete_final(self, job_id: str) -> bool:
        """Remove the record if the job is in a final state (never a queued or running one)."""
        raise NotImplementedError

    def lease(self, job_id: str, frame: int, owner: str, ttl: float) -> bool:
        """Take frame `frame` of a job for `owner` for `ttl` seconds; true if it was free, its lease had lapsed, or
        `owner` held it already (then it is renewed). The workers that share a job's frames render a frame only
        under its lease, so that while its holder lives no one else renders it."""
        raise NotImplementedError

    def drop_leases(self, job_id: str, owner: str | None = None) -> None:
        """Remove a job's frame leases (only `owner`'s, given one)."""
        raise NotImplementedError

    def close(self) -> None:
        pass


# --- SQLite ----------------------------------------------------------------------------------------------------

_SQL_TYPES = {str: "TEXT", int: "INTEGER", float: "REAL"}


class SqliteRecords(Records):
    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        cols = ", ".join(f"{k} {_SQL_TYPES[t]}" + (" PRIMARY KEY" if k == "id" else "") for k, t in FIELDS.items())
        with self._conn() as c:
            c.execute(f"CREATE TABLE IF NOT EXISTS jobs ({cols})")
            c.execute("CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state)")
            c.execute("CREATE TABLE IF NOT EXISTS leases (job TEXT, frame INTEGER, owner TEXT, until REAL, "
                      "PRIMARY KEY (job, frame))")

    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.path, timeout=30, isolation_level=None, check_same_thread=False)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.row_factory = sqlite3.Row
            self._local.conn = conn
        return conn

    def create(self, rec: dict[str, Any]) -> None:
        rec = _blank(rec)
        keys = list(FIELDS)
        self._conn().execute(
            f"INSERT INTO jobs ({', '.join(keys)}) VALUES ({', '.join('?' for _ in keys)})", [rec[k] for k in keys]
        )

    def get(self, job_id: str) -> dict[str, Any] | None:
        row = self._conn().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return dict(row) if row else None

    def list(self, limit: int = 100, states: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
        if states:
            q = f"SELECT * FROM jobs WHERE state IN ({', '.join('?' for _ in states)}) ORDER BY created DESC LIMIT ?"
            rows = self._conn().execute(q, (*states, limit)).fetchall()
        else:
            rows = self._conn().execute("SELECT * FROM jobs ORDER BY created DESC LIMIT ?", (limit,)).fetchall()
        return [dict(r) for r in rows]

    def update(self, job_id: str, fields: dict[str, Any], expect: dict[str, tuple] | None = None) -> bool:
        for k in (*fields, *(expect or {})):
            if k not in FIELDS:
                raise KeyError(k)
        sets = ", ".join(f"{k} = ?" for k in fields)
        where, args = ["id = ?"], [*fields.values(), job_id]
        for k, allowed in (expect or {}).items():
            vals = [v for v in allowed if v is not None]
            parts = []
            if vals:
                parts.append(f"{k} IN ({', '.join('?' for _ in vals)})")
                args.extend(vals)
            if len(vals) != len(allowed):
                parts.append(f"{k} IS NULL")
            where.append("(" + " OR ".join(parts or ["0"]) + ")")
        cur = self._conn().execute(f"UPDATE jobs SET {sets} WHERE {' AND '.join(where)}", args)
        return cur.rowcount == 1

    def finished_before(self, cutoff: float, limit: int = 1000) -> builtins.list[str]:
        rows = self._conn().execute(
            f"SELECT id FROM jobs WHERE state IN ({', '.join('?' for _ in FINAL)}) AND finished < ? LIMIT ?",
            (*FINAL, cutoff, limit),
        ).fetchall()
        return [r["id"] for r in rows]

    def delete_final(self, job_id: str) -> bool:
        cur = self._conn().execute(
            f"DELETE FROM jobs WHERE id = ? AND state IN ({', '.join('?' for _ in FINAL)})", (job_id, *FINAL)
        )
        return cur.rowcount == 1

    def lease(self, job_id: str, frame: int, owner: str, ttl: float) -> bool:
        now = time.time()
        cur = self._conn().execute(
            "INSERT INTO leases (job, frame, owner, until) VALUES (?, ?, ?, ?) ON CONFLICT (job, frame) DO UPDATE "
            "SET owner = excluded.owner, until = excluded.until WHERE leases.until < ? OR leases.owner = excluded.owner",
            (job_id, int(frame), owner, now + ttl, now))
        return cur.rowcount == 1

    def drop_leases(self, job_id: str, owner: str | None = None) -> None:
        if owner is None:
            self._conn().execute("DELETE FROM leases WHERE job = ?", (job_id,))
        else:
            self._conn().execute("DELETE FROM leases WHERE job = ? AND owner = ?", (job_id, owner))

    def close(self) -> None:
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            conn.close()
            self._local.conn = None


# --- Redis -----------------------------------------------------------------------------------------------------

# KEYS = job hash, active-id set, job id. ARGV = n, then n pairs (field, allowed values each followed by '\x1f'),
# then field/value pairs.
_CAS = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
local n = tonumber(ARGV[1])
local i = 2
for c = 1, n do
  local f = ARGV[i]
  local allowed = ARGV[i + 1]
  i = i + 2
  local v = redis.call('HGET', KEYS[1], f)
  if not v then v = '' end
  local ok = false
  for a in string.gmatch(allowed, '([^\\31]*)\\31') do
    if a == v then ok = true end
  end
  if not ok then return 0 end
end
local args = {}
for j = i, #ARGV, 2 do
  table.insert(args, ARGV[j])
  table.insert(args, ARGV[j + 1])
  if ARGV[j] == 'state' then  -- keep the set of active (queued / running) job ids in step
    if ARGV[j + 1] == 'queued' or ARGV[j + 1] == 'running' then
      redis.call('SADD', KEYS[2], KEYS[3])
    else
      redis.call('SREM', KEYS[2], KEYS[3])
    end
  end
end
if #args > 0 then redis.call('HSET', KEYS[1], unpack(args)) end
return 1
"""


# KEYS = job hash, index; ARGV = job id, then the final states
_DELETE_FINAL = """
local state = redis.call('HGET', KEYS[1], 'state')
for i = 2, #ARGV do
  if state == ARGV[i] then
    redis.call('DEL', KEYS[1])
    redis.call('ZREM', KEYS[2], ARGV[1])
    return 1
  end
end
return 0
"""


# KEYS = the lease. ARGV = owner, ttl in ms. Taken when free (an expired key is gone) or already the owner's.
_LEASE = """
local cur = redis.call('GET', KEYS[1])
if (not cur) or cur == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[2])
  return 1
end
return 0
"""


def _enc(v: Any) -> str:
    return "" if v is None else repr(v) if isinstance(v, float) else str(v)


def _dec(k: str, v: str | None) -> Any:
    if v is None or v == "":
        return 0 if FIELDS[k] is int and k in ("done", "total", "attempts", "completions") else None
    t = FIELDS[k]
    return t(float(v)) if t is int else t(v)


class RedisRecords(Records):
    def __init__(self, url: str, prefix: str = "lodcast") -> None:
        import redis

        # decode_responses: every answer is a str, which redis's annotations (bytes | str) cannot express
        self.client: Any = redis.Redis.from_url(url, decode_responses=True)
        self.prefix = prefix
        self._cas = self.client.register_script(_CAS)
        self._delete_final = self.client.register_script(_DELETE_FINAL)
        self._lease = self.client.register_script(_LEASE)

    def _key(self, job_id: str) -> str:
        return f"{self.prefix}:job:{job_id}"

    @property
    def _index(self) -> str:
        return f"{self.prefix}:jobs"

    @property
    def _active(self) -> str:
        return f"{self.prefix}:active"

    def create(self, rec: dict[str, Any]) -> None:
        rec = _blank(rec)
        pipe = self.client.pipeline()
        pipe.hset(self._key(rec["id"]), mapping={k: _enc(v) for k, v in rec.items()})
        pipe.zadd(self._index, {rec["id"]: rec["created"] or time.time()})
        if rec["state"] in ACTIVE:
            pipe.sadd(self._active, rec["id"])
        pipe.execute()

    def get(self, job_id: str) -> dict[str, Any] | None:
        raw = self.client.hgetall(self._key(job_id))
        if not raw:
            return None
        return {k: _dec(k, raw.get(k)) for k in FIELDS}

    def _fetch(self, ids: list[str]) -> list[dict[str, Any]]:
        pipe = self.client.pipeline()
        for i in ids:
            pipe.hgetall(self._key(i))
        return [{k: _dec(k, raw.get(k)) for k in FIELDS} for raw in pipe.execute() if raw]

    def list(self, limit: int = 100, states: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
        if states and set(states) <= set(ACTIVE):  # the reaper's question: answered from the active set, not a scan
            recs = [r for r in self._fetch(sorted(self.client.smembers(self._active))) if r["state"] in states]
            recs.sort(key=lambda r: r["created"] or 0.0, reverse=True)
            return recs[:limit]
        out: list[dict[str, Any]] = []
        start, chunk = 0, max(limit, 100)
        while len(out) < limit:
            ids = self.client.zrevrange(self._index, start, start + chunk - 1)
            if not ids:
                break
            start += chunk
            pipe = self.client.pipeline()
            for i in ids:
                pipe.hgetall(self._key(i))
            for raw in pipe.execute():
                if not raw:
                    continue
                rec = {k: _dec(k, raw.get(k)) for k in FIELDS}
                if states is None or rec["state"] in states:
                    out.append(rec)
                    if len(out) >= limit:
                        break
        return out

    def update(self, job_id: str, fields: dict[str, Any], expect: dict[str, tuple] | None = None) -> bool:
        args: list[str] = [str(len(expect or {}))]
        for k, allowed in (expect or {}).items():
            if k not in FIELDS:
                raise KeyError(k)
            args += [k, "".join(_enc(a) + "\x1f" for a in allowed)]
        for k, v in fields.items():
            if k not in FIELDS:
                raise KeyError(k)
            args += [k, _enc(v)]
        return bool(self._cas(keys=[self._key(job_id), self._active, job_id], args=args))

    def finished_before(self, cutoff: float, limit: int = 1000) -> builtins.list[str]:
        # the index is scored by creation: a job that finished before the cutoff was created before it
        out: list[str] = []
        start, chunk = 0, 500
        while len(out) < limit:
            ids = self.client.zrangebyscore(self._index, "-inf", cutoff, start=start, num=chunk)
            if not ids:
                break
            start += chunk
            out += [r["id"] for r in self._fetch(ids)
                    if r["state"] in FINAL and r["finished"] is not None and r["finished"] < cutoff]
        return out[:limit]

    def delete_final(self, job_id: str) -> bool:
        return bool(self._delete_final(keys=[self._key(job_id), self._index], args=[job_id, *FINAL]))

    def lease(self, job_id: str, frame: int, owner: str, ttl: float) -> bool:
        key = f"{self.prefix}:lease:{job_id}:{int(frame)}"
        return bool(self._lease(keys=[key], args=[owner, max(1, int(ttl * 1000))]))

    def drop_leases(self, job_id: str, owner: str | None = None) -> None:
        for key in self.client.scan_iter(match=f"{self.prefix}:lease:{job_id}:*", count=1000):
            if owner is None or self.client.get(key) == owner:
                self.client.delete(key)

    def close(self) -> None:
        self.client.close()


def open_records(settings: Any) -> Records:
    if settings.is_redis:
        return RedisRecords(settings.queue, prefix=settings.queue_name)
    return SqliteRecords(settings.state_dir / "jobs.db" if settings.sqlite_path() == settings.state_dir / "queue.db"
                         else settings.sqlite_path().with_name(settings.sqlite_path().stem + "-jobs.db"))


def status_json(rec: dict[str, Any]) -> dict[str, Any]:
    """The job status exactly as docs/design.md's Interfaces section fixes it (times ISO 8601 UTC, or null)."""
    from datetime import datetime, timezone

    def iso(t: float | None) -> str | None:
        return None if t is None else datetime.fromtimestamp(t, tz=timezone.utc).isoformat().replace("+00:00", "Z")

    return {
        "id": rec["id"],
        "kind": rec["kind"],
        "state": rec["state"],
        "progress": {"done": int(rec["done"] or 0), "total": int(rec["total"] or 0)},
        "error": rec["error"] or None,
        "created": iso(rec["created"]),
        "started": iso(rec["started"]),
        "finished": iso(rec["finished"]),
    }


__all__ += ["status_json", "ACTIVE"]

