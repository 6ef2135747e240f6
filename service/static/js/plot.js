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
