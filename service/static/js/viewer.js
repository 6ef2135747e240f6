// The HDR image viewer of the job page: the job's float data (GET
// /jobs/{id}/pixels, little-endian float32, the EXR's own values), not the
// tonemapped PNG. Zoom to single pixels and pan (wheel, drag, keys, pinch),
// fit / 1:1, exposure in stops, sRGB / linear / false-colour display, any
// layer of the image (beauty, var, relative error, samples, AOVs, denoised)
// and one of its channels, a pixel inspector (value ± standard error from the
// var layer), and an A/B comparison with another job of the same size (split
// slider or difference, with RMSE and relMSE between the two).
//
//   const viewer = hdrViewer(jobId);  root.append(viewer.el);
//   viewer.reload();   // the job's frame changed (a preview event)
//   viewer.destroy();
//
// Keys (the image focused): + / - zoom, arrows pan, f fit, 1 one-to-one,
// e / E exposure up / down half a stop, 0 exposure 0.

import { api } from "./api.js";
import { h, replace } from "./ui.js";

const ZOOM_MIN = 1 / 16;
const ZOOM_MAX = 128; // screen pixels per image pixel
const RELERR = "rel. error"; // a layer the viewer derives: sqrt(var) / |beauty|
// False colour: log10 of the value from 1e-3 to 1e3 through a viridis-like ramp.
const RAMP = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
const RAMP_LO = -3;
const RAMP_HI = 3;

// A layer of a job's image: {width, height, channels: [names], layers: [names], source, data}.
async function fetchLayer(jobId, layer) {
  const response = await fetch(`/jobs/${jobId}/pixels?layer=${encodeURIComponent(layer)}`);
  if (!response.ok) {
    let detail = `HTTP ${response.status}`;
    try { detail = (await response.json()).detail; } catch { /* not JSON */ }
    const err = new Error(typeof detail === "string" ? detail : JSON.stringify(detail));
    err.status = response.status;
    throw err;
  }
  const head = response.headers;
  return {
    width: Number(head.get("x-image-width")),
    height: Number(head.get("x-image-height")),
    channels: head.get("x-image-channels").split(","),
    layers: head.get("x-image-layers").split(","),
    source: head.get("x-image-source"),
    data: new Float32Array(await response.arrayBuffer()),
  };
}

function srgb(v) {
  if (!(v > 0)) return 0;
  if (v >= 1) return 255;
  const s = v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055;
  return Math.round(255 * s);
}

// The false-colour ramp sampled at RAMP_STEPS points, so a pixel looks its colour up.
const RAMP_STEPS = 1024;
const RAMP_LUT = Array.from({ length: RAMP_STEPS }, (_, k) => {
  const x = (k / (RAMP_STEPS - 1)) * (RAMP.length - 1);
  const i = Math.min(Math.floor(x), RAMP.length - 2);
  const f = x - i;
  return RAMP[i].map((c, j) => Math.round(c + f * (RAMP[i + 1][j] - c)));
});

function ramp(v) {
  const t = Math.min(Math.max((Math.log10(Math.max(v, 1e-30)) - RAMP_LO) / (RAMP_HI - RAMP_LO), 0), 1);
  return RAMP_LUT[Math.round(t * (RAMP_STEPS - 1))];
}

export function fmtValue(v) {
  if (!Number.isFinite(v)) return String(v);
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e5)) return v.toExponential(3);
  return v.toPrecision(4);
}

export function hdrViewer(jobId) {
  // -- state ------------------------------------------------------------------------
  let layerName = "beauty";
  let channel = "rgb"; // or an index into the layer's channels, or "lum"
  let display = "srgb"; // "linear", "false"
  let exposure = 0;
  let scale = 1;
  let ox = 0;
  let oy = 0;
  let fitted = true; // follow the stage's size
  let A = null; // {beauty, var, layer (the shown one), layers, width, height, source}
  let B = null; // the compared job's beauty
  let compareId = "";
  let compareMode = "split"; // "diff"
  let split = 0.5;
  let pinned = null; // [x, y] a tapped pixel stays inspected
  let loading = null;
  let again = false;
  let destroyed = false;

  // -- elements ---------------------------------------------------------------------
  const layerSelect = h("select#hdr-layer", { "aria-label": "layer" });
  const channelSelect = h("select#hdr-channel", { "aria-label": "channel" });
  const displaySelect = h("select#hdr-display", { "aria-label": "display" },
    h("option", { value: "srgb" }, "sRGB"), h("option", { value: "linear" }, "linear"),
    h("option", { value: "false" }, "false colour"));
  const exposureInput = h("input#hdr-exposure", { type: "range", min: -12, max: 12, step: 0.5, value: 0,
    "aria-label": "exposure in stops" });
  const exposureLabel = h("span.mono#hdr-exposure-value", {}, "+0.0 EV");
  const fitButton = h("button.small#hdr-fit", { type: "button", title: "fit the image (f)" }, "Fit");
  const oneButton = h("button.small#hdr-one", { type: "button", title: "one image pixel per screen pixel (1)" }, "1:1");
  const zoomLabel = h("span.mono.muted#hdr-zoom", {}, "");
  const compareSelect = h("select#hdr-compare", { "aria-label": "compare with job" },
    h("option", { value: "" }, "compare with…"));
  const modeSelect = h("select#hdr-compare-mode", { "aria-label": "comparison", hidden: true },
    h("option", { value: "split" }, "split"), h("option", { value: "diff" }, "difference |A−B|"));
  const splitInput = h("input#hdr-split", { type: "range", min: 0, max: 1, step: 0.001, value: 0.5,
    "aria-label": "split position", hidden: true });
  const compareStats = h("span.mono#hdr-compare-stats", {});
  const canvas = h("canvas#hdr-canvas", { tabindex: 0, "aria-label": "HDR image: drag to pan, wheel or pinch to zoom" });
  const stageEl = h("div.hdr-stage#hdr-stage", {}, canvas);
  const inspector = h("div.hdr-inspector.mono#hdr-inspector", { "aria-live": "off" }, "Point at a pixel to read it.");
  const status = h("div.muted#hdr-status", {}, "Loading the float data…");
  const el = h("div.hdr#hdr-viewer", {},
    h("div.hdr-bar", {}, layerSelect, channelSelect, displaySelect,
      h("label.hdr-exposure", {}, "exposure", exposureInput, exposureLabel),
      fitButton, oneButton, zoomLabel),
    h("div.hdr-bar", {}, compareSelect, modeSelect, splitInput, compareStats),
    stageEl, inspector, status);
  const offA = document.createElement("canvas");
  const offB = document.createElement("canvas");

  // -- pixels to an 8-bit picture ------------------------------------------------------
  function shownLayer() {
    if (!A) return null;
    if (layerName === "beauty") return A.beauty;
    if (layerName === "var") return A.var;
    if (layerName === RELERR) return A.relerr || (A.relerr = relativeError(A.beauty, A.var));
    return A.layer && A.layer.name === layerName ? A.layer : null;
  }

  function relativeError(beauty, variance) {
    const n = beauty.width * beauty.height;
    const data = new Float32Array(n);
    for (let i = 0; i < n; i++) {
      const m = (Math.abs(beauty.data[3 * i]) + Math.abs(beauty.data[3 * i + 1]) + Math.abs(beauty.data[3 * i + 2])) / 3;
      const v = (variance.data[3 * i] + variance.data[3 * i + 1] + variance.data[3 * i + 2]) / 3;
      data[i] = m > 0 ? Math.sqrt(v) / m : 0;
    }
    return { name: RELERR, width: beauty.width, height: beauty.height, channels: ["rel"], data };
  }

  // The value(s) shown for pixel i of `layer`: [r, g, b] after the channel choice.
  function pick(layer, i, out) {
    const c = layer.channels.length;
    const d = layer.data;
    if (c === 1) { out[0] = out[1] = out[2] = d[i]; return out; }
    const r = d[c * i], g = d[c * i + 1], b = c > 2 ? d[c * i + 2] : 0;
    if (channel === "rgb") { out[0] = r; out[1] = g; out[2] = b; }
    else if (channel === "lum") { out[0] = out[1] = out[2] = 0.2126 * r + 0.7152 * g + 0.0722 * b; }
    else { const v = d[c * i + Number(channel)]; out[0] = out[1] = out[2] = v; }
    return out;
  }

  function paint(off, layer, other) {
    const { width, height } = layer;
    off.width = width;
    off.height = height;
    const ctx = off.getContext("2d");
    const image = ctx.createImageData(width, height);
    const px = image.data;
    const gain = Math.pow(2, exposure);
    const v = [0, 0, 0];
    const w = [0, 0, 0];
    for (let i = 0, n = width * height; i < n; i++) {
      pick(layer, i, v);
      if (other) { pick(other, i, w); v[0] = Math.abs(v[0] - w[0]); v[1] = Math.abs(v[1] - w[1]); v[2] = Math.abs(v[2] - w[2]); }
      const o = 4 * i;
      if (display === "false") {
        const c = ramp(gain * (0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2]));
        px[o] = c[0]; px[o + 1] = c[1]; px[o + 2] = c[2];
      } else if (display === "linear") {
        px[o] = 255 * gain * v[0]; px[o + 1] = 255 * gain * v[1]; px[o + 2] = 255 * gain * v[2]; // clamped by the array
      } else {
        px[o] = srgb(gain * v[0]); px[o + 1] = srgb(gain * v[1]); px[o + 2] = srgb(gain * v[2]);
      }
      px[o + 3] = 255;
    }
    ctx.putImageData(image, 0, 0);
  }

  function repaint() {
    const layer = shownLayer();
    if (!layer) return;
    const comparing = B && layerName === "beauty";
    if (comparing && compareMode === "diff") paint(offA, layer, B);
    else paint(offA, layer, null);
    if (comparing && compareMode === "split") paint(offB, B, null);
    draw();
  }

  // -- the view: scale and offset in CSS pixels ---------------------------------------
  function stageSize() {
    const r = stageEl.getBoundingClientRect();
    return [Math.max(r.width, 1), Math.max(r.height, 1)];
  }

  function fit() {
    if (!A) return;
    const [cw, ch] = stageSize();
    scale = Math.min(cw / A.width, ch / A.height);
    ox = (cw - scale * A.width) / 2;
    oy = (ch - scale * A.height) / 2;
    fitted = true;
    draw();
  }

  function zoomAt(factor, cx, cy) {
    const next = Math.min(Math.max(scale * factor, ZOOM_MIN), ZOOM_MAX);
    ox = cx - (cx - ox) * (next / scale);
    oy = cy - (cy - oy) * (next / scale);
    scale = next;
    fitted = false;
    draw();
  }

  function oneToOne() {
    const [cw, ch] = stageSize();
    zoomAt(1 / scale, cw / 2, ch / 2);
  }

  function draw() {
    if (!A) return;
    const [cw, ch] = stageSize();
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(cw * dpr) || canvas.height !== Math.round(ch * dpr)) {
      canvas.width = Math.round(cw * dpr);
      canvas.height = Math.round(ch * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.imageSmoothingEnabled = scale < 1; // whole pixels when zoomed in
    ctx.setTransform(dpr * scale, 0, 0, dpr * scale, dpr * ox, dpr * oy);
    ctx.drawImage(offA, 0, 0);
    if (B && layerName === "beauty" && compareMode === "split") {
      const xs = ox + split * scale * A.width; // the split in screen pixels
      ctx.save();
      ctx.setTransform(1, 0, 0, 1, 0, 0);
      ctx.beginPath();
      ctx.rect(dpr * xs, 0, canvas.width - dpr * xs, canvas.height);
      ctx.clip();
      ctx.setTransform(dpr * scale, 0, 0, dpr * scale, dpr * ox, dpr * oy);
      ctx.drawImage(offB, 0, 0);
      ctx.restore();
      ctx.setTransform(1, 0, 0, 1, 0, 0);
      ctx.fillStyle = "#ffb547";
      ctx.fillRect(dpr * xs - dpr, 0, 2 * dpr, canvas.height);
    }
    zoomLabel.textContent = `${scale >= 1 ? Math.round(scale * 100) / 100 : scale.toPrecision(2)}×`;
    canvas.dataset.scale = String(scale);
    inspect(lastPointer);
  }

  // -- the pixel inspector --------------------------------------------------------------
  let lastPointer = null;
  function pixelAt(cx, cy) {
    if (!A) return null;
    const x = Math.floor((cx - ox) / scale);
    const y = Math.floor((cy - oy) / scale);
    return x >= 0 && y >= 0 && x < A.width && y < A.height ? [x, y] : null;
  }

  function inspect(pointer) {
    lastPointer = pointer;
    const at = pinned || (pointer && pixelAt(pointer[0], pointer[1]));
    if (!at || !A) {
      replace(inspector, "Point at a pixel to read it (tap to pin).");
      delete inspector.dataset.x;
      return;
    }
    const [x, y] = at;
    const i = y * A.width + x;
    const parts = [h("span", {}, `x ${x}  y ${y}`)];
    const layer = shownLayer();
    if (layerName === "beauty") {
      ["R", "G", "B"].forEach((name, c) => {
        const value = A.beauty.data[3 * i + c];
        const se = Math.sqrt(A.var.data[3 * i + c]);
        parts.push(h(`span.hdr-${name}`, { "data-channel": name, "data-value": value, "data-stderr": se },
          `${name} ${fmtValue(value)} ± ${fmtValue(se)}`));
      });
      if (B) {
        ["R", "G", "B"].forEach((name, c) => parts.push(h("span.muted", { "data-b": name },
          `B.${name} ${fmtValue(B.data[3 * i + c])}`)));
      }
    } else if (layer) {
      layer.channels.forEach((name, c) => {
        const value = layer.data[layer.channels.length * i + c];
        parts.push(h("span", { "data-channel": name, "data-value": value }, `${name} ${fmtValue(value)}`));
      });
    }
    replace(inspector, parts);
    inspector.dataset.x = String(x);
    inspector.dataset.y = String(y);
  }

  // -- input: wheel, drag, pinch, keys ---------------------------------------------------
  const pointers = new Map(); // id -> [x, y]
  let pinch = null; // [distance, scale] at the pinch's start
  let moved = 0;
  function local(e) {
    const r = canvas.getBoundingClientRect();
    return [e.clientX - r.left, e.clientY - r.top];
  }
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [x, y] = local(e);
    zoomAt(Math.pow(1.2, -Math.sign(e.deltaY) * Math.min(Math.abs(e.deltaY) / 100, 3)), x, y);
  }, { passive: false });
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, local(e));
    moved = 0;
    if (pointers.size === 2) {
      const [p, q] = [...pointers.values()];
      pinch = [Math.hypot(p[0] - q[0], p[1] - q[1]), scale];
    }
  });
  canvas.addEventListener("pointermove", (e) => {
    const now = local(e);
    const before = pointers.get(e.pointerId);
    if (before) {
      pointers.set(e.pointerId, now);
      if (pointers.size === 2 && pinch) {
        const [p, q] = [...pointers.values()];
        const d = Math.hypot(p[0] - q[0], p[1] - q[1]);
        zoomAt((pinch[1] * d / Math.max(pinch[0], 1)) / scale, (p[0] + q[0]) / 2, (p[1] + q[1]) / 2);
      } else if (pointers.size === 1) {
        ox += now[0] - before[0];
        oy += now[1] - before[1];
        moved += Math.abs(now[0] - before[0]) + Math.abs(now[1] - before[1]);
        fitted = false;
        draw();
      }
    }
    inspect(now);
  });
  const release = (e) => {
    if (pointers.has(e.pointerId) && pointers.size === 1 && moved < 4) { // a tap or click: pin or unpin
      const at = pixelAt(...local(e));
      pinned = pinned && at && pinned[0] === at[0] && pinned[1] === at[1] ? null : at;
      inspect(local(e));
    }
    pointers.delete(e.pointerId);
    if (pointers.size < 2) pinch = null;
  };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("pointerleave", () => { if (!pointers.size) inspect(null); });
  canvas.addEventListener("keydown", (e) => {
    const [cw, ch] = stageSize();
    const step = 40;
    const keys = {
      "+": () => zoomAt(1.5, cw / 2, ch / 2), "=": () => zoomAt(1.5, cw / 2, ch / 2),
      "-": () => zoomAt(1 / 1.5, cw / 2, ch / 2), f: fit, 1: oneToOne,
      ArrowLeft: () => { ox += step; draw(); }, ArrowRight: () => { ox -= step; draw(); },
      ArrowUp: () => { oy += step; draw(); }, ArrowDown: () => { oy -= step; draw(); },
      e: () => setExposure(exposure + 0.5), E: () => setExposure(exposure - 0.5), 0: () => setExposure(0),
    };
    const action = keys[e.key];
    if (action) { e.preventDefault(); action(); }
  });

  // -- controls -----------------------------------------------------------------------
  function setExposure(value) {
    exposure = Math.min(Math.max(value, -12), 12);
    exposureInput.value = String(exposure);
    exposureLabel.textContent = `${exposure >= 0 ? "+" : ""}${exposure.toFixed(1)} EV`;
    repaint();
  }
  exposureInput.addEventListener("input", () => setExposure(Number(exposureInput.value)));
  displaySelect.addEventListener("change", () => { display = displaySelect.value; repaint(); });
  channelSelect.addEventListener("change", () => { channel = channelSelect.value; repaint(); inspect(lastPointer); });
  layerSelect.addEventListener("change", async () => {
    layerName = layerSelect.value;
    channel = "rgb";
    await ensureLayer();
    renderChannels();
    if (layerName === RELERR && display !== "false") { display = "false"; displaySelect.value = "false"; }
    repaint();
    inspect(lastPointer);
  });
  fitButton.addEventListener("click", fit);
  oneButton.addEventListener("click", oneToOne);
  modeSelect.addEventListener("change", () => { compareMode = modeSelect.value; splitInput.hidden = compareMode !== "split"; repaint(); });
  splitInput.addEventListener("input", () => { split = Number(splitInput.value); draw(); });
  compareSelect.addEventListener("focus", listCandidates);
  compareSelect.addEventListener("change", () => compareWith(compareSelect.value));

  function renderLayers() {
    const names = [...A.layers].sort((a, b) => (a === "beauty" ? -1 : b === "beauty" ? 1 : 0));
    names.splice(names.indexOf("var") + 1 || names.length, 0, RELERR);
    replace(layerSelect, names.map((name) => h("option", { value: name, selected: name === layerName }, name)));
  }

  function renderChannels() {
    const layer = shownLayer();
    const names = layer ? layer.channels : [];
    const options = names.length > 1 ? [["rgb", names.join(" ")], ["lum", "luminance"],
      ...names.map((n, i) => [String(i), n.split(".").pop()])] : [["rgb", names[0] || "value"]];
    replace(channelSelect, options.map(([value, label]) => h("option", { value, selected: value === channel }, label)));
    channelSelect.disabled = options.length < 2;
  }

  async function ensureLayer() {
    if (["beauty", "var", RELERR].includes(layerName)) return;
    if (A.layer && A.layer.name === layerName && A.layer.version === A.version) return;
    try {
      const layer = await fetchLayer(jobId, layerName);
      A.layer = { ...layer, name: layerName, version: A.version };
    } catch (err) {
      status.textContent = `Layer ${layerName}: ${err.message}`;
    }
  }

  // -- A/B --------------------------------------------------------------------------------
  let candidatesListed = false;
  async function listCandidates() {
    if (candidatesListed || !A) return;
    candidatesListed = true;
    try {
      const jobs = await api.get("/jobs?limit=200");
      const same = jobs.filter((j) => j.id !== jobId && j.width === A.width && j.height === A.height
        && (j.status === "done" || j.partial || j.status === "running"));
      replace(compareSelect, h("option", { value: "" }, same.length ? "compare with…" : "no other job of this size"),
        same.map((j) => h("option", { value: j.id, selected: j.id === compareId },
          `${j.id.slice(0, 8)} · ${j.method} · ${j.sampler} · ${j.spp ?? "target"} spp · ${j.status}`)));
    } catch (err) {
      candidatesListed = false;
      status.textContent = `Jobs to compare: ${err.message}`;
    }
  }

  async function compareWith(id) {
    compareId = id;
    B = null;
    compareStats.textContent = "";
    modeSelect.hidden = splitInput.hidden = !id;
    if (!id) { repaint(); return; }
    try {
      const other = await fetchLayer(id, "beauty");
      if (other.width !== A.width || other.height !== A.height) {
        throw new Error(`job ${id} is ${other.width}×${other.height}, this one ${A.width}×${A.height}`);
      }
      B = other;
      if (layerName !== "beauty") { layerName = "beauty"; layerSelect.value = "beauty"; renderChannels(); }
      splitInput.hidden = compareMode !== "split";
      compareStats.textContent = differenceStats();
      repaint();
    } catch (err) {
      compareStats.textContent = `Cannot compare: ${err.message}`;
    }
  }

  // RMSE over every pixel and channel; relMSE the mean of (A−B)² / (B² + 0.01),
  // B taken as the reference (pbrt's imgtool weighs its relative MSE alike).
  function differenceStats() {
    const a = A.beauty.data;
    const b = B.data;
    let se = 0;
    let rel = 0;
    for (let i = 0; i < a.length; i++) {
      const d = a[i] - b[i];
      se += d * d;
      rel += (d * d) / (b[i] * b[i] + 0.01);
    }
    const rmse = Math.sqrt(se / a.length);
    const relmse = rel / a.length;
    compareStats.dataset.rmse = String(rmse);
    compareStats.dataset.relmse = String(relmse);
    return `A = this job, B = ${compareId.slice(0, 8)}: RMSE ${fmtValue(rmse)} · relMSE ${fmtValue(relmse)}`;
  }

  // -- loading ------------------------------------------------------------------------------
  async function reload() {
    if (destroyed) return;
    if (loading) { again = true; return; }
    loading = (async () => {
      try {
        const [beauty, variance] = await Promise.all([fetchLayer(jobId, "beauty"), fetchLayer(jobId, "var")]);
        const first = !A;
        A = { beauty, var: variance, layers: beauty.layers, width: beauty.width, height: beauty.height,
          source: beauty.source, version: (A ? A.version : 0) + 1, layer: A && A.layer };
        if (!A.layers.includes(layerName) && layerName !== RELERR) layerName = "beauty";
        await ensureLayer();
        renderLayers();
        renderChannels();
        stageEl.style.aspectRatio = `${A.width} / ${A.height}`;
        status.textContent = A.source === "running" ? "The frame merged so far: it updates as units land."
          : A.source === "partial" ? "Partial: the units that finished before the job stopped." : "";
        el.dataset.source = A.source;
        el.dataset.version = String(A.version);
        if (B) compareStats.textContent = differenceStats();
        repaint();
        if (first || fitted) fit();
        if (first) listCandidates();
      } catch (err) {
        status.textContent = err.status === 404 ? "No pixels yet: they come with the first unit." : `Pixels: ${err.message}`;
      } finally {
        loading = null;
        if (again && !destroyed) { again = false; reload(); }
      }
    })();
  }

  const resize = new ResizeObserver(() => { if (fitted) fit(); else draw(); });
  resize.observe(stageEl);

  return {
    el,
    reload,
    destroy() { destroyed = true; resize.disconnect(); },
  };
}
