// A job's convergence, log-log: the error statistic after each complete pass
// (GET /jobs/{id} `passes`) against the samples so far, with the 1/sqrt(N)
// slope of an unbiased Monte Carlo estimate through the first point and, for a
// job rendering to a noise target, the target. Plain SVG, drawn here.

const NS = "http://www.w3.org/2000/svg";

function el(tag, attrs = {}, text = null) {
  const node = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text !== null) node.textContent = text;
  return node;
}

// Powers of ten spanning [lo, hi] (log10 values), at least the two ends.
function decades(lo, hi) {
  const out = [];
  for (let d = Math.ceil(lo - 1e-9); d <= Math.floor(hi + 1e-9); d++) out.push(d);
  return out.length ? out : [lo, hi];
}

// Tick labels at powers of ten: samples as 1e4, errors as percentages.
function samplesLabel(d) {
  return Number.isInteger(d) ? (d >= 3 ? `1e${d}` : String(10 ** d)) : "";
}

function errorLabel(d) {
  return Number.isInteger(d) ? `${+(100 * 10 ** d).toPrecision(2)} %` : "";
}

// The plot as an <svg>, or null when fewer than two passes have an error.
export function convergencePlot(passes, target = null, width = 320, height = 200) {
  const points = (passes || []).filter((p) => p.rel_error > 0 && p.samples > 0)
    .map((p) => [Math.log10(p.samples), Math.log10(p.rel_error)]);
  if (points.length < 2) return null;
  const m = { l: 44, r: 10, t: 10, b: 30 };
  const xs = points.map((p) => p[0]);
  const ys = points.map((p) => p[1]);
  if (target) ys.push(Math.log10(target));
  let [x0, x1] = [Math.min(...xs), Math.max(...xs)];
  let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  if (x1 - x0 < 1e-6) x1 = x0 + 1;
  if (y1 - y0 < 1e-6) y1 = y0 + 1;
  const pad = (y1 - y0) * 0.08;
  y0 -= pad; y1 += pad;
  const X = (x) => m.l + (x - x0) / (x1 - x0) * (width - m.l - m.r);
  const Y = (y) => height - m.b - (y - y0) / (y1 - y0) * (height - m.t - m.b);
  const svg = el("svg", { viewBox: `0 0 ${width} ${height}`, class: "plot", role: "img",
    "aria-label": "error against samples, log-log" });
  for (const d of decades(x0, x1)) {
    svg.append(el("line", { x1: X(d), x2: X(d), y1: m.t, y2: height - m.b, class: "grid" }));
    svg.append(el("text", { x: X(d), y: height - m.b + 14, "text-anchor": "middle", class: "tick" },
      samplesLabel(d)));
  }
  for (const d of decades(y0, y1)) {
    svg.append(el("line", { x1: m.l, x2: width - m.r, y1: Y(d), y2: Y(d), class: "grid" }));
    svg.append(el("text", { x: m.l - 4, y: Y(d) + 4, "text-anchor": "end", class: "tick" },
      errorLabel(d)));
  }
  svg.append(el("text", { x: width - m.r, y: height - 4, "text-anchor": "end", class: "axis" },
    "samples"));
  // 1/sqrt(N) through the first point: an unbiased estimate's error falls along it
  const [px, py] = points[0];
  svg.append(el("line", { x1: X(x0), y1: Y(py - 0.5 * (x0 - px)), x2: X(x1),
    y2: Y(py - 0.5 * (x1 - px)), class: "slope" }));
  if (target) {
    svg.append(el("line", { x1: m.l, x2: width - m.r, y1: Y(Math.log10(target)),
      y2: Y(Math.log10(target)), class: "target" }));
  }
  svg.append(el("polyline", { points: points.map(([x, y]) => `${X(x)},${Y(y)}`).join(" "),
    class: "curve" }));
  for (const [x, y] of points) svg.append(el("circle", { cx: X(x), cy: Y(y), r: 2.5, class: "dot" }));
  return svg;
}

// Several curves on one log-log plot, each in its colour, with a legend:
// series = [{label, color, points: [[x, y], ...]}] (x, y > 0; others dropped).
// `percent` labels the y axis in per cent (an error statistic); otherwise as
// numbers (an RMSE). Returns an <svg>, or null with nothing to draw.
export function curvesPlot(series, { xLabel = "samples", percent = false, width = 480, height = 280,
  label = "error against samples, log-log" } = {}) {
  const lines = series.map((s) => ({ ...s, points: s.points.filter(([x, y]) => x > 0 && y > 0)
    .map(([x, y]) => [Math.log10(x), Math.log10(y)]) })).filter((s) => s.points.length);
  if (!lines.length) return null;
  const m = { l: 52, r: 10, t: 10, b: 30 };
  const xs = lines.flatMap((s) => s.points.map((p) => p[0]));
  const ys = lines.flatMap((s) => s.points.map((p) => p[1]));
  let [x0, x1] = [Math.min(...xs), Math.max(...xs)];
  let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  if (x1 - x0 < 1e-6) { x0 -= 0.5; x1 += 0.5; }
  if (y1 - y0 < 1e-6) { y0 -= 0.5; y1 += 0.5; }
  const pad = (y1 - y0) * 0.08;
  y0 -= pad; y1 += pad;
  const X = (x) => m.l + (x - x0) / (x1 - x0) * (width - m.l - m.r);
  const Y = (y) => height - m.b - (y - y0) / (y1 - y0) * (height - m.t - m.b);
  const svg = el("svg", { viewBox: `0 0 ${width} ${height}`, class: "plot curves", role: "img",
    "aria-label": label });
  for (const d of decades(x0, x1)) {
    svg.append(el("line", { x1: X(d), x2: X(d), y1: m.t, y2: height - m.b, class: "grid" }));
    svg.append(el("text", { x: X(d), y: height - m.b + 14, "text-anchor": "middle", class: "tick" },
      xLabel === "samples" ? samplesLabel(d) : (Number.isInteger(d) ? `${+(10 ** d).toPrecision(2)} s` : "")));
  }
  for (const d of decades(y0, y1)) {
    svg.append(el("line", { x1: m.l, x2: width - m.r, y1: Y(d), y2: Y(d), class: "grid" }));
    svg.append(el("text", { x: m.l - 4, y: Y(d) + 4, "text-anchor": "end", class: "tick" },
      percent ? errorLabel(d) : (Number.isInteger(d) ? `1e${d}` : "")));
  }
  svg.append(el("text", { x: width - m.r, y: height - 4, "text-anchor": "end", class: "axis" }, xLabel));
  lines.forEach((s, i) => {
    const g = el("g", { class: "series", "data-series": s.label });
    // presentation attributes, not style="": the dashboard's CSP allows no inline styles
    g.append(el("polyline", { points: s.points.map(([x, y]) => `${X(x)},${Y(y)}`).join(" "),
      class: "series-line", stroke: s.color }));
    for (const [x, y] of s.points) {
      g.append(el("circle", { cx: X(x), cy: Y(y), r: 2.5, class: "series-dot", fill: s.color }));
    }
    g.append(el("text", { x: width - m.r - 4, y: m.t + 12 + 13 * i, "text-anchor": "end", class: "legend",
      fill: s.color }, s.label));
    svg.append(g);
  });
  return svg;
}
