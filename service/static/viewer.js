// The viewer page: orbit/zoom/pan, named views, the TF editor, shading, clipping, a second TF and blend modes;
// previews while the user drags, refinement to the requested quality when they stop.

import { apiJson, ApiError } from "./api.js";
import { Orbit, VIEWS, viewAngles, worldBox } from "./camera.js";
import { Stream } from "./progressive.js";
import { TfEditor } from "./tfeditor.js";

// What a preview (asked for while the user drags) trades for speed, in one place: the image edge against the
// requested one, and the quality and sampling of its scene (the scene model's `quality` and `sampling`); of that
// scene's progressive render only the first, coarsest stage is asked for (`stages=1`).
export const PREVIEW = { scale: 0.5, quality: { reduction: 8 }, sampling: { step: 1.0 } };
const SHADING = { ambient: 0.3, diffuse: 0.7, specular: 0.2, shininess: 32, light: "headlight" };
const KEYS = { a: "anterior", p: "posterior", l: "left", r: "right", s: "superior", i: "inferior" };

const $ = (id) => document.getElementById(id);
const volume = decodeURIComponent(location.pathname.split("/")[2] || "");
const stream = new Stream(volume);
const state = {
  tf: null, tf2: null, tf2on: false, editing: "tf", mode: "composite", isovalue: 0, shading: false,
  plane: { on: false, axis: 0, at: 0.5, flip: false }, crop: [[0, 1], [0, 1], [0, 1]],
  quality: "lossless", size: 512,
};
// what tests and benchmarks read: every image shown, and the scene and image of the last final stage
const log = [];
window.lodcastViewer = { log, state, ready: false, final: null, PREVIEW,
                        changed: (dragging) => changed(dragging), lastInput: () => tInput };

let orbit = null;
let box = null;
let summary = null;
let editor = null;
let histogram = null;
let tInput = 0;
let previewBusy = false;
let previewWanted = false;

function status(text, error = false) {
  const el = $("status");
  el.textContent = text;
  el.classList.toggle("error", error);
}

function failed(e) {
  if (e instanceof ApiError) status(`${e.status}: ${e.detail}`, true);
  else status(String(e), true);
  window.lodcastViewer.error = String(e && e.detail ? e.detail : e);
}

// --- the scene ------------------------------------------------------------------------------------------------
function clip() {
  const out = {};
  const { lo, hi } = box;
  const at = (axis, f) => lo[axis] + f * (hi[axis] - lo[axis]);
  if (state.plane.on) {
    const point = [0, 1, 2].map((a) => (a === state.plane.axis ? at(a, state.plane.at) : box.center[a]));
    const normal = [0, 0, 0];
    normal[state.plane.axis] = state.plane.flip ? -1 : 1;
    out.planes = [{ point, normal }];
  }
  if (state.crop.some(([a, b]) => a > 0 || b < 1)) {
    out.box = { min: state.crop.map(([a], k) => at(k, a)), max: state.crop.map(([, b], k) => at(k, b)) };
  }
  return Object.keys(out).length ? out : null;
}

function scene(preview) {
  const size = preview ? Math.max(32, Math.round(state.size * PREVIEW.scale)) : state.size;
  const s = { camera: orbit.camera(), width: size, height: size, tf: state.tf,
              quality: preview ? PREVIEW.quality : state.quality, background: [0, 0, 0, 1], format: "png" };
  if (preview && PREVIEW.sampling) s.sampling = PREVIEW.sampling;
  if (state.mode !== "composite") s.mode = state.mode;
  if (state.mode === "iso") s.isovalue = state.isovalue;
  if (state.tf2on && state.tf2 && state.mode === "composite") s.tf2 = state.tf2;
  if (state.shading) s.shading = SHADING;
  const c = clip();
  if (c) s.clip = c;
  return s;
}

// --- showing stages -------------------------------------------------------------------------------------------
async function show(line, kind, t0, sc, serial) {
  const im = new Image();
  im.src = `data:image/png;base64,${line.image}`;
  await im.decode();
  if (serial !== stream.serial) return false; // a newer request's images own the view now
  const cv = $("view");
  if (cv.width !== state.size) {
    cv.width = state.size;
    cv.height = state.size;
  }
  const g = cv.getContext("2d");
  g.imageSmoothingEnabled = true;
  g.drawImage(im, 0, 0, cv.width, cv.height);
  const shown = performance.now();
  const rep = line.report || {};
  const entry = { kind, stage: line.stage, final: line.final, width: sc.width, height: sc.height,
                  reduction: rep.reduction, predicted_delta_e: rep.predicted_delta_e, wall_ms: rep.wall_ms,
                  input_ms: t0, shown_ms: shown, roundtrip_ms: shown - t0 };
  log.push(entry);
  if (kind === "refine" && line.final) {
    window.lodcastViewer.final = { scene: sc, image: line.image, report: rep };
    commandLine();
  }
  const fmt = (v, d) => (typeof v === "number" ? v.toFixed(d) : "–");
  status(`${kind === "preview" ? "preview" : line.final ? "final" : "refining"} · stage ${line.stage} · ` +
         `reduction ${fmt(rep.reduction, 1)}:1 · predicted ΔE ${fmt(rep.predicted_delta_e, 2)} · ` +
         `server ${fmt(rep.wall_ms, 0)} ms · shown ${fmt(shown - t0, 0)} ms after input`);
  return kind !== "preview";
}

async function sendPreview() {
  previewWanted = false;
  previewBusy = true;
  const t0 = tInput;
  const sc = scene(true);
  const serial = stream.serial + 1; // the serial run() is about to take
  try {
    await stream.run(sc, (line) => show(line, "preview", t0, sc, serial), 1);
  } catch (e) {
    failed(e);
  } finally {
    previewBusy = false;
  }
  if (previewWanted) sendPreview();
}

async function refine(attempt = 0) {
  const t0 = tInput;
  const sc = scene(false);
  const serial = stream.serial + 1;
  let final = false;
  try {
    const whole = await stream.run(sc, (line) => {
      final = final || line.final;
      return show(line, "refine", t0, sc, serial);
    });
    if (whole && !final) {
      // cancelled by a request of this page that the server saw after it: a preview aborted here but overtaken on
      // its own connection, whose session header ended this stream. Still the newest request: asked again
      if (attempt < 2) return refine(attempt + 1);
      status("the server ended the stream before its final stage (restarted, or the session taken over)", true);
    }
  } catch (e) {
    failed(e);
  }
}

// every change of the view or the scene: a preview while the user drags, the refinement when they stop
function changed(dragging) {
  if (!orbit || !state.tf) return;
  tInput = performance.now();
  if (dragging) {
    previewWanted = true;
    if (!previewBusy) sendPreview();
  } else {
    previewWanted = false;
    refine();
  }
}

// --- saving ---------------------------------------------------------------------------------------------------
function download(name, blob) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(a.href), 1000);
}

function commandLine() {
  const f = window.lodcastViewer.final;
  if (!f) return "";
  const text = `lodcast render "\${LODCAST_ROOT:-.}/${volume}" -o ${volume}.png --scene - <<'EOF'\n` +
               `${JSON.stringify(f.scene)}\nEOF`;
  $("command").value = text;
  return text;
}

// --- controls -------------------------------------------------------------------------------------------------
let presetShown = false; // while a preset is being put into the editor: the preset field keeps its name

function setPreset(name) {
  const tf = name in (histogram ? histogram.adapted : {}) ? histogram.adapted[name] : window.lodcastViewer.presets[name];
  if (!tf || !tf.points) return;
  state[state.editing] = { points: tf.points.map((p) => ({ ...p })) };
  presetShown = true;
  editor.setPoints(state[state.editing].points);
  presetShown = false;
}

function listPeaks() {
  const ul = $("peaks");
  ul.replaceChildren();
  for (const p of histogram.peaks.filter((q) => q.tf)) {
    const b = document.createElement("button");
    b.type = "button";
    b.className = "peak";
    b.textContent = `${p.value.toPrecision(4)} (${(100 * p.weight).toFixed(p.weight < 0.01 ? 2 : 1)} %)`;
    b.title = `α-histogram peak ${p.lo.toPrecision(4)}–${p.hi.toPrecision(4)}, prominence ${p.prominence} decades: show this range`;
    b.addEventListener("click", () => applyPeak(p));
    const li = document.createElement("li");
    li.append(b);
    ul.append(li);
  }
}

function applyPeak(p) {
  state[state.editing] = { points: p.tf.points.map((q) => ({ ...q })) };
  editor.setPoints(state[state.editing].points);
}

async function loadHistogram() {
  const alpha = Number($("alpha").value) || 4;
  histogram = await apiJson(`/volumes/${encodeURIComponent(volume)}/histogram?alpha=${alpha}`);
  editor.setHistogram(histogram);
  listPeaks();
}

function selectPoint(p) {
  if (!p) return;
  $("pt-color").value = editor.selectedHex();
  $("pt-opacity").value = p.opacity;
  $("pt-value").value = p.value;
}

function wireControls() {
  editor = new TfEditor($("tf"), (tf, dragging) => {
    state[state.editing] = tf;
    if (!presetShown) $("preset").value = ""; // edited: no longer the preset it started from
    changed(dragging);
  });
  editor.onSelect = selectPoint;
  editor.onPeak = applyPeak;
  $("log").addEventListener("change", (e) => {
    editor.log = e.target.checked;
    editor.draw();
  });
  $("alpha").addEventListener("change", () => loadHistogram().catch(failed));
  $("preset").addEventListener("change", (e) => setPreset(e.target.value));
  $("pt-color").addEventListener("input", (e) => editor.edit({ color: e.target.value }));
  $("pt-opacity").addEventListener("change", (e) => editor.edit({ opacity: Number(e.target.value) }));
  $("pt-value").addEventListener("change", (e) => editor.edit({ value: Number(e.target.value) }));
  for (const r of document.querySelectorAll("input[name=editing]")) {
    r.addEventListener("change", (e) => {
      state.editing = e.target.value;
      if (!state[state.editing]) state[state.editing] = { points: state.tf.points.map((p) => ({ ...p })) };
      editor.setPoints(state[state.editing].points, false);
    });
  }
  $("tf2on").addEventListener("change", (e) => {
    state.tf2on = e.target.checked;
    if (!state.tf2) state.tf2 = { points: state.tf.points.map((p) => ({ ...p })) };
    changed(false);
  });
  $("mode").addEventListener("change", (e) => {
    state.mode = e.target.value;
    $("isovalue-row").hidden = state.mode !== "iso";
    changed(false);
  });
  $("isovalue").addEventListener("change", (e) => {
    state.isovalue = Number(e.target.value);
    changed(false);
  });
  $("shading").addEventListener("change", (e) => {
    state.shading = e.target.checked;
    changed(false);
  });
  $("plane-on").addEventListener("change", (e) => {
    state.plane.on = e.target.checked;
    changed(false);
  });
  $("plane-axis").addEventListener("change", (e) => {
    state.plane.axis = Number(e.target.value);
    changed(false);
  });
  $("plane-flip").addEventListener("change", (e) => {
    state.plane.flip = e.target.checked;
    changed(false);
  });
  const slider = (el, set) => {
    el.addEventListener("input", () => {
      set(Number(el.value));
      changed(true);
    });
    el.addEventListener("change", () => changed(false));
  };
  slider($("plane-at"), (v) => (state.plane.at = v));
  for (const [k, axis] of ["x", "y", "z"].entries()) {
    slider($(`crop-${axis}-min`), (v) => (state.crop[k][0] = Math.min(v, state.crop[k][1] - 0.01)));
    slider($(`crop-${axis}-max`), (v) => (state.crop[k][1] = Math.max(v, state.crop[k][0] + 0.01)));
  }
  $("quality").addEventListener("change", (e) => {
    const v = e.target.value;
    state.quality = v === "lossless" || v === "full" ? v : { reduction: Number(v) };
    changed(false);
  });
  $("size").addEventListener("change", (e) => {
    state.size = Number(e.target.value);
    changed(false);
  });
  $("save-scene").addEventListener("click", () => {
    const f = window.lodcastViewer.final;
    if (f) download(`${volume}-scene.json`, new Blob([JSON.stringify(f.scene, null, 2)], { type: "application/json" }));
  });
  $("save-png").addEventListener("click", () => {
    const f = window.lodcastViewer.final;
    if (f) download(`${volume}.png`, new Blob([Uint8Array.from(atob(f.image), (c) => c.charCodeAt(0))], { type: "image/png" }));
  });
  $("copy-command").addEventListener("click", async () => {
    const text = commandLine();
    try {
      await navigator.clipboard.writeText(text);
      status("copied the lodcast render command line");
    } catch {
      $("command").select(); // no clipboard (an insecure origin): selected for the user to copy
    }
  });
  const views = $("views");
  for (const v of VIEWS) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = v;
    b.title = `${v} view (key ${Object.keys(KEYS).find((k) => KEYS[k] === v)})`;
    b.addEventListener("click", () => namedView(v));
    views.append(b);
  }
  document.addEventListener("keydown", (e) => {
    const typing = e.target instanceof Element && e.target.closest("input, select, textarea, dialog");
    if (typing || e.ctrlKey || e.metaKey || e.altKey) return;
    const k = e.key.toLowerCase();
    if (k in KEYS) namedView(KEYS[k]);
    else if (k === "f") {
      orbit.fit();
      changed(false);
    }
  });
}

function namedView(v) {
  const a = viewAngles(v, summary.orientation);
  if (!a) return;
  orbit.setView(a.azimuth, a.elevation);
  changed(false);
}

// --- orbit, zoom, pan: mouse and touch (pointer events) ---------------------------------------------------------
function wireView() {
  const cv = $("view");
  const pointers = new Map();
  let wheelTimer = null;
  cv.addEventListener("contextmenu", (e) => e.preventDefault());
  cv.addEventListener("pointerdown", (e) => {
    cv.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, pan: e.button !== 0 || e.shiftKey });
  });
  cv.addEventListener("pointermove", (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x;
    const dy = e.clientY - p.y;
    const h = cv.getBoundingClientRect().height;
    if (pointers.size === 1) {
      if (p.pan) orbit.panBy(dx, dy, h);
      else orbit.rotate(dx, dy);
    } else if (pointers.size === 2) { // pinch: zoom by the change of spread, pan by the midpoint's move
      const [a, b] = [...pointers.values()];
      const other = a === p ? b : a;
      const before = Math.hypot(p.x - other.x, p.y - other.y);
      const after = Math.hypot(e.clientX - other.x, e.clientY - other.y);
      if (before > 0 && after > 0) orbit.zoom(before / after);
      orbit.panBy(dx / 2, dy / 2, h);
    }
    p.x = e.clientX;
    p.y = e.clientY;
    if (dx || dy) changed(true);
  });
  const end = (e) => {
    if (!pointers.delete(e.pointerId)) return;
    if (pointers.size === 0) changed(false);
  };
  cv.addEventListener("pointerup", end);
  cv.addEventListener("pointercancel", end);
  cv.addEventListener("wheel", (e) => {
    e.preventDefault();
    orbit.zoom(Math.exp(e.deltaY * 0.0015));
    changed(true);
    clearTimeout(wheelTimer);
    wheelTimer = setTimeout(() => changed(false), 250);
  }, { passive: false });
}

async function main() {
  $("volume").textContent = volume;
  document.title = `${volume} · lodcast`;
  wireControls();
  wireView();
  try {
    summary = await apiJson(`/volumes/${encodeURIComponent(volume)}`);
    const presets = await apiJson("/presets");
    window.lodcastViewer.presets = presets;
    await loadHistogram();
    const sel = $("preset");
    sel.append(new Option("(edited)", ""));
    for (const name of Object.keys(presets)) {
      const o = document.createElement("option");
      o.value = name;
      o.textContent = presets[name].template ? `${name} (adapted to this volume)` : name;
      sel.append(o);
    }
    sel.value = "auto";
    box = worldBox(summary);
    orbit = new Orbit(box);
    window.lodcastViewer.orbit = orbit;
    $("info").textContent = `${summary.shape.join("×")} ${summary.dtype}, values ${histogram.value_range.map((v) => v.toPrecision(4)).join(" … ")}`;
    state.tf = { points: histogram.adapted.auto.points.map((p) => ({ ...p })) };
    editor.setPoints(state.tf.points, false);
    window.lodcastViewer.editor = editor;
    window.lodcastViewer.ready = true;
    changed(false);
  } catch (e) {
    failed(e);
  }
}

main();
