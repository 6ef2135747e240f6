// The dashboard's entry point: a hash router over its views, the logged-in
// user in the top bar, and a health light.
//   #/login  #/jobs  #/jobs/<id>  #/submit  #/workers  #/experiments  #/experiments/<id>
//   #/compare?jobs=<id>,<id>[&reference=<id>]
// Every view but the login page needs a login; an API answer 401 anywhere
// (api.js raises UNAUTHORIZED) brings the login page, which comes back here.

import { UNAUTHORIZED, api, connectionState } from "./api.js";
import { may, onSessionChange, readOnlyReason, refresh, session, setMe } from "./session.js";
import { h, replace, toast } from "./ui.js";
import { jobsView } from "./views/jobs.js";
import { jobView } from "./views/job.js";
import { holdLoginLink, loginView } from "./views/login.js";
import { submitView } from "./views/submit.js";
import { workersView } from "./views/workers.js";
import { experimentView, experimentsView } from "./views/experiments.js";
import { compareView } from "./views/compare.js";

const LOGIN = /^#\/login(?:\?(.*))?$/;
const routes = [
  [LOGIN, "login", (m) => (root) => loginView(root, new URLSearchParams(m[1] || ""))],
  [/^#?\/?(jobs)?\/?(\?.*)?$/, "jobs", () => jobsView],
  [/^#\/jobs\/([0-9a-f]{6,32})$/, "jobs", (m) => (root) => jobView(root, m[1])],
  [/^#\/submit$/, "submit", () => submitView],
  [/^#\/workers$/, "workers", () => workersView],
  [/^#\/experiments$/, "experiments", () => experimentsView],
  [/^#\/compare\?(.*)$/, "jobs", (m) => (root) => compareView(root, new URLSearchParams(m[1]))],
  [/^#\/experiments\/([0-9a-f]{6,32})$/, "experiments", (m) => (root) => experimentView(root, m[1])],
];

let cleanup = null;

// To the login page, which goes on to `next` afterwards; replaces the history
// entry, so Back does not bounce off the login page.
function toLogin(next, extra = "") {
  location.replace(`#/login?next=${encodeURIComponent(next)}${extra}`);
}

function route() {
  const hash = location.hash || "#/jobs";
  if (!session.me && !LOGIN.test(hash)) {
    toLogin(hash);
    return;
  }
  if (cleanup) { cleanup(); cleanup = null; }
  const root = document.getElementById("view");
  for (const [pattern, nav, view] of routes) {
    const match = pattern.exec(hash);
    if (!match) continue;
    for (const link of document.querySelectorAll("[data-nav]")) {
      link.classList.toggle("active", link.dataset.nav === nav);
    }
    replace(root);
    cleanup = view(match)(root) || null;
    return;
  }
  replace(root, h("div.empty", {}, "No such page. ", h("a", { href: "#/jobs" }, "Back to the jobs.")));
}

// -- the account in the top bar ---------------------------------------------------
function renderAccount(me) {
  document.body.classList.toggle("logged-out", !me);
  const account = document.getElementById("account");
  account.hidden = !me;
  if (!me) { replace(account); return; }
  const logout = h("button.small#logout", { type: "button", title: "end this browser's login" }, "Log out");
  logout.addEventListener("click", async () => {
    logout.disabled = true;
    try {
      await api.logout();
    } catch (err) {
      if (err.status !== 401) { // a 401: the login was over already
        toast(`Log out: ${err.message}`, true);
        logout.disabled = false;
        return;
      }
    }
    setMe(null);
    location.hash = "#/login";
  });
  const reason = readOnlyReason();
  replace(account,
    h("span.who#whoami", { title: reason || `logged in as ${me.user} (${me.role})` },
      h("span.user#whoami-user", {}, me.user),
      h(`span.role.role-${me.role}#whoami-role`, {}, me.role)),
    logout);
  const submitLink = document.querySelector("[data-nav='submit']");
  submitLink.classList.toggle("off", !may.submit());
  submitLink.title = may.submit() ? "" : reason;
}

window.addEventListener(UNAUTHORIZED, () => {
  const was = session.me;
  setMe(null);
  const hash = location.hash || "#/jobs";
  if (!LOGIN.test(hash)) toLogin(hash, was ? "&ended=1" : "");
});

// -- health -------------------------------------------------------------------------
const HEALTH = {}; // the health poll, as a link of the connection banner (api.js)
async function health() {
  const el = document.getElementById("health");
  let report;
  try {
    const response = await fetch("/healthz");
    report = await response.json();
  } catch {
    el.className = "health down";
    el.textContent = "service unreachable";
    connectionState(HEALTH, false);
    return;
  }
  connectionState(HEALTH, true);
  el.className = `health ${report.status}`;
  const parts = [report.executor === "local" ? `local pool · ${report.workers} processes` : "celery"];
  if (report.broker && report.broker !== "ok") parts.push("broker unreachable");
  if ((report.disk && report.disk !== "ok") || report.ledger_writes === "failing") {
    parts.push("disk full: new work refused");
  }
  // Which replica runs the scheduler (service.leader): this one, or another.
  const lead = report.leadership;
  if (lead && lead.role === "leader") parts.push(`scheduler here (${lead.replica})`);
  else if (lead) parts.push(`standby · scheduler on ${lead.holder || "no replica yet"}`);
  if (report.status !== "ok") parts.unshift(report.status);
  el.textContent = parts.join(" · ");
  el.title = JSON.stringify(report, null, 1);
}

// -- tables on a phone ----------------------------------------------------------------
// Below 640 px a table row is a card (app.css): each cell shows its column's
// heading before its value, from a data-label set here for every table.grid
// the views render (once per frame, whatever changed).
let labelling = false;
function labelCells() {
  labelling = false;
  for (const table of document.querySelectorAll("#view table.grid")) {
    const heads = [...table.querySelectorAll("thead th")].map((th) => th.textContent.trim());
    for (const row of table.querySelectorAll("tbody tr")) {
      [...row.children].forEach((cell, i) => {
        if (heads[i] && cell.dataset.label !== heads[i]) cell.dataset.label = heads[i];
      });
    }
  }
}
new MutationObserver(() => {
  if (!labelling) { labelling = true; requestAnimationFrame(labelCells); }
}).observe(document.getElementById("view"), { childList: true, subtree: true });

async function start() {
  // A login link the service did not use by itself (it came from another
  // site, or the browser did not say where from: service/api/routes/dashboard.py):
  // its token leaves the address bar at once, and the login page asks first.
  const link = new URLSearchParams(location.search).get("token");
  if (link !== null) {
    holdLoginLink(link);
    history.replaceState(null, "", "/#/login?link=1");
  }
  onSessionChange(renderAccount);
  try {
    await refresh();
  } catch (err) {
    setMe(null); // the service does not answer: the login page says so when tried
    toast(`Could not ask who is logged in: ${err.message}`, true);
  }
  window.addEventListener("hashchange", route);
  route();
}

start();
health();
setInterval(health, 5000);
window.addEventListener("online", health); // the banner goes as soon as the network is back
