// The jobs list: every job with its progress, filtered by status, live.
// It loads GET /jobs once, then follows GET /events (job, deleted, resync).

import { api, stream } from "../api.js";
import { may, readOnlyReason, session } from "../session.js";
import { badge, fmt, h, progressBar, replace, toast } from "../ui.js";

const STATUSES = ["all", "queued", "running", "paused", "done", "failed", "canceled"];
const LIMIT = 500;

// Elapsed seconds now: the server's figure plus the time since we received
// it, while the job runs (so the column ticks between events).
export function elapsedNow(job) {
  const base = job.progress.elapsed;
  if (base === null || base === undefined) return null;
  return job.status === "running" ? base + (Date.now() - job._received) / 1000 : base;
}

export function etaNow(job) {
  const eta = job.progress.eta;
  if (eta === null || eta === undefined || job.status !== "running") return eta;
  return Math.max(eta - (Date.now() - job._received) / 1000, 0);
}

// The ETA as shown: "estimating…" while a running job has none yet (the
// service gives one once a rate is measured between two landings of units).
export function etaText(job) {
  if (job.status !== "running") return job.status === "done" ? "finished" : "–";
  const eta = etaNow(job);
  return eta === null || eta === undefined ? "estimating…" : fmt.duration(eta);
}

// A relative error as a percentage: 0.0183 -> "1.83 %"; unknown -> "?".
export function errorText(e) {
  return e === null || e === undefined ? "?" : `${+(100 * e).toPrecision(3)} %`;
}

export function progressLabel(job) {
  const p = job.progress;
  if (!p.units_total) return job.status === "queued" ? "waiting" : "–";
  if (job.target) return `error ${errorText(p.rel_error)} → ${errorText(p.target_rel_error)}`;
  return `${fmt.percent(p.fraction)} · ${fmt.count(p.samples_done)}/${fmt.count(p.samples_total)}`;
}

// How far along the bar is: the samples' fraction, or for a job rendering to
// a noise target the work its error says is done, (target / error)^2 (error
// falls as 1/sqrt(samples)).
export function progressFraction(job) {
  const p = job.progress;
  if (!job.target) return p.fraction;
  if (job.status === "done") return 1;
  if (p.rel_error === null || p.rel_error === undefined) return 0;
  return Math.min((p.target_rel_error / p.rel_error) ** 2, 1);
}

export function jobsView(root) {
  const jobs = new Map(); // id -> job, newest first by `created`
  let filter = new URLSearchParams(location.hash.split("?")[1] || "").get("status") || "all";
  const tabs = h("div.tabs", { role: "tablist", "aria-label": "filter by status" });
  const body = h("tbody");
  const selected = new Set(); // done jobs ticked for #/compare
  const compareButton = h("button#compare-jobs", { type: "button", disabled: true,
    title: "tick done jobs to plot their convergence together",
    onclick: () => { location.hash = `#/compare?jobs=${[...selected].join(",")}`; } }, "Compare");
  const table = h("table.grid#jobs-table", {},
    h("thead", {}, h("tr", {}, ["", "Job", "Owner", "Scene", "Method", "Sampler", "spp", "Depth", "Priority",
      "Status", "Progress", "Elapsed", "ETA", "Submitted"].map((t, i) =>
      h(i >= 6 && i <= 8 || i >= 11 && i <= 12 ? "th.num" : "th", {}, t)))),
    body);
  const error = h("div");
  // A viewer cannot submit: the button stays, off, with the reason beside it.
  const newJob = may.submit() ? h("a.button#new-job", { href: "#/submit" }, "+ New job")
    : [h("span.muted.read-only#read-only-note", {}, readOnlyReason()),
      h("button#new-job", { type: "button", disabled: true, title: readOnlyReason() }, "+ New job")];
  replace(root,
    h("div.page-head", {}, h("h1", {}, session.me.role === "artist" ? "Your jobs" : "Jobs"), tabs, h("div.spacer"),
      compareButton, newJob),
    error,
    h("div.panel", {}, table));

  function renderTabs() {
    const counts = { all: jobs.size };
    for (const job of jobs.values()) counts[job.status] = (counts[job.status] || 0) + 1;
    replace(tabs, STATUSES.map((s) => h(`button${s === filter ? ".active" : ""}`, {
      role: "tab", "aria-selected": String(s === filter), "data-status": s,
      onclick: () => { filter = s; history.replaceState(null, "", s === "all" ? "#/jobs" : `#/jobs?status=${s}`); render(); },
    }, s, h("span.count", {}, counts[s] || 0))));
  }

  function renderCompare() {
    for (const id of [...selected]) if (!jobs.has(id) || jobs.get(id).status !== "done") selected.delete(id);
    compareButton.disabled = selected.size === 0 || selected.size > 8;
    compareButton.textContent = selected.size ? `Compare (${selected.size})` : "Compare";
  }

  function row(job) {
    const tick = job.status === "done" ? h("input.select", { type: "checkbox", "data-select": job.id,
      "aria-label": `compare ${job.id}`, checked: selected.has(job.id),
      onclick: (event) => event.stopPropagation(),
      onchange: (event) => {
        if (event.target.checked) selected.add(job.id); else selected.delete(job.id);
        renderCompare();
      } }) : null;
    return h("tr.clickable", { "data-job": job.id, onclick: () => { location.hash = `#/jobs/${job.id}`; } },
      h("td.select", {}, tick),
      h("td", {}, h("a.mono", { href: `#/jobs/${job.id}` }, job.id)),
      h("td.owner", {}, job.owner),
      h("td", { title: job.scene_hash }, job.scene),
      h("td", {}, job.method),
      h("td", {}, job.sampler),
      h("td.num", {}, job.spp),
      h("td.num", {}, job.depth),
      h("td.num", {}, job.priority),
      h("td", {}, badge(job.status)),
      h("td", {}, progressBar(progressFraction(job), progressLabel(job), job.status)),
      h("td.num.elapsed", {}, fmt.duration(elapsedNow(job))),
      h("td.num.eta", {}, job.status === "done" ? "–" : etaText(job)),
      h("td", { title: job.created }, fmt.time(job.created)));
  }

  function render() {
    renderTabs();
    renderCompare();
    const shown = [...jobs.values()]
      .filter((job) => filter === "all" || job.status === filter)
      .sort((a, b) => (a.created < b.created ? 1 : a.created > b.created ? -1 : 0));
    replace(body, shown.length ? shown.map(row)
      : h("tr", {}, h("td.empty", { colspan: 14 }, filter === "all"
        ? h("span", {}, "No jobs yet. ", may.submit() ? h("a", { href: "#/submit" }, "Submit one.") : null)
        : `No ${filter} jobs.`)));
  }

  function put(job) {
    job._received = Date.now();
    jobs.set(job.id, job);
  }

  async function load() {
    try {
      const list = await api.get(`/jobs?limit=${LIMIT}`);
      jobs.clear();
      list.forEach(put);
      replace(error);
      render();
    } catch (err) {
      replace(error, h("div.error-box", {}, `Could not load the jobs: ${err.message}`));
    }
  }

  let pending = false; // coalesce bursts of events into one render per frame
  function scheduleRender() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; render(); });
  }

  const close = stream("/events", {
    job: (job) => { put(job); scheduleRender(); },
    deleted: ({ job_id }) => { jobs.delete(job_id); scheduleRender(); },
    resync: () => load(),
  }, (state) => { if (state === "open") load(); });
  const ticker = setInterval(() => {
    for (const tr of body.querySelectorAll("tr[data-job]")) {
      const job = jobs.get(tr.dataset.job);
      if (job && job.status === "running") {
        tr.querySelector(".elapsed").textContent = fmt.duration(elapsedNow(job));
        tr.querySelector(".eta").textContent = etaText(job);
      }
    }
  }, 1000);
  load().catch((err) => toast(err.message, true));
  return () => { close(); clearInterval(ticker); };
}
