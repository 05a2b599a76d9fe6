// The transfer-function editor: control points (value, opacity, colour) dragged over the volume's histogram (plain
// and α-histogram, linear or log counts), the α-histogram's peaks marked as one-click suggestions.

const PAD = { left: 6, right: 6, top: 8, bottom: 18 };
const R = 6; // a point's radius in CSS pixels

const hex = (c) => "#" + c.map((v) => Math.round(v * 255).toString(16).padStart(2, "0")).join("");
const rgb = (h) => [1, 3, 5].map((i) => Math.round((parseInt(h.slice(i, i + 2), 16) / 255) * 1000) / 1000);

export function tfAt(points, value) {
  if (value <= points[0].value) return points[0];
  for (let i = 1; i < points.length; i++) {
    const a = points[i - 1];
    const b = points[i];
    if (value <= b.value) {
      const t = b.value > a.value ? (value - a.value) / (b.value - a.value) : 1;
      return { value, color: a.color.map((c, k) => c + t * (b.color[k] - c)), opacity: a.opacity + t * (b.opacity - a.opacity) };
    }
  }
  return points[points.length - 1];
}

export class TfEditor {
  // onChange(points, dragging): after every edit; `dragging` while a point moves
  constructor(canvas, onChange) {
    this.canvas = canvas;
    this.onChange = onChange;
    this.points = [];
    this.hist = null;
    this.log = true;
    this.range = [0, 1];
    this.selected = 0;
    this.dragging = null;
    this.onSelect = () => {};
    this.onPeak = () => {};
    canvas.addEventListener("pointerdown", (e) => this.down(e));
    canvas.addEventListener("pointermove", (e) => this.move(e));
    canvas.addEventListener("pointerup", (e) => this.up(e));
    canvas.addEventListener("pointercancel", (e) => this.up(e));
    canvas.addEventListener("dblclick", (e) => this.remove(e));
    new ResizeObserver(() => this.draw()).observe(canvas);
  }

  setHistogram(hist) {
    this.hist = hist;
    this.range = [hist.edges[0], hist.edges[hist.edges.length - 1]];
    this.draw();
  }

  setPoints(points, notify = true) {
    this.points = points.map((p) => ({ value: p.value, color: [...p.color], opacity: p.opacity }));
    this.selected = Math.min(this.selected, this.points.length - 1);
    this.draw();
    this.onSelect(this.points[this.selected]);
    if (notify) this.onChange(this.tf(), false);
  }

  tf() {
    return { points: this.points.map((p) => ({ value: p.value, color: p.color, opacity: p.opacity })) };
  }

  // the selected point's fields from the panel's inputs
  edit(fields) {
    const p = this.points[this.selected];
    if (!p) return;
    if (fields.color) p.color = rgb(fields.color);
    if (fields.opacity !== undefined) p.opacity = Math.max(0, Math.min(1, fields.opacity));
    if (fields.value !== undefined) p.value = fields.value;
    this.sort();
    this.draw();
    this.onChange(this.tf(), false);
  }

  selectedHex() {
    const p = this.points[this.selected];
    return p ? hex(p.color) : "#ffffff";
  }

  // --- geometry ------------------------------------------------------------------------------------------
  size() {
    const r = this.canvas.getBoundingClientRect();
    return { w: r.width, h: r.height };
  }

  x(value) {
    const { w } = this.size();
    const [lo, hi] = this.range;
    return PAD.left + ((value - lo) / (hi - lo || 1)) * (w - PAD.left - PAD.right);
  }

  y(opacity) {
    const { h } = this.size();
    return PAD.top + (1 - opacity) * (h - PAD.top - PAD.bottom);
  }

  at(e) {
    const r = this.canvas.getBoundingClientRect();
    const { w, h } = this.size();
    const [lo, hi] = this.range;
    const fx = (e.clientX - r.left - PAD.left) / (w - PAD.left - PAD.right);
    const fy = (e.clientY - r.top - PAD.top) / (h - PAD.top - PAD.bottom);
    const round = (v) => Math.round(v * 1000) / 1000;
    return { value: round(lo + Math.max(0, Math.min(1, fx)) * (hi - lo)), opacity: round(Math.max(0, Math.min(1, 1 - fy))),
             px: e.clientX - r.left, py: e.clientY - r.top };
  }

  hit(px, py) {
    let best = -1;
    let bestD = (R + 4) ** 2;
    this.points.forEach((p, i) => {
      const d = (this.x(p.value) - px) ** 2 + (this.y(p.opacity) - py) ** 2;
      if (d <= bestD) {
        best = i;
        bestD = d;
      }
    });
    return best;
  }

  sort() {
    const sel = this.points[this.selected];
    const drag = this.dragging !== null ? this.points[this.dragging] : null;
    this.points.sort((a, b) => a.value - b.value);
    this.selected = this.points.indexOf(sel);
    if (drag) this.dragging = this.points.indexOf(drag);
  }

  // --- interaction ---------------------------------------------------------------------------------------
  down(e) {
    const p = this.at(e);
    const peak = this.peakAt(p.px, p.py);
    if (peak) {
      if (peak.tf) this.onPeak(peak);
      return;
    }
    let i = this.hit(p.px, p.py);
    if (i < 0) { // a new point on the curve's colour, where the pointer is
      const c = tfAt(this.points, p.value);
      this.points.push({ value: p.value, color: [...c.color], opacity: p.opacity });
      this.sort();
      i = this.points.findIndex((q) => q.value === p.value && q.opacity === p.opacity);
    }
    this.selected = i;
    this.dragging = i;
    this.canvas.setPointerCapture(e.pointerId);
    this.onSelect(this.points[i]);
    this.draw();
    this.onChange(this.tf(), true);
  }

  move(e) {
    if (this.dragging === null) return;
    const p = this.at(e);
    const q = this.points[this.dragging];
    q.value = p.value;
    q.opacity = p.opacity;
    this.sort();
    this.onSelect(this.points[this.selected]);
    this.draw();
    this.onChange(this.tf(), true);
  }

  up(e) {
    if (this.dragging === null) return;
    this.dragging = null;
    if (this.canvas.hasPointerCapture(e.pointerId)) this.canvas.releasePointerCapture(e.pointerId);
    this.onChange(this.tf(), false);
  }

  remove(e) {
    const p = this.at(e);
    const i = this.hit(p.px, p.py);
    if (i < 0 || this.points.length <= 1) return;
    this.points.splice(i, 1);
    this.selected = Math.max(0, Math.min(this.selected, this.points.length - 1));
    this.draw();
    this.onSelect(this.points[this.selected]);
    this.onChange(this.tf(), false);
  }

  // --- drawing -------------------------------------------------------------------------------------------
  curve(counts, maxOf) {
    const f = this.log ? (v) => Math.log10(1 + v) : (v) => v;
    const top = f(maxOf) || 1;
    return counts.map((c) => f(c) / top);
  }

  draw() {
    const cv = this.canvas;
    const { w, h } = this.size();
    const dpr = window.devicePixelRatio || 1;
    if (cv.width !== Math.round(w * dpr) || cv.height !== Math.round(h * dpr)) {
      cv.width = Math.round(w * dpr);
      cv.height = Math.round(h * dpr);
    }
    const g = cv.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, w, h);
    const base = this.y(0);
    const span = base - this.y(1);
    if (this.hist) {
      const { edges, counts, alpha_counts: alpha, peaks } = this.hist;
      const top = Math.max(...counts, ...alpha);
      const plain = this.curve(counts, top);
      g.fillStyle = "#4a5568";
      for (let i = 0; i < plain.length; i++) {
        const x0 = this.x(edges[i]);
        const x1 = this.x(edges[i + 1]);
        g.fillRect(x0, base - plain[i] * span, Math.max(1, x1 - x0), plain[i] * span);
      }
      const a = this.curve(alpha, top);
      g.strokeStyle = "#f6ad55";
      g.lineWidth = 1.5;
      g.beginPath();
      a.forEach((v, i) => {
        const x = this.x((edges[i] + edges[i + 1]) / 2);
        if (i === 0) g.moveTo(x, base - v * span);
        else g.lineTo(x, base - v * span);
      });
      g.stroke();
      for (const p of peaks) { // suggestions: triangles under the axis
        const x = this.x(p.value);
        g.fillStyle = p.background ? "#718096" : "#f6ad55";
        g.beginPath();
        g.moveTo(x, base + 2);
        g.lineTo(x - 5, base + 11);
        g.lineTo(x + 5, base + 11);
        g.closePath();
        g.fill();
      }
    }
    if (!this.points.length) return;
    // the TF: opacity curve, filled with its colours
    const [lo, hi] = this.range;
    const grad = g.createLinearGradient(this.x(lo), 0, this.x(hi), 0);
    for (const p of this.points) {
      const t = Math.max(0, Math.min(1, (p.value - lo) / (hi - lo || 1)));
      grad.addColorStop(t, `rgba(${p.color.map((c) => Math.round(c * 255)).join(",")},0.45)`);
    }
    const xs = [this.x(lo), ...this.points.map((p) => this.x(p.value)), this.x(hi)];
    const ys = [this.points[0].opacity, ...this.points.map((p) => p.opacity), this.points[this.points.length - 1].opacity].map((o) => this.y(o));
    g.beginPath();
    g.moveTo(xs[0], base);
    xs.forEach((x, i) => g.lineTo(x, ys[i]));
    g.lineTo(xs[xs.length - 1], base);
    g.closePath();
    g.fillStyle = grad;
    g.fill();
    g.strokeStyle = "#e2e8f0";
    g.lineWidth = 1;
    g.beginPath();
    xs.forEach((x, i) => (i ? g.lineTo(x, ys[i]) : g.moveTo(x, ys[i])));
    g.stroke();
    this.points.forEach((p, i) => {
      g.beginPath();
      g.arc(this.x(p.value), this.y(p.opacity), R, 0, 2 * Math.PI);
      g.fillStyle = hex(p.color);
      g.fill();
      g.lineWidth = i === this.selected ? 3 : 1.5;
      g.strokeStyle = i === this.selected ? "#63b3ed" : "#1a202c";
      g.stroke();
    });
  }

  // the peak whose marker is under canvas position (px, py), if any
  peakAt(px, py) {
    if (!this.hist) return null;
    const base = this.y(0);
    if (py < base) return null;
    return this.hist.peaks.find((p) => Math.abs(this.x(p.value) - px) <= 6) || null;
  }

  // canvas position of a point (for tests and keyboard users: the same place a pointer would grab)
  pointPosition(i) {
    const p = this.points[i];
    return { x: this.x(p.value), y: this.y(p.opacity) };
  }
}
