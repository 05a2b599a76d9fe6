"""The hostile-input table (issue 49, items 3 and 5): each hostile file and number the issue lists, run through the
real readers and the real service, with what each cost.

Files go through `lodcast ingest` in a child process (wall time, peak RSS from VmHWM, files left at the
destination, exit status and its one line) and through a real `lodcast serve` on loopback (with a token, an import
root and one in-process worker): uploaded where uploads take the format, imported from the import root otherwise,
the job waited for. Requests (cameras, path components, a job's cost, the token, the listing) go to the same
server. Each try is judged: a clear error (CLI exit 2 with one line; HTTP 4xx or a failed job whose
message names the field or the file), silent (accepted where it should be refused), or a 500 (a 5xx, a traceback,
a timeout). Rows judged "works" are inputs that should work: `.nii.gz` uploads ingested, a one-chunk zarr source
ingested (its time and memory are the figures), a running ingest cancelled and the next job done.

    python benchmarks/bench_hostile_inputs.py --json docs/measurements/hostile_inputs.json
    python benchmarks/bench_hostile_inputs.py --zarr-side 1024 ...   # the issue's one-chunk zarr (minutes)
"""
from __future__ import annotations

import argparse
import collections
import datetime
import gzip
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import nibabel as nib
import nrrd
import numpy as np
import tifffile
import zarr

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from phantoms import multiframe  # noqa: E402

from lodcast.service.testing import free_port, make_volume, running, start_serve, tiny_scene  # noqa: E402

TOKEN = "bench-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PEAK = ("import sys; from lodcast.service.cli import main; rc = main(sys.argv[1:]); "
        "print(next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM'))); sys.exit(rc)")
NAMED = re.compile(r"^[a-z_][a-z0-9_]*(\.[a-z0-9_]+)*: \S")
OME = "http://www.openmicroscopy.org/Schemas/OME/2016-06"


# --- the hostile files ------------------------------------------------------------------------------------------

def ome_tiff(path: Path, other: str) -> None:
    """A (4, 8, 8) OME-TIFF holding 2 pages whose OME-XML takes the other 2 from the file `other`."""
    xml = (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="{OME}" UUID="urn:uuid:0000-own"><Image ID="Image:0">'
           f'<Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint8" SizeX="8" SizeY="8" SizeZ="4" SizeC="1" '
           f'SizeT="1"><Channel ID="Channel:0:0" SamplesPerPixel="1"/><TiffData FirstZ="0" IFD="0" PlaneCount="2">'
           f'<UUID FileName="{path.name}">urn:uuid:0000-own</UUID></TiffData><TiffData FirstZ="2" IFD="0" '
           f'PlaneCount="2"><UUID FileName="{other}">urn:uuid:0000-other</UUID></TiffData></Pixels></Image></OME>')
    tifffile.imwrite(path, np.zeros((2, 8, 8), np.uint8), description=xml, metadata=None)


def nrrd_file(path: Path, fields: str, data: bytes, sizes: str = "4 4 2") -> None:
    path.write_bytes(f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: {sizes}\n{fields}\n".encode() + data)


def world_nrrd(path: Path, spacing: tuple, origin: tuple) -> None:
    header = {"space": "left-posterior-superior", "space directions": np.diag(spacing[::-1]).tolist(),
              "space origin": list(origin[::-1])}
    nrrd.write(str(path), np.ones((4, 4, 4), np.uint8), header)


def one_chunk_zarr(path: Path, side: int) -> None:
    a = zarr.create_array(str(path), shape=(side,) * 3, chunks=(side,) * 3, dtype="uint8", fill_value=0, zarr_format=3)
    a[:] = np.arange(side, dtype=np.uint8)[:, None, None]


def hostile_files(d: Path, secret: Path, zarr_side: int) -> list[tuple[str, Path, str | None, list[str]]]:
    """(kind, file, upload format or None to import it, extra CLI arguments)."""
    out: list[tuple[str, Path, str | None, list[str]]] = []
    for how, name in (("absolute", str(secret)), ("dotdot", "../private/secret.tif"), ("link", "other.tif")):
        sub = d / f"ome-{how}"
        sub.mkdir()
        if how == "link":
            (sub / "other.tif").symlink_to(secret)
        ome_tiff(sub / "up.ome.tif", name)
        out.append(("OME-TIFF naming another file (UUID FileName)", sub / "up.ome.tif", "tiff", []))
    for syntax, tag in ((None, "native"), ("1.2.840.10008.1.2.5", "rle")):
        multiframe(d / f"frames-{tag}.dcm", 2**31 - 1, syntax)
        out.append(("DICOM NumberOfFrames 2³¹−1 in one frame", d / f"frames-{tag}.dcm", None, []))
    for name, fields, data in (("lines.nrrd", "encoding: raw\nline skip: 1000000000000\n", bytes(600)),
                               ("bytes.nrrd", "encoding: raw\nbyte skip: 100000\n", bytes(600)),
                               ("gzbytes.nrrd", "encoding: gzip\nbyte skip: 1000000000000\n", gzip.compress(bytes(600)))):
        nrrd_file(d / name, fields, data)
        out.append(("NRRD line/byte skip beyond the file (10¹²)", d / name, "nrrd", []))
    for n in (20_000, 1_000_000):
        nrrd_file(d / f"thin{n}.nrrd", "encoding: gzip\n", gzip.compress(bytes(n)), sizes=f"1 1 {n}")
        out.append(("thin 1×1×N gzip NRRD", d / f"thin{n}.nrrd", "nrrd", []))
    for tag, spacing, origin in (("s1e308", (1e308, 1, 1), (0, 0, 0)), ("s1e-320", (1, 1e-320, 1), (0, 0, 0)),
                                 ("o1e308", (1, 1, 1), (1e308, 0, 0)), ("o-1e308", (1, 1, 1), (0, -1e308, 0)),
                                 ("onan", (1, 1, 1), (0, 0, float("nan")))):
        world_nrrd(d / f"world-{tag}.nrrd", spacing, origin)
        out.append(("spacing/origin without a finite world box", d / f"world-{tag}.nrrd", "nrrd", ["--orient", "source"]))
    if zarr_side:
        one_chunk_zarr(d / f"chunk{zarr_side}.zarr", zarr_side)
        out.append((f"zarr source, one {zarr_side}³ chunk", d / f"chunk{zarr_side}.zarr", None, []))
    return out


# --- runs -------------------------------------------------------------------------------------------------------

def files_under(p: Path) -> int:
    hidden = [q for q in p.parent.glob(f".{p.name}*")]
    return sum(1 for q in [p, *hidden] if q.exists() for f in ([q] if q.is_file() else q.rglob("*")) if f.is_file())


def cli(src: Path, dest: Path, extra: list[str], timeout: float) -> dict[str, Any]:
    t0 = time.monotonic()
    try:
        out = subprocess.run([sys.executable, "-c", PEAK, "ingest", "--no-progress", str(src), str(dest), *extra],
                             capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"exit": None, "seconds": timeout, "judged": "500", "line": "timed out"}
    seconds = time.monotonic() - t0
    lines = out.stderr.strip().splitlines()
    rss = int(out.stdout.split()[-1]) // 1024 if out.stdout.split() else None
    files = files_under(dest)
    shutil.rmtree(dest, ignore_errors=True)
    judged = ("clear" if out.returncode == 2 and len(lines) == 1 else
              "silent" if out.returncode == 0 else "500")
    return {"exit": out.returncode, "seconds": round(seconds, 2), "peak_rss_mb": rss, "files_left": files,
            "judged": judged, "line": lines[-1][:240] if lines else ""}


def wait_job(c: httpx.Client, job: str, timeout: float) -> dict[str, Any]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        st = c.get(f"/jobs/{job}").json()
        if st["state"] in ("done", "failed", "cancelled"):
            return st
        time.sleep(0.1)
    c.delete(f"/jobs/{job}")
    return {"state": "timeout", "error": f"not finished within {timeout} s"}


def http_file(c: httpx.Client, root: Path, imports: Path, name: str, src: Path, fmt: str | None,
              timeout: float) -> dict[str, Any]:
    t0 = time.monotonic()
    if fmt is not None:
        r = c.post(f"/volumes/{name}/upload", params={"format": fmt}, content=src.read_bytes())
    else:
        rel = src.relative_to(imports)
        r = c.post("/volumes", json={"name": name, "source": str(rel)})
    if r.status_code >= 500:
        return {"status": r.status_code, "judged": "500", "line": r.text[:240]}
    if r.status_code >= 400:
        msg = json.dumps(r.json().get("detail"))[:240]
        return {"status": r.status_code, "judged": "clear", "line": msg}
    st = wait_job(c, r.json()["id"], timeout)
    seconds = time.monotonic() - t0
    made = (root / name).exists()
    shutil.rmtree(root / name, ignore_errors=True)
    judged = ("silent" if st["state"] == "done" else
              "clear" if st["state"] == "failed" and st.get("error") and "Traceback" not in st["error"] else "500")
    return {"status": r.status_code, "job": st["state"], "seconds": round(seconds, 2), "store_made": made,
            "judged": judged, "line": (st.get("error") or "")[:240]}


def judge_4xx(r: httpx.Response, want: int | tuple[int, ...], field: str | None) -> str:
    if r.status_code >= 500:
        return "500"
    if r.status_code < 400:
        return "silent"
    detail = r.json().get("detail")
    msgs = [d["msg"] for d in detail] if isinstance(detail, list) else [str(detail)]
    ok = r.status_code in ((want,) if isinstance(want, int) else want)
    named = field is None or any(field in m for m in msgs)
    return "clear" if ok and named else "silent"


LOOK = {"eye": [11.5, -60.0, 11.5], "target": [11.5, 11.5, 11.5]}
CAMERAS = [({"azimuth": 10, "distance": 1e308}, "camera.distance"), ({"azimuth": 10, "distance": 1e-308}, "camera.distance"),
           ({"azimuth": 10, "fov": 1e-300}, "camera.fov"), ({**LOOK, "fov": 1e-300}, "camera.fov"),
           ({"eye": [1e308, 0, 0], "target": [0, 0, 0]}, "camera.eye"),
           ({"eye": [0, -1e308, 0], "target": [11.5, 11.5, 11.5]}, "camera.eye"),
           ({"eye": [-1e308, 0, 0], "target": [1e308, 0, 0]}, "camera.target"),
           ({"eye": [11.5, -60.0, 11.5], "target": [11.5, 1e308, 11.5]}, "camera.target"),
           ({**LOOK, "projection": "orthographic", "view_height": 1e-300}, "camera.view_height"),
           ({**LOOK, "projection": "orthographic", "view_height": 1e308}, "camera.view_height")]
LONG = ["a" * 256, "sub/" + "é" * 128 + "/x.npy", "blob.npy/" + "b" * 300, "x" * 4000, "/" + "c" * 300]


def requests(c: httpx.Client, base: str, root: Path) -> list[tuple[str, str, dict[str, Any]]]:
    """(kind, judged, detail) per try of the request-level inputs."""
    rows: list[tuple[str, str, dict[str, Any]]] = []

    def timed(kind: str, f: Any, judge: Any) -> None:
        t0 = time.monotonic()
        try:
            r = f()
        except httpx.HTTPError as exc:  # a dropped connection
            rows.append((kind, "500", {"line": f"{type(exc).__name__}: {exc}"[:240]}))
            return
        if r.status_code == 202 and kind.startswith("job"):  # accepted: not to be run
            c.delete(f"/jobs/{r.json()['id']}")
        rows.append((kind, judge(r), {"status": r.status_code, "seconds": round(time.monotonic() - t0, 3),
                                      "line": r.text[:200]}))

    for cam, field in CAMERAS:
        timed("extreme cameras (render)", lambda cam=cam: c.post("/volumes/tiny/render", json=tiny_scene(camera=cam)),
              lambda r, field=field: judge_4xx(r, 422, field))
        timed("extreme cameras (job)", lambda cam=cam: c.post("/jobs", json={
            "kind": "turntable", "volume": "tiny", "scene": tiny_scene(camera=cam), "frames": 2}),
              lambda r, field=field: judge_4xx(r, 422, field.split(".")[-1]))
    for source in LONG:
        for path, body in (("/volumes", {"name": "longname", "source": source}),
                           ("/jobs", {"kind": "ingest", "name": "longname", "source": source})):
            timed("path component over 255 bytes", lambda path=path, body=body: c.post(path, json=body),
                  lambda r: judge_4xx(r, 422, "source"))
    near = {**tiny_scene(4096), "sampling": {"step": 0.1}}  # each frame near LODCAST_MAX_SAMPLES
    for frames in (1000, 3000):
        timed("job cost over LODCAST_MAX_JOB_SAMPLES", lambda frames=frames: c.post("/jobs", json={
            "kind": "turntable", "volume": "tiny", "scene": near, "frames": frames}),
              lambda r: judge_4xx(r, 422, "frames"))
    timed("job cost over LODCAST_MAX_JOB_SAMPLES", lambda: c.post("/jobs", json={
        "kind": "scenes", "volume": "tiny", "scenes": [near] * 1000}), lambda r: judge_4xx(r, 422, "scenes"))
    bad = b'{"camera": '
    for method, path in (("POST", "/volumes/tiny/render"), ("POST", "/jobs"), ("POST", "/volumes"),
                         ("GET", "/volumes"), ("POST", "/volumes/x/upload?format=nifti&overwrite=maybe")):
        for auth in ("", "Bearer wrong", "Basic " + TOKEN):
            timed("no token, bad body (401 before 422)", lambda method=method, path=path, auth=auth: httpx.request(
                method, base + path, content=bad, headers={"content-type": "application/json", "Authorization": auth}),
                  lambda r: "clear" if r.status_code == 401 else "500" if r.status_code >= 500 else "silent")
    for name, what in _bad_stores(root).items():
        timed("GET /volumes beside a bad store", lambda: c.get("/volumes"),
              lambda r, name=name, what=what: "clear" if r.status_code == 200 and any(
                  v["id"] == name and what in v.get("error", "") for v in r.json()) else
              "500" if r.status_code >= 500 else "silent")
        timed("render of a bad store", lambda name=name: c.post(f"/volumes/{name}/render", json=tiny_scene()),
              lambda r, what=what: judge_4xx(r, (404, 409), what))
    return rows


def _bad_stores(root: Path) -> dict[str, str]:
    """Copies of "tiny" with the attributes an older lodcast let through (spacing 1e308, ...)."""
    def edit(name: str, key: str, value: Any) -> None:
        shutil.copytree(root / "tiny", root / name)
        meta = json.loads((root / name / "zarr.json").read_text())
        meta["attributes"][key] = value
        (root / name / "zarr.json").write_text(json.dumps(meta))

    edit("huge", "spacing", [1e308, 1e308, 1e308])
    edit("subnormal", "spacing", [1e-320, 1.0, 1.0])
    edit("faraway", "origin", [1e308, -1e308, 0.0])
    return {"huge": "spacing", "subnormal": "spacing", "faraway": "origin"}


def nii_gz(c: httpx.Client, d: Path, timeout: float) -> list[tuple[str, str, dict[str, Any]]]:
    data = np.arange(6 * 7 * 8, dtype=np.int16).reshape(8, 7, 6)
    nib.save(nib.Nifti1Image(data, np.diag([1.0, 2.0, 3.0, 1.0])), d / "v.nii")
    rows = []
    for i in range(3):
        t0 = time.monotonic()
        r = c.post(f"/volumes/nii{i}/upload", params={"format": "nifti"}, content=gzip.compress((d / "v.nii").read_bytes()))
        st = wait_job(c, r.json()["id"], timeout) if r.status_code == 202 else {"state": str(r.status_code)}
        ok = st["state"] == "done" and c.get(f"/volumes/nii{i}").json().get("shape") == [6, 7, 8]
        rows.append((".nii.gz upload (should work)", "works" if ok else "500" if r.status_code >= 500 else "silent",
                     {"status": r.status_code, "job": st["state"], "seconds": round(time.monotonic() - t0, 2)}))
    return rows


def cancel_ingest(c: httpx.Client, d: Path, root: Path, timeout: float) -> list[tuple[str, str, dict[str, Any]]]:
    """An ingest that runs for seconds is cancelled (DELETE /jobs/{id}) once running: the seconds until the next
    job, a small upload queued behind it, is done; the cancelled one leaves no store."""
    np.save(d / "big.npy", np.random.default_rng(0).integers(0, 255, (320, 320, 320), dtype=np.uint8))
    np.save(d / "small.npy", np.zeros((8, 8, 8), np.uint8))
    rows = []
    for i in range(2):
        job = c.post(f"/volumes/slow{i}/upload", params={"format": "npy"}, content=(d / "big.npy").read_bytes()).json()
        end = time.monotonic() + timeout
        while c.get(f"/jobs/{job['id']}").json()["state"] == "queued" and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(1.0)  # well into its reading
        nxt = c.post(f"/volumes/next{i}/upload", params={"format": "npy"}, content=(d / "small.npy").read_bytes()).json()
        t0 = time.monotonic()
        c.delete(f"/jobs/{job['id']}")
        st = wait_job(c, nxt["id"], timeout)
        seconds = time.monotonic() - t0
        first = c.get(f"/jobs/{job['id']}").json()["state"]
        ok = st["state"] == "done" and first == "cancelled" and not (root / f"slow{i}").exists()
        rows.append(("DELETE /jobs/{id} of a running ingest", "works" if ok else "silent",
                     {"cancelled": first, "next_job": st["state"], "seconds_to_next_done": round(seconds, 2)}))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--zarr-side", type=int, default=512, help="side of the one-chunk zarr source (0: none)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds one ingest may take before it counts as hung")
    ap.add_argument("--only", default=None, help="only the files whose kind contains this word (no requests)")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        root, imports = base / "root", base / "imports"
        root.mkdir()
        imports.mkdir()
        (base / "private").mkdir()
        secret = base / "private" / "secret.tif"
        tifffile.imwrite(secret, np.full((2, 8, 8), 200, np.uint8))
        (imports / "private").mkdir()
        shutil.copy(secret, imports / "private" / "secret.tif")
        sources = imports / "src"
        sources.mkdir()
        files = [f for f in hostile_files(sources, imports / "private" / "secret.tif", args.zarr_side)
                 if args.only is None or args.only in f[0]]
        for kind, src, _, extra in files:
            r = cli(src, base / "cli.zarr", extra, args.timeout)
            if kind.startswith("zarr") and r["judged"] == "silent":  # a valid volume: its cost is what is judged
                r["judged"] = "works"
            rows.append({"kind": kind, "via": "CLI", "input": src.name, "bytes": _size(src), **r})
            print(json.dumps(rows[-1]), flush=True)
        make_volume(root, "tiny")
        port = free_port()
        server = start_serve(root, port, env={"LODCAST_TOKEN": TOKEN, "LODCAST_IMPORT_ROOTS": str(imports)},
                             log=base / "serve.log")
        url = f"http://127.0.0.1:{port}"
        with running(server), httpx.Client(base_url=url, headers=AUTH, timeout=args.timeout) as c:
            for i, (kind, src, fmt, _) in enumerate(files):
                for via in (("upload", "import") if fmt else ("import",)):
                    r = http_file(c, root, imports, f"{via}{i}", src, fmt if via == "upload" else None, args.timeout)
                    if kind.startswith("zarr") and r["judged"] == "silent":
                        r["judged"] = "works"
                    rows.append({"kind": kind, "via": via, "input": src.name, **r})
                    print(json.dumps(rows[-1]), flush=True)
            more = [] if args.only else [*requests(c, url, root), *nii_gz(c, base, args.timeout),
                                         *cancel_ingest(c, base, root, args.timeout)]
            for kind, judged, detail in more:
                rows.append({"kind": kind, "via": "HTTP", "judged": judged, **detail})
                print(json.dumps(rows[-1]), flush=True)
        log = (base / "serve.log").read_text()
    table: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for r in rows:
        table[r["kind"]][r["judged"]] += 1
    out = {"date": datetime.date.today().isoformat(),
           "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.processor() or platform.machine()})",
           "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
           "table": {k: {"tries": sum(v.values()), **v} for k, v in table.items()},
           "tracebacks_in_server_log": log.count("Traceback"), "rows": rows}
    print(json.dumps(out["table"], indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


def _size(p: Path) -> int:
    return p.stat().st_size if p.is_file() else sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


if __name__ == "__main__":
    main()
