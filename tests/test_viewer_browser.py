"""The web viewer in a real browser: Debian's headless Chromium driven through selenium and the system's chromedriver,
against a real `lodcast serve` on two small synthetic stores. The page loads with no console errors; an orbit drag
and a TF point drag change the image; previews arrive before the refined image; the saved scene reproduces the
page's final image through `lodcast render`; two pages on two volumes do not cancel each other; with LODCAST_TOKEN
set a page gets no image until it is given the token. Screenshots go to out/viewer-tests/ (git-ignored)."""
from __future__ import annotations

import base64
import io
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from lodcast.renderer.image.delta_e import delta_e_stats
from lodcast.service.testing import (
    CHROMEDRIVER,
    CHROMIUM,
    chromium,
    free_port,
    in_ci,
    make_volume,
    page_wait,
    pointer_drag,
    running,
    start_serve,
)

ARTEFACTS = Path(__file__).resolve().parents[1] / "out" / "viewer-tests"
TOKEN = "browser-token"
SIZE = 256

try:
    from selenium.webdriver.common.by import By
except ImportError:  # the `test` extra installs it
    By = None

if By is None or not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
    why = "the viewer's browser tests need selenium, chromium and chromium-driver (.ci/run installs them)"
    if in_ci():
        raise RuntimeError(why)
    pytest.skip(why, allow_module_level=True)


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("browser") / "root"
    root.mkdir()
    make_volume(root, "a", n=64, block_size=8)  # 64³: progressive renders have three stages
    make_volume(root, "b", n=64, block_size=8)
    return root


@pytest.fixture(scope="module")
def server(root: Path, tmp_path_factory: pytest.TempPathFactory):
    port = free_port()
    proc = start_serve(root, port, log=tmp_path_factory.mktemp("log") / "serve.log")
    with running(proc):
        yield f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory):
    downloads = tmp_path_factory.mktemp("downloads")
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    with chromium(downloads) as driver:
        driver.downloads = downloads
        yield driver


def finals(driver: Any) -> int:
    return driver.execute_script("return window.lodcastViewer.log.filter(e => e.final && e.kind === 'refine').length")


def open_viewer(driver: Any, url: str) -> None:
    driver.get(url)
    page_wait(driver, "return window.lodcastViewer && window.lodcastViewer.ready && window.lodcastViewer.final")
    if driver.execute_script("return window.lodcastViewer.state.size") != SIZE:  # a quick picture for the tests
        n = finals(driver)
        driver.execute_script(f"const s = document.getElementById('size'); s.value = '{SIZE}'; "
                              "s.dispatchEvent(new Event('change'))")
        page_wait(driver, f"return window.lodcastViewer.log.filter(e => e.final && e.kind === 'refine').length > {n}")


def final_image(driver: Any) -> np.ndarray:
    b64 = driver.execute_script("return window.lodcastViewer.final.image")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))).convert("RGBA"), np.float64) / 255.0


def new_final(driver: Any, before: int, timeout: float = 60.0) -> np.ndarray:
    page_wait(driver, f"return window.lodcastViewer.log.filter(e => e.final && e.kind === 'refine').length > {before} "
                 "&& !document.getElementById('status').textContent.startsWith('refining')", timeout)
    return final_image(driver)


def severe(driver: Any) -> list[dict]:
    return [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def downloaded(folder: Path, name: str, timeout: float = 20.0) -> Path:
    """The file once the browser has finished writing it (Chromium writes NAME.crdownload and renames it)."""
    path, end = folder / name, time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and path.stat().st_size > 0 and not list(folder.glob("*.crdownload")):
            return path
        time.sleep(0.05)
    raise AssertionError(f"{name} was not downloaded")


def test_the_page_loads_with_no_console_errors(browser, server):
    browser.get(server + "/")
    links = page_wait(browser, "const a = [...document.querySelectorAll('#volumes a')]; return a.length && a.map(x => x.getAttribute('href'))")
    assert links == ["/volumes/a/view", "/volumes/b/view"]
    browser.save_screenshot(str(ARTEFACTS / "index.png"))
    open_viewer(browser, server + "/volumes/a/view")
    peaks = browser.execute_script("return window.lodcastViewer.editor.hist.peaks.length")
    assert peaks >= 1 and browser.find_element(By.ID, "command").get_attribute("value").startswith("lodcast render")
    browser.save_screenshot(str(ARTEFACTS / "viewer.png"))
    img = final_image(browser)
    assert img.shape == (SIZE, SIZE, 4) and img[..., :3].max() > 0.2  # a picture, not a black square
    assert severe(browser) == []


def set_tf(driver: Any, points: str) -> np.ndarray:
    """The editor's points set as a user's edit would (a refined render follows); its final image."""
    n = finals(driver)
    driver.execute_script(f"window.lodcastViewer.editor.setPoints({points})")
    return new_final(driver, n)


#: translucent: both blobs of make_volume and their overlap show
TRANSLUCENT = "[{value: 0, color: [0.2, 0.4, 1.0], opacity: 0}, {value: 1000, color: [1.0, 0.9, 0.8], opacity: 0.6}]"


def changed(a: np.ndarray, b: np.ndarray) -> float:
    """The share of pixels whose colour differs by more than 2 % in some channel."""
    return float((np.abs(a - b).max(axis=-1) > 0.02).mean())


def test_an_orbit_drag_shows_previews_then_a_different_refined_image(browser, server):
    open_viewer(browser, server + "/volumes/a/view")
    before, n = set_tf(browser, TRANSLUCENT), finals(browser)
    start = len(browser.execute_script("return window.lodcastViewer.log"))
    view = browser.find_element(By.ID, "view")
    # the button held until a preview is on screen: a drag that ends sooner asks for the refined image at once
    pointer_drag(browser, view, (200, 200), [(12, 3)] * 10,
                 hold=f"return window.lodcastViewer.log.slice({start}).some(e => e.kind === 'preview')")
    after = new_final(browser, n)
    browser.save_screenshot(str(ARTEFACTS / "orbit.png"))
    log = browser.execute_script("return window.lodcastViewer.log")[start:]
    previews = [e for e in log if e["kind"] == "preview"]
    first_final = next(e for e in log if e["final"] and e["kind"] == "refine")
    assert previews and min(e["shown_ms"] for e in previews) < first_final["shown_ms"]
    assert all(e["width"] == SIZE // 2 for e in previews)  # the preview's smaller image (PREVIEW.scale)
    cam = browser.execute_script("return window.lodcastViewer.final.scene.camera")
    assert cam["azimuth"] != 0 and cam["elevation"] != 0  # turned both ways
    assert changed(after, before) > 0.05, changed(after, before)
    assert severe(browser) == []


def test_touch_turns_and_pinch_zooms(browser, server):
    """One finger orbits, two fingers spreading apart zoom in (a smaller orbit distance)."""
    from selenium.webdriver.common.actions import interaction
    from selenium.webdriver.common.actions.action_builder import ActionBuilder

    open_viewer(browser, server + "/volumes/a/view")
    view = browser.find_element(By.ID, "view")
    rect = view.rect
    cx, cy = int(rect["x"] + rect["width"] / 2), int(rect["y"] + rect["height"] / 2)
    n = finals(browser)
    act = ActionBuilder(browser)
    finger = act.add_pointer_input(interaction.POINTER_TOUCH, "finger")
    finger.create_pointer_move(x=cx, y=cy)
    finger.create_pointer_down()
    for k in range(1, 9):
        finger.create_pointer_move(x=cx - 10 * k, y=cy, duration=40)
    finger.create_pointer_up(0)
    act.perform()
    new_final(browser, n)
    cam = browser.execute_script("return window.lodcastViewer.final.scene.camera")
    assert cam["azimuth"] == pytest.approx(32.0, abs=4.0) and cam["elevation"] == 0, cam  # 80 px at 0.4°/px
    n, before = finals(browser), cam["distance"]
    act = ActionBuilder(browser)
    fingers = [act.add_pointer_input(interaction.POINTER_TOUCH, f"f{i}") for i in range(2)]
    for i, f in enumerate(fingers):
        f.create_pointer_move(x=cx + (20 if i else -20), y=cy)
        f.create_pointer_down()
    for k in range(1, 7):
        for i, f in enumerate(fingers):
            f.create_pointer_move(x=cx + (1 if i else -1) * (20 + 15 * k), y=cy, duration=30)
    for f in fingers:
        f.create_pointer_up(0)
    act.perform()
    new_final(browser, n)
    cam = browser.execute_script("return window.lodcastViewer.final.scene.camera")
    # the pinch's midpoint stays put but each finger's move pans by half of it at the zoom of that moment: a
    # pan of rounding size turns the camera to the look-at form; its distance in bounding-sphere radii (64³ box)
    radius = 64 * np.sqrt(3) / 2
    after = cam.get("distance") or float(np.linalg.norm(np.subtract(cam["eye"], cam["target"]))) / radius
    assert after < 0.6 * before, (before, cam)
    assert severe(browser) == []


def test_a_tf_point_drag_changes_the_image(browser, server):
    open_viewer(browser, server + "/volumes/a/view")
    opaque = set_tf(browser, TRANSLUCENT)
    n = finals(browser)
    tf = browser.find_element(By.ID, "tf")
    pos = browser.execute_script("return window.lodcastViewer.editor.pointPosition(1)")
    pointer_drag(browser, tf, (pos["x"], pos["y"]), [(0, 12)] * 4)  # the opaque point dragged down: less opacity
    faint = new_final(browser, n)
    browser.save_screenshot(str(ARTEFACTS / "tf-drag.png"))
    points = browser.execute_script("return window.lodcastViewer.final.scene.tf.points")
    assert 0.1 < points[1]["opacity"] < 0.45 and abs(points[1]["value"] - 1000) < 20, points
    # less opacity at the densest values: the picture changes and gets darker over black
    assert changed(faint, opaque) > 0.05 and faint[..., :3].mean() < 0.95 * opaque[..., :3].mean(), \
        (changed(faint, opaque), faint[..., :3].mean(), opaque[..., :3].mean())
    assert severe(browser) == []


def test_the_panel_sets_the_scene(browser, server):
    """Shading, a clipping plane, the crop box, a second TF and a blend mode, each set in the panel as a user does,
    reach the scene of the next refined image (and change the picture)."""
    open_viewer(browser, server + "/volumes/a/view")
    base = set_tf(browser, TRANSLUCENT)

    def act(script: str) -> dict:
        n = finals(browser)
        browser.execute_script(script)
        new_final(browser, n)
        return browser.execute_script("return window.lodcastViewer.final.scene")

    click = "document.getElementById('{}').click()"
    assert act(click.format("shading"))["shading"]["light"] == "headlight"
    sc = act(click.format("plane-on"))
    assert sc["clip"]["planes"][0]["normal"] == [1, 0, 0] and changed(final_image(browser), base) > 0.05
    sc = act("const r = document.getElementById('crop-z-max'); r.value = '0.5'; r.dispatchEvent(new Event('input')); "
             "r.dispatchEvent(new Event('change'))")
    # the volume's box runs from -0.5 to 63.5 on each axis (64 voxels of 1, origin 0): z cropped at half
    assert sc["clip"]["box"] == {"min": [-0.5, -0.5, -0.5], "max": [63.5, 63.5, 31.5]}
    assert act(click.format("tf2on"))["tf2"]["points"]
    sc = act("const m = document.getElementById('mode'); m.value = 'mip'; m.dispatchEvent(new Event('change'))")
    assert sc["mode"] == "mip" and "tf2" not in sc  # a second TF composites: not with MIP
    assert severe(browser) == []


def test_the_saved_scene_reproduces_the_view_through_lodcast_render(browser, server, root, tmp_path):
    open_viewer(browser, server + "/volumes/a/view")
    n = finals(browser)
    browser.find_element(By.TAG_NAME, "body").send_keys("l")  # the left view, by its key
    page = new_final(browser, n)
    for f in browser.downloads.glob("*"):
        f.unlink()
    browser.find_element(By.ID, "save-scene").click()
    saved = downloaded(browser.downloads, "a-scene.json")
    scene = json.loads(saved.read_text())
    assert scene["camera"]["azimuth"] == 90 and scene["quality"] == "lossless"
    browser.find_element(By.ID, "save-png").click()  # the image on screen, as the server sent it
    png = downloaded(browser.downloads, "a.png")
    assert png.read_bytes() == base64.b64decode(browser.execute_script("return window.lodcastViewer.final.image"))
    command = browser.find_element(By.ID, "command").get_attribute("value")
    assert json.loads(command.split("\n")[1]) == scene  # the command line carries the same scene
    out = tmp_path / "cli.png"
    run = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "render", str(root / "a"), "-o", str(out),
                          "--scene", str(saved)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    cli = np.asarray(Image.open(out).convert("RGBA"), np.float64) / 255.0
    stats = delta_e_stats(page, cli)
    assert stats["mean"] <= 0.5 and stats["max"] <= 5.0, stats


def test_two_pages_on_two_volumes_do_not_cancel_each_other(browser, server):
    open_viewer(browser, server + "/volumes/a/view")
    first = browser.current_window_handle
    browser.switch_to.new_window("tab")
    open_viewer(browser, server + "/volumes/b/view")
    second = browser.current_window_handle
    counts = {}
    for handle, key in ((first, "r"), (second, "s")):  # each page asks for a new view, one right after the other
        browser.switch_to.window(handle)
        counts[handle] = finals(browser)
        browser.execute_script(f"document.dispatchEvent(new KeyboardEvent('keydown', {{key: '{key}'}}))")
    for handle, azimuth, elevation in ((first, -90, 0), (second, 0, 90)):
        browser.switch_to.window(handle)
        new_final(browser, counts[handle])
        cam = browser.execute_script("return window.lodcastViewer.final.scene.camera")
        assert (round(cam["azimuth"]), round(cam["elevation"])) == (azimuth, elevation)
    browser.switch_to.window(second)
    browser.close()
    browser.switch_to.window(first)


def test_with_a_token_a_page_gets_no_image_until_given_it(browser, root, tmp_path):
    port = free_port()
    with running(start_serve(root, port, env={"LODCAST_TOKEN": TOKEN}, log=tmp_path / "serve.log")):
        # a token kept by an earlier page of this tab goes (a fresh browser is still at a data: URL, which has no storage)
        browser.execute_script("if (location.protocol.startsWith('http')) sessionStorage.clear()")
        browser.get(f"http://127.0.0.1:{port}/volumes/a/view")
        page_wait(browser, "return document.getElementById('token-dialog').open")
        browser.save_screenshot(str(ARTEFACTS / "token-asked.png"))
        browser.find_element(By.CSS_SELECTOR, "#token-dialog button[value=cancel]").click()
        page_wait(browser, "return document.getElementById('status').classList.contains('error')")
        assert browser.execute_script("return window.lodcastViewer.log.length") == 0
        assert "401" in browser.find_element(By.ID, "status").text
        browser.get(f"http://127.0.0.1:{port}/volumes/a/view")
        page_wait(browser, "return document.getElementById('token-dialog').open")
        browser.find_element(By.ID, "token-input").send_keys(TOKEN)
        browser.find_element(By.ID, "token-ok").click()
        page_wait(browser, "return window.lodcastViewer.final")
        assert browser.execute_script("return window.lodcastViewer.log.length") >= 1
        browser.save_screenshot(str(ARTEFACTS / "token-given.png"))
        browser.execute_script("sessionStorage.clear()")
