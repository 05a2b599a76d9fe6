// The orbit camera of docs/design.md: azimuth 0, elevation 0 looks from -y towards +y with +z up; azimuth turns
// towards +x, elevation towards +z; distance in bounding-sphere radii. A pan moves eye and target together in the
// view plane, which the orbit form cannot say: a panned view is sent as the equivalent look-at camera.

const RAD = Math.PI / 180;
const LETTER = { anterior: "A", posterior: "P", left: "L", right: "R", superior: "S", inferior: "I" };
const OPPOSITE = { A: "P", P: "A", L: "R", R: "L", S: "I", I: "S" };
export const VIEWS = Object.keys(LETTER);

const add = (a, b) => a.map((v, i) => v + b[i]);
const scale = (a, s) => a.map((v) => v * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => scale(a, 1 / Math.hypot(...a));

// The volume's box in world x, y, z from its summary (arrays are z, y, x): origin - spacing/2 to
// origin + (shape - 1/2) * spacing.
export function worldBox(summary) {
  const sh = [...summary.shape].reverse();
  const sp = [...summary.spacing].reverse();
  const org = [...summary.origin].reverse();
  const lo = org.map((o, i) => o - sp[i] / 2);
  const hi = org.map((o, i) => o + (sh[i] - 0.5) * sp[i]);
  const center = lo.map((v, i) => (v + hi[i]) / 2);
  const radius = 0.5 * Math.hypot(...hi.map((v, i) => v - lo[i]));
  return { lo, hi, center, radius };
}

function basis(azimuth, elevation) {
  const a = azimuth * RAD;
  const e = elevation * RAD;
  const d = [Math.sin(a) * Math.cos(e), -Math.cos(a) * Math.cos(e), Math.sin(e)];
  const up = [-Math.sin(a) * Math.sin(e), Math.cos(a) * Math.sin(e), Math.cos(e)];
  const f = scale(d, -1);
  const r = unit(cross(f, up));
  return { d, f, r, u: cross(r, f) };
}

// The nearest distance (radii) at which every corner of the box is inside the view with `margin` to spare
// (renderer/scene/camera.py: fit_distance).
export function fitDistance(box, azimuth, elevation, fov, aspect = 1, margin = 0.05) {
  const { f, r, u } = basis(azimuth, elevation);
  const t = Math.tan((fov * RAD) / 2) * (1 - margin);
  let need = 0;
  for (const x of [box.lo[0], box.hi[0]])
    for (const y of [box.lo[1], box.hi[1]])
      for (const z of [box.lo[2], box.hi[2]]) {
        const c = [x - box.center[0], y - box.center[1], z - box.center[2]];
        need = Math.max(need, Math.max(Math.abs(dot(c, r)) / (t * aspect), Math.abs(dot(c, u)) / t) - dot(c, f));
      }
  return need / box.radius;
}

// A named view as azimuth/elevation given the patient direction of world +x, +y, +z (the summary's
// `orientation`; a store ingested with orient LPS has ["L", "P", "S"]): renderer/scene/camera.py resolve_view.
export function viewAngles(view, codes) {
  const want = LETTER[view];
  const axes = codes || ["L", "P", "S"];
  for (let i = 0; i < 3; i++) {
    if (axes[i] === want || axes[i] === OPPOSITE[want]) {
      const d = [0, 0, 0];
      d[i] = axes[i] === want ? 1 : -1;
      const elevation = Math.asin(d[2]) / RAD;
      const azimuth = Math.abs(d[2]) < 1 ? Math.atan2(d[0], -d[1]) / RAD : 0;
      return { azimuth, elevation };
    }
  }
  return null;
}

export class Orbit {
  constructor(box, fov = 30) {
    this.box = box;
    this.azimuth = 0;
    this.elevation = 0;
    this.fov = fov;
    this.distance = fitDistance(box, 0, 0, fov);
    this.pan = [0, 0]; // world units along the view's right and up
  }

  setView(azimuth, elevation) {
    this.azimuth = azimuth;
    this.elevation = elevation;
    this.pan = [0, 0];
  }

  fit() {
    this.distance = fitDistance(this.box, this.azimuth, this.elevation, this.fov);
    this.pan = [0, 0];
  }

  rotate(dxPixels, dyPixels) {
    this.azimuth = (((this.azimuth - dxPixels * 0.4) % 360) + 540) % 360 - 180;
    this.elevation = Math.max(-90, Math.min(90, this.elevation + dyPixels * 0.4));
  }

  zoom(factor) {
    this.distance = Math.max(0.05, Math.min(100, this.distance * factor));
  }

  // a drag of (dx, dy) CSS pixels on a view `viewPixels` high moves what is under the pointer with it
  panBy(dxPixels, dyPixels, viewPixels) {
    const perPixel = (2 * this.distance * this.box.radius * Math.tan((this.fov * RAD) / 2)) / viewPixels;
    this.pan = [this.pan[0] - dxPixels * perPixel, this.pan[1] + dyPixels * perPixel];
  }

  // The scene's camera: the orbit form, or the look-at form of a panned view.
  camera() {
    const round = (v) => Math.round(v * 1e6) / 1e6;
    if (this.pan[0] === 0 && this.pan[1] === 0) {
      return { azimuth: round(this.azimuth), elevation: round(this.elevation), distance: round(this.distance),
               fov: this.fov };
    }
    const { d, r, u } = basis(this.azimuth, this.elevation);
    const shift = add(scale(r, this.pan[0]), scale(u, this.pan[1]));
    const target = add(this.box.center, shift);
    const eye = add(target, scale(d, this.box.radius * this.distance));
    return { eye: eye.map(round), target: target.map(round), up: u.map(round), fov: this.fov };
  }
}
