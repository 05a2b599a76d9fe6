"""Issue 47: the web viewer's responsiveness, measured through a real browser (headless Chromium, selenium).

    .venv/bin/python benchmarks/bench_viewer.py [--drags 2] [--large PATH] [--figures docs/images]

A `lodcast serve` on a temporary root holding links to the demo volume (Colin 27 MR head, service/demo.py, ingested
under benchmarks/results/), the chest CT (../shared/data/ct_chest_dicom, ingested under benchmarks/results/) and the
1.15 GB body volume (`--large`, default ../main/benchmarks/results/large/body_550x1024x1024.zarr, opened read-only
through hard links: the service takes no symbolic link out of its root). For each volume and image size the viewer page is opened, its TF set (the demo: "auto", adapted
to the volume; the CTs: ct-bone) and the view dragged with the mouse: 24 moves of 8 px, 60 ms apart, the button
held until the last move's preview is on screen, then released. Measured in the page (performance.now()):
- preview round trip: from the input a preview shows to the moment it is drawn, for every preview of the drag
  (the page asks for the next one when the last arrived: the previews per second follow from it);
- refined: from the release to the final stage (virtually lossless) drawn, and to its first stage.
"4 tabs": the same with three more pages of the same volume open, each asking for a new refined view every second
(other users turning the volume on the same server). Prints a markdown table (medians; n = previews or drags)
and writes it with the JSON of every drag to docs/measurements/viewer.{md,json}. The machine is shared: compare
within one run.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_consistent_lod import DATA, RESULTS, store_of

from lodcast.service.demo import fetch_demo_volume
from lodcast.service.testing import chromium, free_port, page_wait, pointer_drag, running, start_serve

HERE = Path(__file__).resolve().parent
LARGE = HERE.parents[1] / "main" / "benchmarks" / "results" / "large" / "body_550x1024x1024.zarr"
MEASUREMENTS = HERE.parent / "docs" / "measurements"
FINALS = "return window.lodcastViewer.log.filter(e => e.final && e.kind === 'refine').length"
#: (volume id, preset, image size)
CASES = [("demo", "auto", 512), ("chest", "ct-bone", 512), ("chest", "ct-bone", 1024), ("large", "ct-bone", 512)]


def finals(driver: Any) -> int:
    return int(driver.execute_script(FINALS))


def settle(driver: Any, before: int, timeout: float = 600.0) -> None:
    """Until a final stage newer than `before` finals is on screen and no refinement is under way."""
    page_wait(driver, f"{FINALS} > {before} && !document.getElementById('status').textContent.startsWith('refining')",
              timeout)


def select(driver: Any, element: str, value: str) -> None:
    """A choice in one of the page's selects, as a user makes it; waits for the refined image it asks for."""
    n = finals(driver)
    if driver.execute_script(f"const s = document.getElementById('{element}'); if (s.value === '{value}') return false; "
                             f"s.value = '{value}'; s.dispatchEvent(new Event('change')); return true"):
        settle(driver, n)


def open_page(driver: Any, url: str, preset: str, size: int) -> None:
    driver.get(url)
    page_wait(driver, "return window.lodcastViewer && window.lodcastViewer.ready && window.lodcastViewer.final", 600)
    select(driver, "size", str(size))
    select(driver, "preset", preset)


def one_drag(driver: Any, direction: int) -> dict[str, Any]:
    from selenium.webdriver.common.by import By

    start = len(driver.execute_script("return window.lodcastViewer.log"))
    n = finals(driver)
    view = driver.find_element(By.ID, "view")
    t = time.perf_counter()
    pointer_drag(driver, view, (320, 320), [(8 * direction, 2 * direction)] * 24, pause=0.06,
                 hold="const l = window.lodcastViewer.log; return l.length && l[l.length - 1].kind === 'preview' "
                      "&& l[l.length - 1].input_ms === window.lodcastViewer.lastInput()", timeout=600)
    drag_s = time.perf_counter() - t
    settle(driver, n)
    log = driver.execute_script("return window.lodcastViewer.log")[start:]
    previews = [e for e in log if e["kind"] == "preview"]
    refine = [e for e in log if e["kind"] == "refine"]
    final = next(e for e in refine if e["final"])
    return {"drag_s": drag_s, "previews_ms": [e["roundtrip_ms"] for e in previews],
            "preview_stage": [{k: e[k] for k in ("width", "reduction", "predicted_delta_e", "wall_ms")} for e in previews[-1:]],
            "first_stage_ms": refine[0]["roundtrip_ms"], "refined_ms": final["roundtrip_ms"],
            "final": {k: final[k] for k in ("width", "reduction", "predicted_delta_e", "wall_ms")}}


def busy_tabs(driver: Any, url: str, preset: str, size: int, count: int) -> list[str]:
    """`count` more pages of the volume, each turning the view and asking for a refined one every second."""
    main = driver.current_window_handle
    handles = []
    for _ in range(count):
        driver.switch_to.new_window("tab")
        open_page(driver, url, preset, size)
        driver.execute_script("setInterval(() => { window.lodcastViewer.orbit.rotate(15, 0); "
                              "window.lodcastViewer.changed(false); }, 1000)")
        handles.append(driver.current_window_handle)
    driver.switch_to.window(main)
    return handles


def close_tabs(driver: Any, handles: list[str]) -> None:
    main = driver.current_window_handle
    for h in handles:
        driver.switch_to.window(h)
        driver.close()
    driver.switch_to.window(main)


def figures(driver: Any, base: str, dest: Path) -> None:
    """The viewer on the chest CT with ct-bone, then with the α-histogram's first suggestion applied."""
    dest.mkdir(parents=True, exist_ok=True)
    open_page(driver, f"{base}/volumes/chest/view", "ct-bone", 512)
    n = finals(driver)
    driver.execute_script("window.lodcastViewer.orbit.setView(30, 10); window.lodcastViewer.changed(false)")
    settle(driver, n)
    driver.save_screenshot(str(dest / "viewer_chest_bone.png"))
    n = finals(driver)
    driver.execute_script("document.querySelector('#peaks button').click()")
    settle(driver, n)
    driver.save_screenshot(str(dest / "viewer_chest_alpha.png"))


def median(v: list[float]) -> float | None:
    return statistics.median(v) if v else None


def table(rows: list[dict[str, Any]]) -> list[str]:
    out = ["| volume | image | tabs | preview round trip, median (p90) ms | previews/s while dragging | first stage after release ms | refined (lossless) after release ms | final reduction | n previews / drags |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = sorted(x for d in r["drags"] for x in d["previews_ms"])
        p90 = p[min(len(p) - 1, int(0.9 * len(p)))] if p else None
        rate = sum(len(d["previews_ms"]) for d in r["drags"]) / sum(d["drag_s"] for d in r["drags"])
        fmt = lambda v: "–" if v is None else f"{v:.0f}"  # noqa: E731
        out.append(f"| {r['volume']} | {r['size']}² | {r['tabs']} | {fmt(median(p))} ({fmt(p90)}) | {rate:.1f} | "
                   f"{fmt(median([d['first_stage_ms'] for d in r['drags']]))} | "
                   f"{fmt(median([d['refined_ms'] for d in r['drags']]))} | "
                   f"{r['drags'][-1]['final']['reduction']:.1f}:1 | {len(p)} / {len(r['drags'])} |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drags", type=int, default=2, help="drags per case (alternating direction)")
    ap.add_argument("--large", type=Path, default=LARGE, help="the 1.15 GB store (opened read-only, linked)")
    ap.add_argument("--chest", type=Path, default=None, help="a chest CT store to link instead of ingesting one")
    ap.add_argument("--figures", type=Path, default=None, help="write the docs' screenshots here")
    ap.add_argument("--cases", default="all", help="comma-separated volume ids to measure (demo, chest, large)")
    a = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    demo = store_of("demo_" + fetch_demo_volume().name, fetch_demo_volume().path)
    chest = a.chest or Path(store_of("ct_chest", DATA / "ct_chest_dicom").location)
    wanted = {c[0] for c in CASES} if a.cases == "all" else set(a.cases.split(","))
    # beside the stores: hard links need the same filesystem
    with tempfile.TemporaryDirectory(prefix="bench_viewer_", dir=RESULTS) as tmp:
        root = Path(tmp) / "root"
        root.mkdir()
        for name, path in (("demo", Path(demo.location)), ("chest", chest), ("large", a.large)):
            if path.exists():  # a tree of hard links: the service takes no links out of its root, nor a copy here
                shutil.copytree(path.resolve(), root / name, copy_function=os.link)
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        rows: list[dict[str, Any]] = []
        with running(start_serve(root, port, log=Path(tmp) / "serve.log")), chromium() as driver:
            if a.figures:
                figures(driver, base, a.figures)
            for vid, preset, size in CASES:
                if vid not in wanted or not (root / vid).exists():
                    continue
                url = f"{base}/volumes/{vid}/view"
                for tabs in (1, 4):
                    open_page(driver, url, preset, size)
                    others = busy_tabs(driver, url, preset, size, tabs - 1)
                    drags = [one_drag(driver, 1 if k % 2 == 0 else -1) for k in range(a.drags)]
                    close_tabs(driver, others)
                    rows.append({"volume": vid, "size": size, "tabs": tabs, "preset": preset, "drags": drags})
                    print(table(rows)[-1], flush=True)
    command = "python benchmarks/bench_viewer.py " + " ".join(sys.argv[1:])
    machine = f"{platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs (shared)"
    lines = ["# Web viewer: preview round trip and time to the refined image (issue 47)", "",
             f"{time.strftime('%Y-%m-%d')}, {machine}, headless Chromium through selenium; the renderer on the "
             f"CPU (PoCL). Command: `{command}`.", "",
             "Preview round trip: input (a mouse move) to the preview drawn in the page; the page asks for the next "
             "preview when the last one arrived. Refined: the mouse released to the final stage drawn "
             "(quality \"lossless\"). 4 tabs: three more pages of the same volume, each asking for a new refined "
             "view every second. Previews: the first stage (`stages=1`) of a scene at half the image edge, "
             "`{\"reduction\": 8}`, step 1 (PREVIEW in service/static/viewer.js).", "", *table(rows), ""]
    MEASUREMENTS.mkdir(parents=True, exist_ok=True)
    (MEASUREMENTS / "viewer.md").write_text("\n".join(lines))
    (MEASUREMENTS / "viewer.json").write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "machine": machine,
                                                          "command": command, "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
