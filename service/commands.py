"""CLI subcommands of the service: ``serve``, ``worker``, ``submit``, ``jobs``. Imports stay lazy (no FastAPI
until a command runs). They speak to a server (``--url``, default ``LODCAST_URL``) or, without one, to the local
store root's embedded queue (``--root``, default ``LODCAST_ROOT``)."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_serve", "add_worker", "add_submit", "add_jobs", "serve_forever"]


def _settings(args: argparse.Namespace, **extra: Any) -> Any:
    from lodcast.service.settings import Settings

    kw: dict[str, Any] = {k: v for k, v in extra.items() if v is not None}
    mb = getattr(args, "device_budget_mb", None)
    if mb is not None:  # handed to the renderer through the settings (service/rendering.py: RenderEngine)
        if not (mb > 0 and mb == mb and mb != float("inf")):
            raise ValueError(f"--device-budget-mb: must be a positive number of megabytes, got {mb}")
        kw["device_budget_mb"] = float(mb)
    if getattr(args, "root", None):
        kw["root"] = args.root
    if getattr(args, "queue", None):
        kw["queue"] = args.queue
    if getattr(args, "state_root", None):
        kw["state_root"] = args.state_root
    settings = Settings(**kw)
    if not getattr(args, "url", None) and not settings.remote and not Path(settings.root).is_dir():
        raise ValueError(f"--root: {settings.root} is not a folder")
    return settings


def _device_budget_opt(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device-budget-mb", type=float, default=None,
                   help="most device memory (MB, 10^6 bytes) one render's volume data may use; larger ones render in "
                        "several passes, same image (default LODCAST_DEVICE_BUDGET_MB, else one device allocation)")


def _url_opts(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", default=os.environ.get("LODCAST_URL"), help="server URL (default LODCAST_URL); without one, the local queue under --root")
    p.add_argument("--token", default=None, help="bearer token (default LODCAST_TOKEN)")
    p.add_argument("--root", default=None, help="store root for local use (default LODCAST_ROOT, else the current folder)")
    p.add_argument("--state-root", default=None, help="local use: folder of the job results and the embedded queue "
                   "(default LODCAST_STATE_ROOT, else the root)")
    p.add_argument("--queue", default=None, help="local use: queue URL (default: embedded SQLite; redis://host:port/db)")


def _print(obj: Any) -> None:
    print(json.dumps(_plain(obj), indent=2))


def _plain(obj: Any) -> Any:
    """The client's typed results as the JSON the server sent (what the commands print and look into)."""
    if isinstance(obj, list):
        return [_plain(x) for x in obj]
    return obj.model_dump(mode="json") if hasattr(obj, "model_dump") else obj


# --- serve -----------------------------------------------------------------------------------------------------

def add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve the HTTP API over the volumes under a store root (with an embedded job queue and worker)")
    p.add_argument("--root", default=None, help="store root, a folder or a URL such as s3://bucket/prefix; volumes are "
                   "stores directly under it (default LODCAST_ROOT, else .)")
    p.add_argument("--state-root", default=None, help="local folder for the embedded queue, uploads and (with a root "
                   "folder) job results; a root URL keeps results in ROOT/.jobs (default LODCAST_STATE_ROOT, else the "
                   "root when it is a folder, else ~/.lodcast/state/HASH of the root URL)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface; set a --token then)")
    p.add_argument("--port", type=int, default=8000, help="TCP port to listen on")
    p.add_argument("--queue", default=None, help="redis://host:port/db to share jobs with `lodcast worker`s on other hosts (default: embedded SQLite)")
    p.add_argument("--workers", type=int, default=None, help="in-process job worker threads (default 1; 0 when workers run separately)")
    p.add_argument("--render-concurrency", type=int, default=None, help="renders at once; more wait in order (default 2)")
    p.add_argument("--import-root", action="append", default=None, help="folder POST /volumes may ingest from (repeatable)")
    p.add_argument("--token", default=None, help="bearer token every route but /healthz needs (default LODCAST_TOKEN)")
    p.add_argument("--max-samples", type=float, default=None,
                   help="most samples one render may take, estimated before it runs (default LODCAST_MAX_SAMPLES, else 2e9)")
    _device_budget_opt(p)
    p.set_defaults(func=_cmd_serve)


def _cmd_serve(args: argparse.Namespace) -> int:
    from lodcast.malloc import tame_malloc

    tame_malloc()  # its workers run ingest jobs
    settings = _settings(args, workers=args.workers, render_concurrency=args.render_concurrency,
                         import_roots=args.import_root, token=args.token,
                         max_samples=None if args.max_samples is None else int(args.max_samples))
    return serve_forever(settings, host=args.host, port=args.port, log_level=args.log_level)


def _check_remote_root(url: str) -> None:
    """A root URL the service cannot list is a one-line error before the banner (a missing bucket, no
    credentials, no fsspec driver for the scheme)."""
    import fsspec

    try:
        fs, path = fsspec.core.url_to_fs(url)
        fs.ls(path.split("/", 1)[0] if "/" in path else path)  # the bucket: the prefix may not exist yet
    except ImportError as exc:
        raise ValueError(f"--root: cannot open {url}: {exc} (for s3:// install lodcast[s3])") from None
    except Exception as exc:  # noqa: BLE001 - whatever the filesystem raises is the same user error
        raise ValueError(f"--root: cannot list {url}: {' '.join(str(exc).split()) or type(exc).__name__}") from None


def _port_free(host: str, port: int) -> None:
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds: a port in TIME_WAIT is free
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ValueError(f"--port: cannot listen on {host}:{port} ({exc.strerror or exc}); is another server "
                             f"running there? Choose another with --port") from None


def serve_forever(settings: Any = None, *, host: str = "127.0.0.1", port: int = 8000, log_level: str = "warning",
                  root: str | os.PathLike[str] | None = None) -> int:
    """Serve the API until Ctrl-C, after printing the URL, an example curl and a client snippet. Used by
    `lodcast serve` and by anything that ends by serving (e.g. the demo): ``serve_forever(root="demo-output")``."""
    import uvicorn

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings
    from lodcast.service.volumes import list_volumes, volume_summary

    if settings is None:
        kw: dict[str, Any] = {"root": root} if root is not None else {}
        settings = Settings(**kw)
    if not (1 <= int(port) <= 65535):
        raise ValueError(f"--port: {port} is not a TCP port")
    from lodcast.service.queue import JobQueue

    settings.local_root.mkdir(parents=True, exist_ok=True)
    if settings.remote:
        _check_remote_root(settings.root)
    JobQueue(settings).check()  # an unreachable Redis is a one-line error now, not a failing request later
    _sweep(settings.root)
    url = f"http://{host if ':' not in host else '[' + host + ']'}:{port}"
    vols = list_volumes(settings.root)
    example, lo, hi = (vols[0] if vols else "VOLUME"), 0.0, 1000.0
    if vols:
        try:
            lo, hi = (float(v) for v in volume_summary(settings.root, example)["value_range"])
        except Exception:  # noqa: BLE001 - the example is a courtesy
            pass
    _port_free(host, int(port))  # before the banner: a busy port is the one line the user sees
    a, m, b = (round(lo + f * (hi - lo), 3) for f in (0.3, 0.6, 0.9))
    scene = json.dumps({"camera": {"azimuth": 30, "elevation": 20}, "background": [0.05, 0.05, 0.08, 1.0],
                        "shading": {},
                        "tf": {"points": [{"value": a, "color": [0.8, 0.3, 0.2], "opacity": 0.0},
                                          {"value": m, "color": [0.95, 0.75, 0.55], "opacity": 0.3},
                                          {"value": b, "color": [1.0, 1.0, 0.95], "opacity": 0.8}]}})
    auth = ' -H "Authorization: Bearer $LODCAST_TOKEN"' if settings.token else ""
    print(f"lodcast: serving {len(vols)} volume(s) from {settings.root} at {url}   (viewer {url}/, API docs {url}/docs; Ctrl-C stops)", flush=True)
    print(f"  curl -s{auth} -X POST {url}/volumes/{example}/render -H 'Content-Type: application/json' \\\n"
          f"       -d '{scene}' -o {example}.png", flush=True)
    print(f"  {sys.executable} - <<'EOF'\nimport lodcast\nc = lodcast.Client('{url}')\nr = c.render('{example}', {scene})\n"
          f"print(r.rgba.shape, r.report['wall_ms'])\nEOF", flush=True)
    # SIGTERM/Ctrl-C: requests in flight get a bounded time to finish (renders stop at their deadline anyway)
    uvicorn.run(create_app(settings), host=host, port=int(port), log_level=log_level, timeout_graceful_shutdown=10)
    return 0


def _sweep(root: Any) -> None:
    """What killed ingests of this host left (store/sweep.py), removed before this process takes work."""
    from lodcast.store.sweep import sweep

    gone = sweep(root)
    if gone:
        print(f"lodcast: removed {len(gone)} folder(s) of killed ingests: {', '.join(gone[:5])}"
              f"{' ...' if len(gone) > 5 else ''}", file=sys.stderr, flush=True)


# --- worker ----------------------------------------------------------------------------------------------------

def add_worker(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="run batch jobs from the queue (SIGTERM / Ctrl-C: finish the frame, hand the job back)")
    p.add_argument("--root", default=None, help="store root, a folder or a URL such as s3://bucket/prefix (default "
                   "LODCAST_ROOT, else .); shared by every worker and the service")
    p.add_argument("--state-root", default=None, help="local folder for the embedded queue, uploads and (with a root "
                   "folder) job results; a root URL keeps results in ROOT/.jobs (default LODCAST_STATE_ROOT, else the "
                   "root when it is a folder, else ~/.lodcast/state/HASH of the root URL)")
    p.add_argument("--queue", default=None, help="redis://host:port/db for a shared queue (default: the root's embedded SQLite queue)")
    p.add_argument("--threads", type=int, default=1, help="jobs run at once by this process (default 1)")
    _device_budget_opt(p)
    p.set_defaults(func=_cmd_worker)


def _cmd_worker(args: argparse.Namespace) -> int:
    from lodcast.service.objectstorage import bound_object_storage, s3_limits
    from lodcast.service.queue import JobQueue, Worker

    if args.threads < 1:
        raise ValueError(f"--threads: must be at least 1, got {args.threads}")
    from lodcast.malloc import tame_malloc

    tame_malloc()  # it runs ingest jobs
    settings = _settings(args)
    bound_object_storage(**s3_limits(settings))  # a job meets an outage within seconds, and resumes after it
    jq = JobQueue(settings)
    jq.check()
    _sweep(settings.root)
    print(f"lodcast worker {os.getpid()} on {'redis' if settings.is_redis else 'sqlite'} queue, root {settings.root}", file=sys.stderr, flush=True)
    return Worker(jq, threads=args.threads).run_forever()


# --- submit / jobs ---------------------------------------------------------------------------------------------

def add_submit(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("submit", help="submit a batch job (JSON file, or - for stdin); prints its status")
    p.add_argument("job", help="JOB.json, e.g. {\"kind\": \"turntable\", \"volume\": \"engine\", \"scene\": {...}, \"frames\": 36}")
    p.add_argument("--wait", action="store_true", help="wait until it finishes (progress bar on a terminal)")
    _url_opts(p)
    p.set_defaults(func=_cmd_submit)


def _read_job(path: str) -> Any:
    try:
        text = sys.stdin.read() if path == "-" else Path(path).read_text()
    except OSError as exc:
        raise ValueError(f"job: cannot read {path}: {exc.strerror or exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"job: {path} is not JSON ({exc.msg} at line {exc.lineno})") from None


def _local(args: argparse.Namespace, create: bool = False) -> Any:
    """The local queue under --root; unless `create`, one must exist already (a job id is looked up where jobs
    were submitted, not in a queue this call would create in the current folder)."""
    from lodcast.service.queue import JobQueue

    settings = _settings(args)
    if not create and not settings.is_redis and not settings.sqlite_path().exists():
        raise ValueError(f"--url: no server given (--url or LODCAST_URL) and no local job queue under {settings.root}")
    jq = JobQueue(settings)
    jq.check()
    return jq


def _client(args: argparse.Namespace) -> Any:
    from lodcast.service.client import Client

    return Client(args.url, token=args.token)


def _cmd_submit(args: argparse.Namespace) -> int:
    data = _read_job(args.job)
    if args.url:
        with _client(args) as c:
            st = c.submit(data)
            if args.wait:
                st = c.wait(st.id)
            st = _plain(st)
    else:
        from lodcast.service.jobs import parse_job, validate_job
        from lodcast.service.queue import Worker
        from lodcast.service.records import status_json

        # no server: the job runs here and now (a local queue no worker reads would keep it queued forever)
        jq = _local(args, create=True)
        job = validate_job(parse_job(data), jq.settings, jq.engine)
        rec = jq.submit(job)
        worker = Worker(jq, threads=1).start()
        try:
            st = status_json(jq.wait(rec["id"]))
        finally:
            worker.stop()
        print(f"ran job {rec['id']} here (no --url / LODCAST_URL); its results: lodcast jobs results {rec['id']} "
              f"--root {jq.settings.root} -o DIR", file=sys.stderr)
    _print(st)
    return 0 if st["state"] not in ("failed", "cancelled") else 1


def add_jobs(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("jobs", help="list, show, cancel or wait for batch jobs, or fetch their results")
    p.add_argument("action", nargs="?", default="list", choices=("list", "show", "cancel", "wait", "results"),
                   help="list the newest jobs, show / cancel / wait for one, or fetch its results into -o DIR")
    p.add_argument("id", nargs="?", help="job id (show, cancel, wait, results)")
    p.add_argument("-o", "--out", default=None, help="results: folder for the frames (frame_00000.png, ...) and a "
                   "turntable's animation (turntable.gif or .mp4) when it has one")
    p.add_argument("--state", choices=("queued", "running", "done", "failed", "cancelled"), help="list: only jobs in this state")
    p.add_argument("--limit", type=int, default=50, help="list: at most this many jobs, newest first")
    p.add_argument("--timeout", type=float, default=None, help="wait: give up after this many seconds (exit 1)")
    _url_opts(p)
    p.set_defaults(func=_cmd_jobs)


def _cmd_jobs(args: argparse.Namespace) -> int:
    if args.action != "list" and not args.id:
        raise ValueError(f"id: `lodcast jobs {args.action}` needs a job id")
    if args.action == "results" and not args.out:
        raise ValueError("-o: `lodcast jobs results ID` needs an output folder (-o DIR)")
    if args.url:
        with _client(args) as c:
            if args.action == "list":
                _print(c.jobs(limit=args.limit, state=args.state))
                return 0
            if args.action == "results":
                return _report_results([*c.results(args.id, args.out), *_remote_animation(c, args.id, Path(args.out))])
            try:
                st = _plain({"show": c.job, "cancel": c.cancel}.get(
                    args.action, lambda i: c.wait(i, timeout=args.timeout))(args.id))
            except TimeoutError as exc:
                print(f"lodcast jobs: {exc}", file=sys.stderr)
                return 1
    else:
        from lodcast.service.records import status_json

        jq = _local(args)
        if args.action == "list":
            _print([status_json(r) for r in jq.list(limit=args.limit, states=(args.state,) if args.state else None)])
            return 0
        if jq.get(args.id) is None:
            raise ValueError(f"id: no job {args.id!r} under {jq.settings.root}")
        if args.action == "results":
            return _report_results(_local_results(jq, args.id, Path(args.out)))
        rec = {"show": jq.get, "cancel": jq.cancel}.get(args.action, lambda i: jq.wait(i, timeout=args.timeout))(args.id)
        st = status_json(rec)
        if args.action == "wait" and st["state"] in ("queued", "running"):
            _print(st)
            print(f"lodcast jobs: job {args.id} still {st['state']} after {args.timeout} s", file=sys.stderr)
            return 1
    _print(st)
    return 0 if args.action != "wait" or st["state"] == "done" else 1


#: the names a turntable's animation is written under (service/queue.py), by the format the job asked for
ANIMATIONS = ("turntable.gif", "turntable.mp4")


def _local_results(jq: Any, job_id: str, dest: Path) -> list[Path]:
    """Copies of a local job's frames (as written so far), and of its animation once written, in `dest`."""
    files = jq.files(job_id)
    dest.mkdir(parents=True, exist_ok=True)
    out = []
    names = files.names()
    for name in files.frames() + [a for a in ANIMATIONS if a in names]:
        (dest / name).write_bytes(files.read(name))
        out.append(dest / name)
    return out


def _remote_animation(client: Any, job_id: str, dest: Path) -> list[Path]:
    """A turntable's animation from the server (GET /jobs/{id}/animation) in `dest`, once written: [] when the job
    has none (not a turntable, no `animation` asked for, or not encoded yet)."""
    from lodcast.service.client import ServiceError

    if client.job(job_id).kind != "turntable":
        return []
    try:
        data = client.animation(job_id)
    except ServiceError as exc:
        if exc.status == 404:
            return []
        raise
    name = ANIMATIONS[0] if data[:4] == b"GIF8" else ANIMATIONS[1]  # GIF says so in its first bytes; else MP4
    dest.mkdir(parents=True, exist_ok=True)
    tmp = dest / f".{name}.tmp{os.getpid()}"
    tmp.write_bytes(data)
    os.replace(tmp, dest / name)
    return [dest / name]


def _report_results(paths: list) -> int:
    for p in paths:
        print(p)
    if not paths:
        print("lodcast jobs: the job has no results (yet)", file=sys.stderr)
        return 1
    return 0
