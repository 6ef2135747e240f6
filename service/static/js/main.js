// The dashboard's entry point: a hash router over four views and a health light.
//   #/jobs  #/jobs/<id>  #/submit  #/workers

import { h, replace } from "./ui.js";
import { jobsView } from "./views/jobs.js";
import { jobView } from "./views/job.js";
import { submitView } from "./views/submit.js";
import { workersView } from "./views/workers.js";

const routes = [
  [/^#?\/?(jobs)?\/?$/, "jobs", () => jobsView],
  [/^#\/jobs\/([0-9a-f]{6,32})$/, "jobs", (m) => (root) => jobView(root, m[1])],
  [/^#\/submit$/, "submit", () => submitView],
  [/^#\/workers$/, "workers", () => workersView],
];

let cleanup = null;

function route() {
  const hash = location.hash || "#/jobs";
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

async function health() {
  const el = document.getElementById("health");
  let report;
  try {
    const response = await fetch("/healthz");
    report = await response.json();
  } catch {
    el.className = "health down";
    el.textContent = "service unreachable";
    return;
  }
  el.className = `health ${report.status}`;
  const parts = [report.executor === "local" ? `local pool · ${report.workers} processes` : "celery"];
  if (report.broker && report.broker !== "ok") parts.push("broker unreachable");
  if (report.status !== "ok") parts.unshift(report.status);
  el.textContent = parts.join(" · ");
  el.title = JSON.stringify(report, null, 1);
}

window.addEventListener("hashchange", route);
route();
health();
setInterval(health, 5000);
