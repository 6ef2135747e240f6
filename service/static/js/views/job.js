// One job: its image sharpening as passes land, the tile map, the noise map,
// the HDR viewer over its float data (viewer.js),
// progress and throughput, its units (a row opens the unit's log), and what
// can be done to it.
// Live from GET /jobs/{id}/events: job, units (snapshot), unit, preview, end.

import { ApiError, api, offline, stream } from "../api.js";
import { may, readOnlyReason } from "../session.js";
import { FINAL, badge, fmt, h, progressBar, replace, toast } from "../ui.js";
import { elapsedNow, errorText, etaText, progressFraction, progressLabel } from "./jobs.js";
import { convergencePlot, curvesPlot } from "../plot.js";
import { hdrViewer } from "../viewer.js";

const WORKER_COLORS = ["#4aa3ff", "#ffb547", "#3ecf8e", "#ff7ab6", "#b48cff", "#5ee0e6", "#ff8f5c",
  "#c3e86b", "#ffd966", "#8fa8ff"];

// A tile's state over its passes: the most telling one of its units.
function tileState(units) {
  const states = units.map((u) => u.state);
  if (states.includes("running")) return "running";
  if (states.includes("failed")) return "failed";
  // skipped: a target job's tile met its target before that pass (finished, no samples)
  if (states.every((s) => s === "done" || s === "skipped")) return "done";
  if (states.includes("done")) return "partial";
  if (states.includes("queued")) return "queued";
  if (states.includes("canceled")) return "canceled";
  return "pending";
}

export function jobView(root, jobId) {
  let job = null;
  let deleted = false;
  const units = new Map(); // index -> unit
  let view = "image"; // or "noise", or "denoised" (a job with denoise, once done)
  let showTiles = null; // null: automatic (on while the job runs)
  let colorBy = "state";
  let unitFilter = "all";
  let previewVersion = 0;
  let closeStream = null;

  // -- skeleton -------------------------------------------------------------------
  const title = h("h1.mono");
  const status = h("span");
  const summary = h("span.muted");
  const owner = h("span#job-owner");
  const actions = h("div.actions#job-actions");
  const banner = h("div");
  const stage = h("div.stage#stage");
  const tiles = h("div.tiles#tile-map");
  const placeholder = h("div.placeholder", {}, "Waiting for the first unit to land…");
  stage.append(placeholder, tiles);
  const viewTabs = h("div.tabs", { role: "tablist", "aria-label": "image or noise" });
  const tileToggle = h("input#show-tiles", { type: "checkbox" });
  const colorSelect = h("select#color-tiles", { "aria-label": "colour tiles by" },
    h("option", { value: "state" }, "by state"), h("option", { value: "worker" }, "by worker"));
  const legend = h("div.legend#legend");
  const progressBox = h("div.panel-body");
  const statsBox = h("div.panel-body");
  const convergenceBox = h("div.panel-body#convergence");
  const convergencePanel = h("div.panel", { hidden: true }, h("h2", {}, "Convergence"), convergenceBox);
  const paramsBox = h("div.panel-body");
  const downloads = h("div.panel-body.actions");
  const workersBox = h("div.panel-body");
  const blocklistBox = h("div.panel-body#blocklist");
  const unitsHead = h("div.viewer-bar");
  const unitsBody = h("tbody");
  const logTitle = h("h2", {}, "Unit log");
  const logBody = h("div.panel-body#unit-log-body");
  const logPanel = h("div.panel#unit-log", { hidden: true }, logTitle, logBody);
  let logUnit = null; // the index whose log is shown
  let logSeen = ""; // that unit's state and tasks when its log was fetched

  replace(root,
    h("div.page-head", {},
      h("a.muted", { href: "#/jobs" }, "← Jobs"), title, status, owner, summary, h("div.spacer"), actions),
    banner,
    h("div.job-layout", {},
      h("div", { style: { display: "flex", flexDirection: "column", gap: "16px" } },
        h("div.panel.viewer", {},
          h("div.viewer-bar", {}, viewTabs,
            h("label.check", {}, tileToggle, "tile map"), colorSelect, h("div", { style: { flex: 1 } }), legend),
          stage),
        h("div.panel", {}, h("h2", {}, "Units"),
          h("div.panel-body", {}, unitsHead,
            h("div.unit-table", {}, h("table.grid#units-table", {},
              h("thead", {}, h("tr", {}, ["#", "Phase", "Region", "Samples", "State", "Worker", "Attempts",
                "Render time", "Error"].map((t) => h("th", {}, t)))), unitsBody)))),
        logPanel),
      h("div.side", {},
        h("div.panel", {}, h("h2", {}, "Progress"), progressBox),
        convergencePanel,
        h("div.panel", {}, h("h2", {}, "Throughput"), statsBox),
        h("div.panel", {}, h("h2", {}, "Workers"), workersBox),
        h("div.panel", {}, h("h2", {}, "Blocklist"), blocklistBox),
        h("div.panel", {}, h("h2", {}, "Parameters"), paramsBox),
        h("div.panel", {}, h("h2", {}, "Downloads"), downloads))));

  tileToggle.addEventListener("change", () => { showTiles = tileToggle.checked; renderTiles(); });
  colorSelect.addEventListener("change", () => { colorBy = colorSelect.value; renderTiles(); });

  // -- actions ----------------------------------------------------------------------
  async function act(label, fn, reopen = false) {
    try {
      const result = await fn();
      if (result && result.id) setJob(result);
      toast(`${label}: done`);
      if (reopen) openStream();
    } catch (err) {
      toast(`${label}: ${err.message}`, true);
    }
  }

  // The action buttons are built once and only enabled or disabled afterwards:
  // re-creating them on every event would swallow clicks and flicker.
  const button = (label, onclick, cls = "") =>
    h(`button${cls}`, { onclick, "data-action": label.toLowerCase(), disabled: true }, label);
  const priorityInput = h("input#priority", { type: "number", min: -100, max: 100,
    style: { width: "70px" }, "aria-label": "priority" });
  const buttons = {
    pause: button("Pause", () => act("Pause", () => api.post(`/jobs/${jobId}/pause`))),
    resume: button("Resume", () => act("Resume", () => api.post(`/jobs/${jobId}/resume`))),
    cancel: button("Cancel", () => act("Cancel", () => api.post(`/jobs/${jobId}/cancel`))),
    retry: button("Retry", () => act("Retry", () => api.post(`/jobs/${jobId}/retry`), true)),
    requeue: button("Requeue", () => act("Requeue", () => api.post(`/jobs/${jobId}/requeue`), true)),
    priority: button("Set", () => {
      const value = Number(priorityInput.value);
      act("Priority", () => api.patch(`/jobs/${jobId}`, { priority: value }));
    }),
    delete: button("Delete", () => {
      if (!confirm(`Delete job ${jobId}, its units and its images?`)) return;
      api.del(`/jobs/${jobId}`).then(() => { toast(`Job ${jobId} deleted`); location.hash = "#/jobs"; })
        .catch((err) => toast(`Delete: ${err.message}`, true));
    }, ".danger"),
  };
  buttons.priority.title = "change the priority (higher runs first)";
  // Someone who may not change this job (a viewer) sees the buttons off, and why.
  const readOnly = h("span.muted.read-only#read-only-note", { hidden: true });
  replace(actions, readOnly, buttons.pause, buttons.resume, buttons.cancel, buttons.retry, buttons.requeue,
    h("span.muted", { style: { marginLeft: "8px" } }, "priority"), priorityInput, buttons.priority,
    buttons.delete);

  function renderActions() {
    const s = job && !deleted ? job.status : null;
    const failedUnits = [...units.values()].some((u) => u.state === "failed");
    const enabled = {
      pause: s === "queued" || s === "running",
      resume: s === "paused",
      cancel: s !== null && !FINAL.has(s),
      retry: s === "failed" || (failedUnits && (s === "running" || s === "paused")),
      requeue: s !== null && s !== "queued",
      priority: s !== null,
      delete: s !== null,
    };
    const mayChange = !job || may.change(job);
    const reason = mayChange ? "" : readOnlyReason() || "you may not change this job";
    for (const [name, on] of Object.entries(enabled)) {
      buttons[name].disabled = !on || !mayChange;
      if (name !== "priority") buttons[name].title = reason;
    }
    buttons.priority.title = reason || "change the priority (higher runs first)";
    priorityInput.disabled = s === null || !mayChange;
    readOnly.hidden = mayChange;
    readOnly.textContent = reason;
    if (job && document.activeElement !== priorityInput) priorityInput.value = job.priority;
  }

  // -- the viewer ---------------------------------------------------------------------
  function sizeStage() {
    if (!job) return;
    const { width, height } = job;
    const maxWidth = Math.max(width, 512);
    stage.style.aspectRatio = `${width} / ${height}`;
    stage.style.width = `min(100%, ${maxWidth}px, calc(72vh * ${width / height}))`;
  }

  function renderViewTabs() {
    const views = [["image", "Image"], ["noise", "Noise"]];
    if (job && job.denoised_url) views.push(["denoised", "Denoised"]);
    views.push(["hdr", "HDR"]);
    replace(viewTabs, views.map(([key, label]) =>
      h(`button${view === key ? ".active" : ""}`, { "data-view": key, role: "tab",
        onclick: () => { view = key; renderViewTabs(); loadImage(); renderLegend(); } }, label)));
  }

  function imageUrl() {
    if (!job || !(job.preview_url)) return null;
    const base = view === "noise" ? job.noise_url
      : view === "denoised" && job.denoised_url ? job.denoised_url : job.preview_url;
    return `${base}?v=${previewVersion}-${job.status === "done" ? "final" : job.progress.units_done}`;
  }

  let loading = null;
  let viewer = null; // the HDR viewer (viewer.js), made when its tab is first opened
  function loadImage() {
    const hdr = view === "hdr";
    stage.hidden = hdr;
    if (viewer) viewer.el.hidden = !hdr;
    if (hdr) {
      if (!viewer) { viewer = hdrViewer(jobId); stage.after(viewer.el); }
      if (job && job.preview_url) viewer.reload();
      return;
    }
    const url = imageUrl();
    if (!url) return;
    const img = new Image();
    img.alt = view === "noise" ? "noise heatmap" : view === "denoised" ? "denoised" : "preview";
    img.id = "preview";
    img.dataset.view = view;
    loading = img;
    img.onload = () => {
      if (loading !== img) return; // a newer one is on its way
      const old = stage.querySelector("img");
      if (old) old.replaceWith(img); else stage.insertBefore(img, tiles);
      placeholder.remove();
      img.dataset.loaded = String(previewVersion);
    };
    img.src = url;
  }

  function renderLegend() {
    if (view === "hdr") {
      replace(legend, h("span.muted", {}, "float data: wheel or pinch to zoom, drag to pan, tap to pin a pixel"));
      return;
    }
    if (view === "denoised") {
      replace(legend, h("span.denoised-note", {}, "Denoised: a biased post-process (Intel Open Image "
        + "Denoise over the merged frame). The EXR keeps the raw R, G, B and their variance; "
        + "denoised.R/G/B sit beside them."));
      return;
    }
    if (view === "noise") {
      replace(legend, h("span", {}, "rel. std. error"), h("span", {}, "0.1%"), h("span.noise-scale"),
        h("span", {}, "100%"), h("span", {}, h("span.sw", { style: { background: "#808080" } }), "< 2 samples"));
      return;
    }
    if (!tilesShown()) { replace(legend); return; }
    if (colorBy === "worker") {
      replace(legend, [...workerColors().entries()].map(([name, color]) =>
        h("span", {}, h("span.sw", { style: { background: color } }), name)));
      return;
    }
    const items = [["pending", "#6c7a89"], ["queued", "#4aa3ff"], ["running", "#ffb547"],
      ["partial", "#3ecf8e80"], ["done", "transparent"], ["failed", "#ff5c69"]];
    replace(legend, items.map(([name, color]) =>
      h("span", {}, h("span.sw", { style: { background: color, border: "1px solid #2a3542" } }), name)));
  }

  function tilesShown() {
    return showTiles === null ? !!job && !FINAL.has(job.status) : showTiles;
  }

  function workerColors() {
    const names = [...new Set([...units.values()].map((u) => u.worker).filter(Boolean))].sort();
    return new Map(names.map((name, i) => [name, WORKER_COLORS[i % WORKER_COLORS.length]]));
  }

  function renderTiles() {
    if (!job) return;
    tileToggle.checked = tilesShown();
    tiles.classList.toggle("show", tilesShown());
    const groups = new Map();
    const add = (key, u) => {
      if (!groups.has(key)) groups.set(key, []);
      groups.get(key).push(u);
    };
    const ts = job.tile_size;
    for (const u of units.values()) {
      const r = u.region;
      if (r.x1 <= r.x0 || r.y1 <= r.y0) continue; // a prepass (photon map, solve): no region
      if (u.kind === "tile" && ts && (r.x1 - r.x0 > ts || r.y1 - r.y0 > ts)) {
        // an early progressive pass's unit spans several tiles (renderer/plan.py
        // groups tiles that hold few samples): it counts for each of them
        for (let y = r.y0; y < r.y1; y += ts) {
          for (let x = r.x0; x < r.x1; x += ts) {
            add(`${x},${y},${Math.min(x + ts, r.x1)},${Math.min(y + ts, r.y1)}`, u);
          }
        }
        continue;
      }
      add(`${r.x0},${r.y0},${r.x1},${r.y1}`, u);
    }
    const colors = workerColors();
    const passes = Math.max(1, ...[...units.values()].map((u) => u.region.pass + 1));
    const frag = document.createDocumentFragment();
    for (const [key, group] of groups) {
      const [x0, y0, x1, y1] = key.split(",").map(Number);
      group.sort((a, b) => a.region.pass - b.region.pass);
      const state = tileState(group);
      const done = group.filter((u) => u.state === "done" || u.state === "skipped").length;
      const workers = [...new Set(group.map((u) => u.worker).filter(Boolean))];
      const current = group.find((u) => u.state === "running") || [...group].reverse().find((u) => u.worker);
      const tile = h(`div.tile.t-${state}`, {
        "data-state": state, "data-tile": key,
        title: [`tile ${x0}–${x1} × ${y0}–${y1}`, `${state} · passes done ${done}/${group.length}`,
          workers.length ? `worker${workers.length > 1 ? "s" : ""}: ${workers.join(", ")}` : "no worker yet",
          `render time ${fmt.duration(group.reduce((s, u) => s + (u.seconds || 0), 0))}`].join("\n"),
        style: { left: `${100 * x0 / job.width}%`, top: `${100 * y0 / job.height}%`,
          width: `${100 * (x1 - x0) / job.width}%`, height: `${100 * (y1 - y0) / job.height}%` },
      });
      if (colorBy === "worker" && current && current.worker) {
        tile.style.background = `${colors.get(current.worker)}66`;
        tile.style.animation = "none";
      }
      if (passes > 1 && state !== "done") {
        tile.append(h("div.bar", { style: { width: `${100 * done / group.length}%` } }));
      }
      frag.append(tile);
    }
    tiles.replaceChildren(frag);
    renderLegend();
  }

  // -- panels -------------------------------------------------------------------------
  function kv(pairs) {
    return h("dl.kv", {}, pairs.map(([k, v, id]) => [h("dt", {}, k), h("dd", id ? { id } : {}, v)]));
  }

  function renderProgress() {
    const p = job.progress;
    replace(progressBox,
      progressBar(progressFraction(job), progressLabel(job), job.status, true),
      h("div", { style: { height: "10px" } }),
      kv([
        ...(job.target ? [
          ["error", `${errorText(p.rel_error)} → ${errorText(p.target_rel_error)}`
            + ` after ${(job.passes || []).length} passes`, "target-error"],
          ["stopped", job.target_stop ? { target: "target met", max_spp: "at the most spp",
            max_seconds: "time budget spent" }[job.target_stop] : "–", "target-stop"],
          ["samples", `${p.samples_done.toLocaleString()} (at most ${p.samples_total.toLocaleString()})`, "samples"],
          ["units", `${p.units_done} / ${p.units_total} · ${p.units_skipped} skipped`, "units"],
        ] : [
          ["samples", `${p.samples_done.toLocaleString()} / ${p.samples_total.toLocaleString()}`, "samples"],
          ["units", `${p.units_done} / ${p.units_total}`, "units"],
        ]),
        ["elapsed", fmt.duration(elapsedNow(job)), "elapsed"],
        ["ETA", etaText(job), "eta"],
        ["submitted", fmt.time(job.created)],
        ["started", fmt.time(job.started)],
        ["finished", fmt.time(job.finished)],
      ]),
      phasesBox(),
      job.error ? h("div.error-box#job-error", {}, job.error) : null);
  }

  // The phases of a DAG job (prepass -> units -> ..., renderer/plan.py): per unit
  // kind, in the order its first stage runs, how many of its units are done.
  function phasesBox() {
    const phases = new Map();
    for (const u of [...units.values()].sort((a, b) => a.stage - b.stage || a.index - b.index)) {
      if (!phases.has(u.kind)) phases.set(u.kind, { done: 0, total: 0, running: 0 });
      const p = phases.get(u.kind);
      p.total += 1;
      if (u.state === "done" || u.state === "skipped") p.done += 1;
      if (u.state === "running") p.running += 1;
    }
    if (phases.size < 2) return null;
    return h("div.phases#phases", {}, h("h3", {}, "Phases"),
      [...phases].map(([kind, p]) => h("div.phase", { "data-phase": kind },
        h("span.phase-name", {}, kind),
        progressBar(p.done / p.total, `${p.done} / ${p.total}${p.running ? ` · ${p.running} running` : ""}`,
          p.done === p.total ? "done" : p.running ? "running" : "queued", false))));
  }

  // The error after each complete pass against the samples (a progressive tile
  // job's `passes`), with the 1/sqrt(N) slope and a target job's target.
  function renderConvergence() {
    const plot = convergencePlot(job.passes, job.target ? job.target.rel_error : null);
    convergencePanel.hidden = !plot;
    if (!plot) return;
    const last = job.passes[job.passes.length - 1];
    // and against render seconds: what a user pays (efficiency is error against time)
    const byTime = curvesPlot([{ label: "by render time", color: "#4aa3ff",
      points: job.passes.map((p) => [p.seconds, p.rel_error]) }],
    { xLabel: "seconds", percent: true, width: 320, height: 200, label: "error against render seconds, log-log" });
    if (byTime) byTime.id = "convergence-time";
    replace(convergenceBox, plot, byTime, h("div.muted", { style: { fontSize: "12px" } },
      `error ${errorText(last.rel_error)} after ${job.passes.length} passes`
      + ` (95th percentile of the relative standard error); dashed: 1/√N`
      + (job.target ? "; line: the target" : "")));
  }

  function renderStats() {
    const s = job.stats;
    replace(statsBox, kv([
      ["samples/s", fmt.rate(s.samples_per_second), "samples-per-second"],
      ["samples/s, last 10 s", fmt.rate(s.recent_samples_per_second), "recent-samples-per-second"],
      ["rays/s", fmt.rate(s.rays_per_second), "rays-per-second"],
      ["seconds per unit", s.seconds_per_unit === null ? "–" : `${s.seconds_per_unit.toFixed(3)} s`],
      ["units retried", s.units_retried],
      ["rays", fmt.count(job.rays)],
    ]));
  }

  function renderParams() {
    const options = Object.entries(job.options || {});
    replace(paramsBox, kv([
      ["owner", job.owner, "param-owner"],
      ["scene", job.scene],
      ["scene hash", h("span.mono", { title: job.scene_hash }, job.scene_hash.slice(0, 12))],
      ["method", job.method],
      ...options.map(([k, v]) => [`  ${k}`, String(v)]),
      ["sampler", job.sampler],
      ["spp", job.target ? `at most ${job.spp}` : job.spp],
      ...(job.target ? [["noise target", `${errorText(job.target.rel_error)}`
        + (job.target.max_seconds ? `, at most ${fmt.duration(job.target.max_seconds)}` : ""),
        "param-target"]] : []),
      ["depth", job.depth],
      ["resolution", `${job.width} × ${job.height}`],
      ["tile size", job.tile_size],
      ["seed", job.seed],
      ["passes", job.target ? "one per sample block (1, 1, 2, 4 … 64 spp), tile by tile until the target"
        : job.progressive ? "progressive (doubling, up to 64 spp a pass)" : "one"],
      ["denoise", job.denoise ? "after the merge (biased; raw kept)" : "no"],
      ["priority", job.priority],
    ]));
  }

  function renderDownloads() {
    const link = (label, url, id) => url
      ? h("a.button", { href: url, download: "", id }, label)
      : h("button", { disabled: true, id }, label);
    // A canceled or failed job's EXR and PNG hold the units it finished (partial).
    const p = job.progress;
    replace(downloads,
      link(job.partial ? "EXR (partial)" : "EXR", job.result_url, "download-exr"),
      link(job.partial ? "PNG (partial)" : "PNG",
        job.preview_url && (job.status === "done" || job.partial) ? job.preview_url : null, "download-png"),
      link("Noise PNG", job.status === "done" ? job.noise_url : null, "download-noise"),
      job.denoise ? link("Denoised PNG", job.denoised_url, "download-denoised") : null,
      h("span.muted#download-note", { style: { fontSize: "12px" } },
        job.status === "done" ? "float32 R, G, B, var.R/G/B, samples.Y and the AOV layers"
          + (job.denoise ? ", denoised.R/G/B" : "")
          : job.partial ? `partial: the ${p.units_done} of ${p.units_total} units finished before `
            + `the job was ${job.status} (pixels without a sample read 0)`
          : "available when the job is done"));
  }

  function renderWorkers() {
    const colors = workerColors();
    const tally = new Map();
    for (const u of units.values()) {
      if (!u.worker) continue;
      const t = tally.get(u.worker) || { done: 0, running: 0, seconds: 0 };
      if (u.state === "done") { t.done += 1; t.seconds += u.seconds || 0; }
      if (u.state === "running") t.running += 1;
      tally.set(u.worker, t);
    }
    replace(workersBox, tally.size ? h("div.worker-list", {}, [...tally.entries()].map(([name, t]) =>
      h("div.row", {}, h("span.sw", { style: { background: colors.get(name), width: "10px", height: "10px",
        borderRadius: "2px", display: "inline-block" } }), h("span.name", { title: name }, name),
      h("span.num", {}, `${t.done} done${t.running ? ` · ${t.running} running` : ""}`),
      h("span.num.muted", {}, fmt.duration(t.seconds)))))
      : h("span.muted", {}, "No unit has run yet."));
  }

  function renderUnits() {
    const counts = {};
    for (const u of units.values()) counts[u.state] = (counts[u.state] || 0) + 1;
    replace(unitsHead, h("div.tabs", {}, ["all", "running", "queued", "pending", "done", "skipped", "failed", "canceled"]
      .filter((s) => s === "all" || counts[s]).map((s) => h(`button${s === unitFilter ? ".active" : ""}`,
        { onclick: () => { unitFilter = s; renderUnits(); }, "data-units": s },
        s, h("span.count", {}, s === "all" ? units.size : counts[s])))));
    const shown = [...units.values()].filter((u) => unitFilter === "all" || u.state === unitFilter)
      .sort((a, b) => a.index - b.index).slice(0, 1000);
    replace(unitsBody, shown.length ? shown.map((u) => h(`tr.clickable${u.index === logUnit ? ".selected" : ""}`, {
      "data-unit": u.index, tabindex: 0, title: "show this unit's log",
      onclick: () => showLog(u.index),
      onkeydown: (e) => { if (e.key === "Enter") showLog(u.index); } },
      h("td.num", {}, u.index),
      h("td", {}, u.kind === "tile" ? `pass ${u.region.pass}` : `${u.kind} (stage ${u.stage})`),
      h("td.mono", {}, `${u.region.x0},${u.region.y0}–${u.region.x1},${u.region.y1}`),
      h("td.mono", {}, `${u.region.sample_start}–${u.region.sample_end}`),
      h("td", {}, badge(u.state)), h("td.mono", {}, u.worker || "–"),
      h("td.num", {}, u.tasks > u.attempts ? `${u.attempts} (${u.tasks} tasks)` : u.attempts),
      h("td.num", {}, u.seconds === null ? "–" : `${u.seconds.toFixed(3)} s`),
      h("td.wrap", {}, u.error || (u.requeue_reason && u.state !== "done"
        ? h("span.muted", { "data-requeued": "yes" }, `requeued: ${u.requeue_reason}`) : ""))))
      : h("tr", {}, h("td.empty", { colspan: 9 }, job && job.progress.units_total ? "No such units."
        : "The job is not planned yet.")));
  }

  // -- a unit's log (GET /jobs/{id}/units/{i}/log): per task, its lines and traceback ----
  async function showLog(index) {
    logUnit = index;
    const unit = units.get(index);
    logSeen = unit ? `${unit.state}/${unit.tasks}` : "";
    logPanel.hidden = false;
    replace(logTitle, `Unit ${index} log`, h("button.close#unit-log-close", { title: "close",
      onclick: () => { logUnit = null; logPanel.hidden = true; renderUnits(); } }, "×"));
    renderUnits();
    try {
      const log = await api.get(`/jobs/${jobId}/units/${index}/log`);
      if (logUnit !== index) return; // another row was chosen meanwhile
      replace(logBody,
        h("div.muted", {}, `${log.state}${log.error ? ` · ${log.error}` : ""}`),
        log.attempts.length ? log.attempts.map((a) => h("div.unit-attempt", { "data-task": a.task },
          h("h3", {}, `task ${a.task} · attempt ${a.attempt} · ${a.outcome}${a.worker ? ` on ${a.worker}` : ""}`),
          a.dropped ? h("div.muted", {}, `${a.dropped} earlier lines dropped`) : null,
          h("pre.log-lines", {}, a.lines.length ? a.lines.join("\n") : "(no log lines)"),
          a.traceback ? h("pre.log-traceback", {}, a.traceback) : null))
          : h("div.muted#unit-log-empty", {}, "No task of this unit has reported yet."));
    } catch (err) {
      if (logUnit === index) replace(logBody, h("div.error-box", {}, `Could not load the log: ${err.message}`));
    }
  }

  function refreshLog() { // the shown unit finished or ran again: its log grew
    const unit = logUnit === null ? null : units.get(logUnit);
    if (unit && `${unit.state}/${unit.tasks}` !== logSeen) showLog(logUnit);
  }

  // -- state ----------------------------------------------------------------------------
  function setJob(next) {
    const planned = job && job.progress.units_total;
    job = next;
    job._received = Date.now();
    replace(title, job.id);
    replace(status, badge(job.status));
    replace(owner, h("span.muted", {}, "by "), h("span.owner", {}, job.owner));
    const goal = job.target ? `to ${errorText(job.target.rel_error)} error (≤ ${job.spp} spp)` : `${job.spp} spp`;
    replace(summary, `${job.scene} · ${job.method} · ${job.sampler} · ${goal} · depth ${job.depth}`);
    document.title = `${job.id} · ${job.status} · rayfarm`;
    sizeStage();
    renderActions(); renderProgress(); renderConvergence(); renderStats(); renderParams();
    renderDownloads();
    renderViewTabs();
    if (!planned && job.progress.units_total) renderTiles();
    if (job.status === "done") loadImage();
    tiles.classList.toggle("show", tilesShown());
    tileToggle.checked = tilesShown();
  }

  let unitsDirty = false;
  function unitsChanged() {
    if (unitsDirty) return;
    unitsDirty = true;
    requestAnimationFrame(() => {
      unitsDirty = false;
      renderTiles(); renderUnits(); renderWorkers(); renderActions(); refreshLog();
      if (job) renderProgress(); // the phases
    });
  }

  function openStream() {
    if (closeStream) closeStream();
    closeStream = stream(`/jobs/${jobId}/events`, {
      job: (data) => setJob(data),
      units: (list) => { units.clear(); list.forEach((u) => units.set(u.index, u)); unitsChanged(); },
      unit: (u) => { units.set(u.index, u); unitsChanged(); },
      preview: (p) => { previewVersion = p.version; loadImage(); },
      deleted: () => {
        deleted = true;
        replace(banner, h("div.error-box", {}, "This job was deleted."));
        renderActions();
      },
      end: () => { if (closeStream) { closeStream(); closeStream = null; } },
    });
  }

  // Workers that failed units of this job; blocklisted ones take none of its
  // units until its owner (or an admin) clears them (service/blocklist.py).
  let blocklistShown = "";
  async function loadBlocklist() {
    let rows;
    try {
      rows = await api.get(`/jobs/${jobId}/blocklist`);
    } catch (err) {
      return;
    }
    const key = JSON.stringify(rows);
    if (key === blocklistShown) return;
    blocklistShown = key;
    replace(blocklistBox, rows.length ? h("div.worker-list", {}, rows.map((b) =>
      h("div.row", { "data-blocked-worker": b.worker },
        h("span.name.mono", { title: b.last_error || "" }, b.worker),
        h("span.num", {}, `${b.failures} failed${b.blocked ? " · blocklisted" : ""}`),
        may.change(job) ? h("button.small", {
          "data-action": "clear-block", title: "let it take this job's units again",
          onclick: async () => {
            try {
              await api.del(`/jobs/${jobId}/blocklist/${encodeURIComponent(b.worker)}`);
              toast(`Cleared ${b.worker}`);
            } catch (err) {
              toast(`Clear failed: ${err.message}`, true);
            }
            loadBlocklist();
          },
        }, "Clear") : null)))
      : h("span.muted", {}, "No worker failed a unit of this job."));
  }

  renderViewTabs();
  loadBlocklist();
  const blocklistTimer = setInterval(() => { if (job && !FINAL.has(job.status)) loadBlocklist(); }, 5000);
  api.get(`/jobs/${jobId}`).then((data) => {
    setJob(data);
    if (data.preview_url) loadImage();
    openStream();
  }).catch((err) => {
    replace(root, h("div.page-head", {}, h("a.muted", { href: "#/jobs" }, "← Jobs")),
      h("div.error-box", {}, err instanceof ApiError && err.status === 404
        ? `There is no job ${jobId}.` : `Could not load job ${jobId}: ${err.message}`));
  });
  const ticker = setInterval(() => {
    if (!job || job.status !== "running" || offline()) return; // frozen: the banner says as of when
    const elapsed = document.getElementById("elapsed");
    const eta = document.getElementById("eta");
    if (elapsed) elapsed.textContent = fmt.duration(elapsedNow(job));
    if (eta) eta.textContent = etaText(job);
  }, 1000);
  return () => {
    if (closeStream) closeStream();
    if (viewer) viewer.destroy();
    clearInterval(ticker); clearInterval(blocklistTimer);
  };
}
