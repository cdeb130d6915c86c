// Learning curves drawn as SVG: SPL (0..1) against environment steps, optional bands
// (mean ± ½ std) and dashed horizontal lines (the pi_HF policies), as in the paper's Fig. 3.

import { h } from "./dom.js";

const WIDTH = 640;
const HEIGHT = 320;
const PAD = { left: 52, right: 16, top: 28, bottom: 44 };

function niceStep(span, target) {
  const raw = span / target;
  const power = 10 ** Math.floor(Math.log10(raw));
  const unit = [1, 2, 2.5, 5, 10].find((m) => m * power >= raw) * power;
  return unit;
}

function fmtSteps(value) {
  if (value >= 1e6) return `${+(value / 1e6).toFixed(2)}M`;
  if (value >= 1e3) return `${+(value / 1e3).toFixed(1)}k`;
  return String(value);
}

/**
 * series: [{label, points: [[x, y], ...], band?: [[x, lo, hi], ...], dashed?: bool,
 *   colour?: index of the palette (default: the series' position)}]
 * Returns a <figure> with the SVG (role="img", described by its title) and a legend.
 */
export function lineChart(series, { title, xLabel = "environment steps", yLabel = "SPL" } = {}) {
  const xs = series.flatMap((s) => s.points.map((p) => p[0]));
  const xMax = Math.max(1, ...xs);
  const x = (v) => PAD.left + (v / xMax) * (WIDTH - PAD.left - PAD.right);
  const y = (v) => HEIGHT - PAD.bottom - Math.min(1, Math.max(0, v)) * (HEIGHT - PAD.top - PAD.bottom);
  const svg = h("svg", {
    viewBox: `0 0 ${WIDTH} ${HEIGHT}`, class: "chart", role: "img", "aria-label": title,
  });
  svg.append(h("title", {}, title));
  const axes = h("g", { class: "axes" });
  for (let v = 0; v <= 1.0001; v += 0.25) {
    axes.append(
      h("line", { x1: PAD.left, x2: WIDTH - PAD.right, y1: y(v), y2: y(v), class: "gridline" }),
      h("text", { x: PAD.left - 8, y: y(v) + 4, "text-anchor": "end" }, v.toFixed(2)),
    );
  }
  const step = niceStep(xMax, 6);
  for (let v = 0; v <= xMax + 1e-9; v += step) {
    axes.append(
      h("line", { x1: x(v), x2: x(v), y1: HEIGHT - PAD.bottom, y2: HEIGHT - PAD.bottom + 5, class: "tick" }),
      h("text", { x: x(v), y: HEIGHT - PAD.bottom + 18, "text-anchor": "middle" }, fmtSteps(v)),
    );
  }
  axes.append(
    h("line", { x1: PAD.left, x2: WIDTH - PAD.right, y1: HEIGHT - PAD.bottom, y2: HEIGHT - PAD.bottom, class: "axis" }),
    h("line", { x1: PAD.left, x2: PAD.left, y1: PAD.top, y2: HEIGHT - PAD.bottom, class: "axis" }),
    h("text", { x: (WIDTH + PAD.left) / 2, y: HEIGHT - 6, "text-anchor": "middle" }, xLabel),
    h("text", { x: 14, y: (HEIGHT - PAD.bottom + PAD.top) / 2, "text-anchor": "middle",
      transform: `rotate(-90 14 ${(HEIGHT - PAD.bottom + PAD.top) / 2})` }, yLabel),
    h("text", { x: PAD.left, y: 18, class: "chart-title" }, title),
  );
  svg.append(axes);
  const legend = h("ul", { class: "legend" });
  series.forEach((s, i) => {
    const colour = `series-${(s.colour ?? i) % 8}`;
    if (s.band && s.band.length > 1) {
      const upper = s.band.map(([bx, , hi]) => `${x(bx)},${y(hi)}`);
      const lower = s.band.map(([bx, lo]) => `${x(bx)},${y(lo)}`).reverse();
      svg.append(h("path", { d: `M${upper.join("L")}L${lower.join("L")}Z`, class: `band ${colour}` }));
    }
    const points = s.points.map(([px, py]) => `${x(px)},${y(py)}`).join(" ");
    svg.append(h("polyline", { points, class: `line ${colour}${s.dashed ? " dashed" : ""}` }));
    if (!s.dashed && s.points.length <= 60) {
      for (const [px, py] of s.points) svg.append(h("circle", { cx: x(px), cy: y(py), r: 2.5, class: `dot ${colour}` }));
    }
    legend.append(h("li", {}, h("span", { class: `swatch ${colour}${s.dashed ? " dashed" : ""}`, "aria-hidden": "true" }), s.label));
  });
  return h("figure", { class: "chart-figure" }, svg, legend);
}

/** Mean and ½ std across runs at the steps every run has reached. */
export function meanHalfStd(curves) {
  if (!curves.length) return { points: [], band: [] };
  const common = curves
    .map((c) => new Map(c.map(([step, spl]) => [step, spl])))
    .reduce((shared, map) => shared.filter((step) => map.has(step)), curves[0].map((p) => p[0]));
  const maps = curves.map((c) => new Map(c));
  const points = [];
  const band = [];
  for (const step of common) {
    const values = maps.map((m) => m.get(step));
    const mean = values.reduce((a, b) => a + b, 0) / values.length;
    const std = Math.sqrt(values.reduce((a, b) => a + (b - mean) ** 2, 0) / values.length);
    points.push([step, mean]);
    band.push([step, mean - std / 2, mean + std / 2]);
  }
  return { points, band };
}
