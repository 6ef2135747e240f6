// The workers: every Celery worker node (or the embedded pool) with its state,
// the units it renders, what it has done and when it was last heard from.
// Polls GET /workers every two seconds. Admins drain (disable) and enable a
// worker, and remove a lost or offline one (POST /workers/{name}/disable|enable,
// DELETE /workers/{name}).

import { api } from "../api.js";
import { session } from "../session.js";
import { badge, fmt, h, replace, toast } from "../ui.js";

const POLL_MS = 2000;

export function workersView(root) {
  const body = h("tbody");
  const note = h("div.muted", { style: { margin: "10px 2px", fontSize: "12.5px" } });
  const error = h("div");
  replace(root,
    h("div.page-head", {}, h("h1", {}, "Workers")),
    error,
    h("div.panel", {}, h("table.grid#workers-table", {},
      h("thead", {}, h("tr", {}, ["Worker", "Kind", "State", "Processes", "Rendering", "Units done",
        "Samples", "Samples/s per process", "Render time", "Up since", "Last seen", ""].map((t, i) =>
        h(i >= 5 && i <= 8 ? "th.num" : "th", {}, t)))),
      body)),
    note);

  function rendering(worker) {
    if (!worker.running.length) return h("span.muted", {}, "–");
    return h("span", {}, worker.running.map((r, i) => [i ? ", " : "",
      h("a.mono", { href: `#/jobs/${r.job_id}`, title: r.since ? `since ${fmt.time(r.since)}` : "" },
        `${r.job_id}/${r.index}`)]));
  }

  function lastSeen(worker) {
    if (worker.kind === "local") return "now (in the service)";
    return worker.silent_seconds < 1.5 ? "just now" : `${fmt.duration(worker.silent_seconds)} ago`;
  }

  const isAdmin = () => !!session.me && session.me.role === "admin";
  const path = (w) => `/workers/${encodeURIComponent(w.name)}`;

  async function act(what, call) {
    try {
      await call();
      toast(what);
    } catch (err) {
      toast(`${what} failed: ${err.message}`, true);
    }
    refresh();
  }

  // An admin's buttons: drain or enable a live worker, remove one that is gone.
  function actions(w) {
    if (!isAdmin()) return h("td", {});
    const gone = w.state === "lost" || w.state === "offline";
    return h("td", {},
      gone && w.kind !== "local" ? h("button.small", {
        "data-action": "remove", title: "forget this worker (it no longer beats)",
        onclick: () => act(`Removed ${w.name}`, () => api.del(path(w))),
      }, "Remove") : null,
      !gone ? h("button.small", {
        "data-action": w.disabled ? "enable" : "disable",
        title: w.disabled ? "let it take units again"
          : "drain: it finishes the units it renders and takes no new ones",
        onclick: () => act(`${w.disabled ? "Enabled" : "Disabled"} ${w.name}`,
          () => api.post(`${path(w)}/${w.disabled ? "enable" : "disable"}`)),
      }, w.disabled ? "Enable" : "Disable") : null);
  }

  async function refresh() {
    let workers;
    try {
      workers = await api.get("/workers");
      replace(error);
    } catch (err) {
      replace(error, h("div.error-box", {}, `Could not load the workers: ${err.message}`));
      return;
    }
    const order = { busy: 0, idle: 1, lost: 2, offline: 3 };
    workers.sort((a, b) => order[a.state] - order[b.state] || a.name.localeCompare(b.name));
    replace(body, workers.length ? workers.map((w) => h("tr", { "data-worker": w.name, "data-state": w.state,
      "data-disabled": w.disabled ? "yes" : "no" },
      h("td.mono", { title: w.host }, w.name),
      h("td", {}, w.kind === "local" ? "local pool" : "celery"),
      h("td", {}, badge(w.state), w.disabled ? [" ", badge("disabled")] : null),
      h("td.num", {}, w.concurrency),
      h("td", {}, rendering(w)),
      h("td.num", {}, w.units_done.toLocaleString()),
      h("td.num", {}, fmt.count(w.samples)),
      h("td.num", {}, fmt.rate(w.samples_per_second)),
      h("td.num", {}, fmt.duration(w.seconds)),
      h("td", { title: w.started || "" }, fmt.time(w.started)),
      h("td", {}, lastSeen(w)),
      actions(w)))
      : h("tr", {}, h("td.empty", { colspan: 12 },
        "No worker has reported yet. Start one with: rayfarm worker (RAYFARM_BROKER_URL set)")));
    const lost = workers.filter((w) => w.state === "lost").length;
    replace(note, `${workers.length} worker${workers.length === 1 ? "" : "s"}`,
      lost ? ` · ${lost} lost (no heartbeat; killed or cut off — the units they rendered were enqueued again)` : "",
      ` · refreshed every ${POLL_MS / 1000} s`);
  }

  refresh();
  const timer = setInterval(refresh, POLL_MS);
  return () => clearInterval(timer);
}
