// The estimator lab: the experiments (GET /experiments) with a form to run a
// new one (POST /experiments), and one experiment's page: its jobs' progress,
// then its measured report — a table per configuration and spp level (bias
// score and verdict, variance, MSE, time, efficiency), the slope and the
// verdicts "unbiased?" and "consistent?", the figures (RMSE and bias against
// spp; bias and variance maps) and the CSV. Polls every two seconds while
// an experiment runs.

import { ApiError, api } from "../api.js";
import { may, readOnlyReason } from "../session.js";
import { badge, fmt, h, progressBar, replace, toast } from "../ui.js";

const POLL_MS = 2000;
const DEFAULT_METHODS = ["path-bsdf", "path-mis", "bdpt", "photon", "raster"];

function num(v, digits = 3) {
  if (v === null || v === undefined) return "–";
  const a = Math.abs(v);
  return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(digits - 1) : v.toPrecision(digits);
}

function verdict(ok, yes, no) {
  if (ok === null || ok === undefined) return h("span.muted", {}, "?");
  return h(`span.verdict.${ok ? "yes" : "no"}`, { "data-verdict": ok ? "yes" : "no" }, ok ? yes : no);
}

function jobsBar(e) {
  const label = `${e.jobs_done}/${e.jobs_total} jobs`;
  return progressBar(e.jobs_total ? e.jobs_done / e.jobs_total : 0, label,
    e.status === "running" ? "running" : e.status);
}

export function experimentsView(root) {
  const body = h("tbody");
  const error = h("div");
  const form = experimentForm();
  replace(root,
    h("div.page-head", {}, h("h1", {}, "Estimator lab"),
      h("span.muted", {}, "the lecture's estimators, measured: bias, variance, convergence")),
    error,
    h("div.lab-layout", {},
      h("div.panel", {}, h("h2", {}, "Experiments"), h("div.panel-body", {},
        h("table.grid#experiments-table", {}, h("thead", {}, h("tr", {},
          ["Experiment", "Owner", "Scene", "Configurations", "spp", "Repeats", "Status", "Jobs",
            "Submitted"].map((t) => h("th", {}, t)))), body))),
      form.el));

  async function load() {
    try {
      const list = await api.get("/experiments");
      replace(error);
      replace(body, list.length ? list.map((e) => h("tr.clickable", {
        "data-experiment": e.id, onclick: () => { location.hash = `#/experiments/${e.id}`; } },
      h("td", {}, h("a.mono", { href: `#/experiments/${e.id}` }, e.id)),
      h("td", {}, e.owner), h("td", {}, e.request.scene),
      h("td", {}, e.request.labels.join(", ")), h("td", {}, e.request.spp.join(", ")),
      h("td.num", {}, e.request.repeats), h("td", {}, badge(e.status)), h("td", {}, jobsBar(e)),
      h("td", { title: e.created }, fmt.time(e.created))))
        : h("tr", {}, h("td.empty", { colspan: 9 }, "No experiments yet.")));
    } catch (err) {
      replace(error, h("div.error-box", {}, `Could not load the experiments: ${err.message}`));
    }
  }
  load();
  const timer = setInterval(load, POLL_MS * 2);
  return () => clearInterval(timer);
}

function experimentForm() {
  const scene = h("select#x-scene", { "aria-label": "scene" });
  const methods = h("div.lab-methods#x-methods");
  const sampler = h("select#x-sampler", { "aria-label": "sampler" });
  const spp = h("input#x-spp", { value: "1, 4, 16, 64", "aria-label": "spp levels" });
  const repeats = h("input#x-repeats", { type: "number", min: 2, max: 64, value: 4, "aria-label": "repeats" });
  const size = h("input#x-size", { type: "number", min: 8, max: 512, value: 32, "aria-label": "image width" });
  const depth = h("input#x-depth", { type: "number", min: 1, max: 64, value: 5, "aria-label": "depth" });
  const reference = h("input#x-reference", { placeholder: "rendered for it (path-mis)", "aria-label": "reference job" });
  const problem = h("div.error#x-error");
  const submit = h("button.primary#x-submit", { type: "submit", disabled: !may.submit(),
    title: may.submit() ? "" : readOnlyReason() }, "Run experiment");
  const field = (label, input, hint) => h("div.field", {}, h("label", {}, label), input,
    hint ? h("div.hint", {}, hint) : null);
  const el = h("form.panel#experiment-form", {}, h("h2", {}, "New experiment"), h("div.panel-body", {},
    field("Scene", scene),
    field("Methods", methods),
    field("Sampler", sampler, "independent (random) samples: plain Monte Carlo falls as 1/√spp"),
    h("div.form-grid", {}, field("spp levels", spp), field("Repeats", repeats), field("Width", size),
      field("Depth", depth)),
    field("Reference job", reference, "a done job of the same scene, size and depth; empty: one is rendered"),
    problem, h("div.actions", {}, submit)));

  Promise.all([api.get("/scenes"), api.get("/methods"), api.get("/samplers")]).then(([scenes, list, samplerList]) => {
    replace(scene, scenes.map((s) => h("option", { value: s.id, selected: s.id === "cornell-box" }, s.name || s.id)));
    const names = [...new Set(list.map((m) => m.name))];
    replace(methods, names.map((name) => h("label.check", {},
      h("input", { type: "checkbox", value: name, checked: DEFAULT_METHODS.includes(name), "data-method": name }), name)));
    replace(sampler, samplerList.map((s) => h("option", { value: s.name, selected: s.name === "random" }, s.name)));
  }).catch((err) => { problem.textContent = `Could not load scenes and methods: ${err.message}`; });

  el.addEventListener("submit", async (event) => {
    event.preventDefault();
    problem.textContent = "";
    const chosen = [...methods.querySelectorAll("input:checked")].map((i) => i.value);
    const width = Number(size.value);
    const body = {
      scene: scene.value, width, height: width, depth: Number(depth.value), repeats: Number(repeats.value),
      spp: spp.value.split(/[\s,]+/).filter(Boolean).map(Number),
      configs: chosen.map((method) => ({ method, sampler: sampler.value })),
    };
    if (reference.value.trim()) body.reference = { job: reference.value.trim() };
    submit.disabled = true;
    try {
      const created = await api.post("/experiments", body);
      toast(`Experiment ${created.id}: ${created.jobs_total} jobs submitted`);
      location.hash = `#/experiments/${created.id}`;
    } catch (err) {
      problem.textContent = err instanceof ApiError ? err.message : String(err);
    } finally {
      submit.disabled = !may.submit();
    }
  });
  return { el };
}

export function experimentView(root, id) {
  const head = h("div.page-head", {}, h("a.muted", { href: "#/experiments" }, "← Lab"),
    h("h1.mono", {}, id));
  const status = h("span");
  const summary = h("div.panel-body#experiment-summary");
  const report = h("div#experiment-report");
  const actions = h("div.actions");
  head.append(status, h("div.spacer"), actions);
  replace(root, head, h("div.panel", {}, h("h2", {}, "Experiment"), summary), report);
  let timer = null;
  let shown = "";

  function kv(pairs) {
    return h("dl.kv", {}, pairs.map(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]));
  }

  function render(e) {
    replace(status, badge(e.status));
    const r = e.request;
    replace(summary, kv([
      ["scene", `${r.scene} · ${r.width}×${r.height} · depth ${r.depth}`],
      ["configurations", r.labels.join(", ")],
      ["spp levels", r.spp.join(", ")], ["repeats", String(r.repeats)],
      ["bias test", `${r.block}×${r.block}-pixel blocks`],
      ["reference", h("a.mono", { href: `#/jobs/${e.reference_job}` }, e.reference_job)],
      ["jobs", jobsBar(e)],
      ["submitted", fmt.time(e.created)], ["finished", e.finished ? fmt.time(e.finished) : "–"],
    ]), e.error ? h("div.error-box", {}, e.error) : null);
    replace(actions, e.status === "running" && may.change({ owner: e.owner }) ? h("button.danger#x-cancel", {
      type: "button", onclick: async () => {
        try { await api.post(`/experiments/${id}/cancel`, {}); toast("Experiment canceled"); } catch (err) {
          toast(`Cancel failed: ${err.message}`, true);
        }
        refresh();
      } }, "Cancel") : null, e.csv_url ? h("a.button#x-csv", { href: e.csv_url }, "CSV") : null);
    if (!e.report) {
      replace(report, e.status === "running" ? h("p.muted", {}, "Measured when every job is done.") : null);
      return;
    }
    const key = e.id + e.status;
    if (key === shown) return;
    shown = key;
    const rows = [];
    for (const c of e.report) {
      c.levels.forEach((l, i) => rows.push(h("tr", { "data-config": c.label, "data-spp": l.spp },
        h("td", {}, i === 0 ? h("strong", {}, c.label) : ""),
        h("td.num", {}, l.spp),
        h("td.num", { title: "pixel blocks whose t test is significant at 5 %, of all; p: the chance of "
          + "that many without bias (under 0.001: biased)" }, `${l.biased_blocks}/${l.blocks} · p ${num(l.bias_p, 2)}`),
        h("td", {}, verdict(l.unbiased, "no bias found", "biased")),
        h("td.num", {}, `${(100 * l.relative_bias).toFixed(2)} %`),
        h("td.num", {}, num(l.variance)), h("td.num", {}, num(l.mse)),
        h("td.num", {}, l.seconds < 1 ? `${num(1000 * l.seconds)} ms` : fmt.duration(l.seconds)),
        h("td.num", {}, num(l.efficiency)),
        h("td.num", {}, i === 0 ? num(c.slope, 2) : ""),
        h("td", {}, i === 0 ? verdict(c.unbiased, "no bias found", "biased") : ""),
        h("td", {}, i === 0 ? verdict(c.consistent, "yes", "no") : ""))));
    }
    replace(report,
      h("div.panel", {}, h("h2", {}, "Report"), h("div.panel-body", {},
        h("table.grid#lab-table", {}, h("thead", {}, h("tr", {}, ["Configuration", "spp", "Significant blocks", "Bias test",
          "Mean bias", "Variance", "MSE", "Time", "Efficiency 1/(MSE·s)", "Slope", "Unbiased?",
          "Consistent?"].map((t) => h("th", {}, t)))), h("tbody", {}, rows)),
        h("p.muted", {}, "Bias test: a t test of the repeats' average against the reference per pixel block "
          + "(luminance); about 5 % of the blocks are significant by chance, and p is the chance of as many "
          + "as seen; biased when p < 0.001. Variance: over the repeats, per pixel. MSE: against the "
          + "reference, less its own variance. Slope: log RMSE against log spp (−0.5 for plain Monte Carlo). "
          + "Consistent: no bias found, or a bias that still falls at the last spp step. \"No bias found\" is "
          + "a measurement at this size and these repeats: a bias smaller than their noise (photon "
          + "mapping's blur at its default radius) needs more repeats or larger blocks to show."))),
      h("div.lab-figures", {},
        h("div.panel", {}, h("h2", {}, "Convergence and bias"), h("div.panel-body", {},
          h("img#lab-plot", { src: e.plot_url, alt: "RMSE and bias score against spp" }))),
        h("div.panel", {}, h("h2", {}, "Bias and variance maps"), h("div.panel-body", {},
          h("img#lab-maps", { src: e.maps_url, alt: "bias and variance maps at the largest spp" })))));
  }

  async function refresh() {
    try {
      const e = await api.get(`/experiments/${id}`);
      render(e);
      if (e.status !== "running" && timer) { clearInterval(timer); timer = null; }
    } catch (err) {
      replace(summary, h("div.error-box", {}, err instanceof ApiError && err.status === 404
        ? `There is no experiment ${id}.` : `Could not load experiment ${id}: ${err.message}`));
    }
  }
  refresh();
  timer = setInterval(refresh, POLL_MS);
  return () => { if (timer) clearInterval(timer); };
}
