// Several done jobs' convergence on one plot (GET /compare): chosen on the
// jobs list (#/compare?jobs=a,b,c), each pass's error statistic against
// samples and against render seconds; marking one job as the reference
// (&reference=c) plots each one's true RMSE against it instead. The figure
// GET /compare.png draws the same with matplotlib for reports.

import { ApiError, api } from "../api.js";
import { fmt, h, replace } from "../ui.js";
import { curvesPlot } from "../plot.js";

const COLORS = ["#4aa3ff", "#ffb547", "#3ecf8e", "#ff7ab6", "#b48cff", "#5ee0e6", "#ff8f5c", "#c3e86b"];

export function compareView(root, params) {
  const ids = (params.get("jobs") || "").split(",").filter(Boolean);
  const reference = params.get("reference") || "";
  const body = h("div#compare-body", {}, h("p.muted", {}, "Measuring…"));
  replace(root, h("div.page-head", {}, h("a.muted", { href: "#/jobs" }, "← Jobs"),
    h("h1", {}, "Compare jobs")), body);

  function go(ref) {
    location.hash = `#/compare?jobs=${ids.join(",")}${ref ? `&reference=${ref}` : ""}`;
  }

  const query = `jobs=${encodeURIComponent(ids.join(","))}${reference ? `&reference=${reference}` : ""}`;
  api.get(`/compare?${query}`).then((report) => {
    const key = report.reference ? "rmse" : "rel_error";
    const series = (x) => report.jobs.map((job, i) => ({
      label: `${job.id.slice(0, 8)} ${job.label}`, color: COLORS[i % COLORS.length],
      points: job.points.filter((p) => p[key] !== undefined && p[key] !== null).map((p) => [p[x], p[key]]),
    }));
    const what = report.reference ? `RMSE against ${report.reference}` : "error statistic (95th percentile "
      + "of the relative standard error)";
    const bySamples = curvesPlot(series("samples"), { xLabel: "samples", percent: !report.reference,
      label: `${what} against samples` });
    const bySeconds = curvesPlot(series("seconds"), { xLabel: "seconds", percent: !report.reference,
      label: `${what} against render seconds` });
    const rows = report.jobs.map((job, i) => {
      const last = job.points[job.points.length - 1];
      return h("tr", { "data-job": job.id },
        h("td", {}, h("span.sw", { style: { background: COLORS[i % COLORS.length] } }),
          h("a.mono", { href: `#/jobs/${job.id}` }, job.id)),
        h("td", {}, job.label), h("td.num", {}, job.spp), h("td.num", {}, job.points.length),
        h("td.num", {}, fmt.count(last.samples)), h("td.num", {}, fmt.duration(last.seconds)),
        h("td.num", { "data-rel-error": last.rel_error }, last.rel_error === null ? "–"
          : `${(100 * last.rel_error).toPrecision(3)} %`),
        h("td.num", { "data-rmse": last.rmse ?? "" }, last.rmse === undefined ? "–" : last.rmse.toPrecision(4)),
        h("td", {}, h("label.check", {}, h("input", { type: "radio", name: "reference", value: job.id,
          checked: job.id === report.reference, "data-reference": job.id,
          onchange: () => go(job.id) }), "reference")));
    });
    replace(body,
      h("div.panel", {}, h("h2", {}, "Jobs"), h("div.panel-body", {},
        h("table.grid#compare-table", {}, h("thead", {}, h("tr", {}, ["Job", "Method", "spp", "Passes",
          "Samples", "Render time", "Error statistic", "RMSE", ""].map((t) => h("th", {}, t)))),
        h("tbody", {}, rows)),
        h("div.actions", { style: { marginTop: "10px" } },
          report.reference ? h("button.small#compare-no-reference", { type: "button", onclick: () => go("") },
            "No reference") : h("span.muted", {}, "Mark a job as the reference to plot each one's true RMSE against it."),
          h("a.button.small#compare-png", { href: `/compare.png?${query}`, target: "_blank", rel: "noopener" },
            "Figure (PNG)")))),
      h("div.compare-plots", {},
        h("div.panel", {}, h("h2", {}, "Against samples"), h("div.panel-body#plot-samples", {},
          bySamples || h("p.muted", {}, "Nothing to plot."))),
        h("div.panel", {}, h("h2", {}, "Against render time"), h("div.panel-body#plot-seconds", {},
          bySeconds || h("p.muted", {}, "Nothing to plot.")))),
      h("p.muted", {}, report.reference ? "RMSE over every pixel, less the reference's own variance; a job "
        + "against itself is 0 and not drawn." : "Each pass's error statistic, as the job's own convergence log."));
  }).catch((err) => {
    replace(body, h("div.error-box", {}, err instanceof ApiError ? err.message : String(err)));
  });
}
