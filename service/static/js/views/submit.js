// The submit form. Scenes, methods (with their options) and samplers come
// from the API (GET /scenes, /methods, /samplers): no second list lives here.
// The service validates; its 422 messages are shown next to their fields.

import { ApiError, api } from "../api.js";
import { may, readOnlyReason } from "../session.js";
import { h, replace, toast } from "../ui.js";

const NUMBER_FIELDS = [
  // [name, label, default, hint]
  ["spp", "Samples per pixel", 16, "per pixel, over all passes"],
  ["depth", "Max depth", "", "surface bounces, 1 = direct light; blank: the scene's"],
  ["width", "Width", "", "blank: the scene camera's"],
  ["height", "Height", "", "blank: the scene camera's"],
  ["tile_size", "Tile size", 32, "pixels per side of a work unit"],
  ["seed", "Seed", 0, "same seed, same pixels"],
  ["priority", "Priority", 0, "-100 … 100, higher runs first"],
];

const THUMB_POLL_MS = 1000;

export function submitView(root) {
  let scenes = [];
  let thumbTimer = null;
  let methods = [];
  const form = h("form#submit-form", { novalidate: true });
  const formError = h("div#form-error");
  // A viewer may look at the registries, not submit or upload: it is told so.
  const readOnly = may.submit() ? null : h("div.notice#read-only-note", {},
    `${readOnlyReason()}. Submitting and uploading need an artist's or an admin's token.`);
  replace(root, h("div.page-head", {}, h("h1", {}, "New render job")), readOnly, formError, form);

  const field = (name, label, control, hint) => h("div.field", { "data-field": name },
    h("label", { for: `f-${name}` }, label), control, hint ? h("span.hint", {}, hint) : null,
    h("span.error", { "data-error-for": name, role: "alert" }));

  // -- controls ---------------------------------------------------------------
  const sceneSelect = h("select#f-scene", { name: "scene" });
  const thumb = h("div.scene-thumb#scene-thumb", {}, "no preview");
  const sceneInfo = h("div.muted#scene-info", { style: { fontSize: "12.5px" } });
  // Three ways in: a scene file with the files it names (their base names),
  // one archive of its folder, or a folder (each file sent with its path).
  const upload = h("input#f-upload", { type: "file", multiple: true,
    "aria-label": "a scene file with its files, or an archive of its folder" });
  const uploadFolder = h("input#f-upload-folder", { type: "file", webkitdirectory: true,
    multiple: true, "aria-label": "a scene's folder" });
  const mainName = h("input#f-main", { type: "text", name: "main",
    placeholder: "e.g. scene.xml or living-room/scene.xml" });
  const mainField = h("div.field", { "data-field": "main", hidden: true },
    h("label", { for: "f-main" }, "Main scene file"), mainName,
    h("span.hint", {}, "the folder or archive holds several scene files: name the one to render"),
    h("span.error", { "data-error-for": "main", role: "alert" }));
  const uploadButton = h("button#upload-button", { type: "button" }, "Upload");
  const sceneReport = h("div#scene-report");
  const methodSelect = h("select#f-method", { name: "method" });
  const methodDoc = h("div.method-doc#method-doc");
  const optionsBox = h("div.form-grid#method-options");
  const samplerSelect = h("select#f-sampler", { name: "sampler" });
  const samplerDoc = h("div.method-doc#sampler-doc");
  const numbers = Object.fromEntries(NUMBER_FIELDS.map(([name, , value]) =>
    [name, h(`input#f-${name}`, { type: "number", name, value, step: 1 })]));
  const progressive = h("input#f-progressive", { type: "checkbox", checked: true });
  const denoise = h("input#f-denoise", { type: "checkbox" });
  // A noise target in percent (blank: a fixed spp); spp is then the ceiling.
  const target = h("input#f-target", { type: "number", name: "target", step: "any", min: 0,
    placeholder: "blank: render exactly spp" });
  const submit = h("button.primary#submit-button", { type: "submit" }, "Submit job");

  replace(form, h("div.submit-layout", {},
    h("div.panel", {}, h("h2", {}, "Scene"), h("div.panel-body.scene-card", {},
      field("scene", "Scene", sceneSelect), thumb, sceneInfo, sceneReport,
      h("div.field", { "data-field": "upload" }, h("label", { for: "f-upload" },
        "Upload a scene: a file (.json, Mitsuba .xml, .gltf, .glb) with the files it names, "
        + "or an archive of its folder (.zip, .tar.gz)"), upload,
      h("label", { for: "f-upload-folder" }, "… or its folder"), uploadFolder,
      h("div.actions", {}, uploadButton),
      h("span.error", { "data-error-for": "upload", role: "alert" })), mainField)),
    h("div", {},
      h("div.panel.form-section", {}, h("h2", {}, "Method"), h("div.panel-body", {},
        h("div.form-grid", {}, field("method", "Method", methodSelect), field("sampler", "Pixel sampler", samplerSelect)),
        methodDoc, samplerDoc, h("div", { style: { height: "10px" } }), optionsBox)),
      h("div.panel.form-section", {}, h("h2", {}, "Render"), h("div.panel-body", {},
        h("div.form-grid", {}, NUMBER_FIELDS.map(([name, label, , hint]) => field(name, label, numbers[name], hint))),
        h("div", { style: { height: "12px" } }),
        field("progressive", "Passes", h("label.check", {}, progressive,
          "progressive: passes that double up to 64 spp each, the preview sharpens while it runs")),
        field("denoise", "Denoise", h("label.check", {}, denoise,
          "also denoise the finished frame (Open Image Denoise; biased, the raw image is kept)")),
        field("target", "Noise target (%)", target,
          "stop when 95 % of the lit pixels have a relative standard error below this; spp is "
          + "then the most per pixel (tile methods only)"))),
      h("div.actions", {}, submit, h("span.muted", {}, "The service checks every field.")))));
  if (!may.submit()) {
    for (const control of [submit, uploadButton, upload, uploadFolder]) {
      control.disabled = true;
      control.title = readOnlyReason();
    }
  }

  // -- registries --------------------------------------------------------------
  function renderScenes(selected) {
    replace(sceneSelect, scenes.map((s) => h("option", { value: s.id ?? s.name,
      selected: (s.id ?? s.name) === selected }, s.kind === "uploaded" ? `${s.name} (uploaded)` : s.name)));
    showScene();
  }

  function showScene() {
    const scene = scenes.find((s) => (s.id ?? s.name) === sceneSelect.value);
    if (!scene) return;
    numbers.width.placeholder = scene.width;
    numbers.height.placeholder = scene.height;
    // An imported file's own depth (veach-bidir's 6) is what a blank field renders.
    numbers.depth.placeholder = scene.default_depth ?? "";
    replace(sceneInfo, `${scene.width} × ${scene.height}`,
      scene.triangles ? ` · ${scene.triangles.toLocaleString()} triangles` : "",
      scene.source ? ` · from ${scene.source}` : "",
      scene.description ? h("div", {}, scene.description) : null);
    showReport(scene);
    clearTimeout(thumbTimer);
    if (scene.thumbnail_url) {
      const img = h("img", { alt: `${scene.name} thumbnail` });
      img.onerror = () => replace(thumb, "no thumbnail");
      img.src = scene.thumbnail_url;
      replace(thumb, img);
      return;
    }
    // Thumbnails are rendered in the background: ask again until this one is there.
    replace(thumb, "rendering a thumbnail…");
    const id = scene.id ?? scene.name;
    thumbTimer = setTimeout(() => api.get(`/scenes/${encodeURIComponent(id)}`).then((fresh) => {
      const i = scenes.findIndex((x) => (x.id ?? x.name) === id);
      if (i >= 0) scenes[i] = fresh;
      if (sceneSelect.value === id) showScene();
    }).catch(() => replace(thumb, "no thumbnail")), THUMB_POLL_MS);
  }

  // An upload's import report: what its files ask for that is not rendered as written.
  function showReport(scene) {
    const report = scene.report || [];
    if (scene.kind !== "uploaded") return replace(sceneReport);
    if (!report.length) {
      return replace(sceneReport, h("div.muted.report-ok", { style: { fontSize: "12.5px" } },
        "Imported as written: the import report is empty."));
    }
    const where = (e) => (e.file || "") + (e.line !== null && e.line !== undefined ? `:${e.line}` : "");
    replace(sceneReport, h("details.import-report", { open: report.length <= 8 },
      h("summary", {}, `Import report: ${report.length} element${report.length === 1 ? "" : "s"} `
        + "not rendered as written"),
      h("table.report-table", {}, h("thead", {}, h("tr", {}, h("th", {}, "where"),
        h("th", {}, "element"), h("th", {}, "what was done"))),
      h("tbody", {}, report.map((e) => h("tr", {}, h("td", {}, where(e)), h("td", {}, e.element),
        h("td", {}, e.action)))))));
  }

  function renderMethods() {
    replace(methodSelect, methods.map((m) => h("option", { value: m.name, selected: m.name === "path-mis" },
      m.aliases && m.aliases.length ? `${m.name} (${m.aliases.join(", ")})` : m.name)));
    showMethod();
  }

  function showMethod() {
    const method = methods.find((m) => m.name === methodSelect.value);
    if (!method) return;
    replace(methodDoc, h("b", {}, `${method.name}: `), method.description);
    replace(optionsBox, method.options.map((o) => {
      let control;
      if (o.choices) {
        control = h(`select#f-opt-${o.name}`, { "data-option": o.name },
          o.choices.map((c) => h("option", { value: c, selected: c === o.default }, String(c))));
      } else if (o.type === "bool") {
        control = h(`input#f-opt-${o.name}`, { type: "checkbox", checked: !!o.default, "data-option": o.name });
      } else {
        control = h(`input#f-opt-${o.name}`, { type: o.type === "str" ? "text" : "number",
          step: o.type === "float" ? "any" : 1, min: o.bounds?.[0], max: o.bounds?.[1],
          value: o.default, "data-option": o.name,
          "data-type": o.type });
      }
      return field(`options.${o.name}`, `${o.name}`, control, o.description);
    }));
  }

  function renderSamplers(samplers) {
    replace(samplerSelect, samplers.map((s) => h("option", { value: s.name, "data-doc": s.description,
      selected: Boolean(s.default) }, s.name)));
    const showDoc = () => replace(samplerDoc, samplerSelect.selectedOptions[0]
      ? [h("b", {}, `${samplerSelect.value}: `), samplerSelect.selectedOptions[0].dataset.doc] : "");
    samplerSelect.addEventListener("change", showDoc);
    showDoc();
  }

  sceneSelect.addEventListener("change", showScene);
  methodSelect.addEventListener("change", showMethod);

  Promise.all([api.get("/scenes"), api.get("/methods"), api.get("/samplers")]).then(([s, m, samplers]) => {
    scenes = s;
    methods = m;
    renderScenes(scenes.some((x) => (x.id ?? x.name) === "cornell-box") ? "cornell-box" : undefined);
    renderMethods();
    renderSamplers(samplers);
  }).catch((err) => replace(formError, h("div.error-box", {}, `Could not load the registries: ${err.message}`)));

  // -- errors ------------------------------------------------------------------
  function clearErrors() {
    replace(formError);
    for (const el of form.querySelectorAll("[data-error-for]")) el.textContent = "";
    for (const el of form.querySelectorAll(".field.invalid")) el.classList.remove("invalid");
  }

  function showErrors(err) {
    const unplaced = [];
    for (const [name, message] of Object.entries(err.fields)) {
      const slot = form.querySelector(`[data-error-for="${CSS.escape(name)}"]`)
        || (name.startsWith("options.") && form.querySelector(`[data-error-for="method"]`));
      if (slot) {
        slot.textContent = message;
        slot.closest(".field").classList.add("invalid");
      } else unplaced.push(message);
    }
    if (!Object.keys(err.fields).length) unplaced.push(err.message);
    if (unplaced.length) replace(formError, h("div.error-box", {}, unplaced.join("\n")));
    const first = form.querySelector(".field.invalid input, .field.invalid select");
    if (first) first.focus();
  }

  // -- upload ------------------------------------------------------------------
  const SCENE = /\.(json|xml|gltf|glb)$/i;
  const ARCHIVE = /\.(zip|tar|tgz|tar\.gz|tbz2|tar\.bz2|txz|tar\.xz)$/i;
  // One input at a time: choosing files forgets the folder, and back.
  upload.addEventListener("change", () => { uploadFolder.value = ""; });
  uploadFolder.addEventListener("change", () => { upload.value = ""; });

  function uploadForm(slot) {
    const data = new FormData();
    const folder = [...uploadFolder.files];
    if (folder.length) {
      // A folder: every file with its path; the service finds the scene file.
      for (const f of folder) data.append("files", f, f.webkitRelativePath || f.name);
    } else {
      const files = [...upload.files];
      const archive = files.length === 1 && ARCHIVE.test(files[0].name) ? files[0] : null;
      const scenesChosen = files.filter((f) => SCENE.test(f.name));
      if (!archive && scenesChosen.length !== 1) {
        slot.textContent = scenesChosen.length
          ? `choose one scene file (chosen: ${scenesChosen.map((f) => f.name).join(", ")}), `
            + "or its folder"
          : "choose a scene file (.json, .xml, .gltf, .glb) and the files it names, an archive "
            + "of its folder, or the folder";
        slot.closest(".field").classList.add("invalid");
        return null;
      }
      data.append("scene", archive || scenesChosen[0]);
      for (const f of files) if (f !== archive && f !== scenesChosen[0]) data.append("files", f);
    }
    if (!mainField.hidden && mainName.value.trim()) data.append("main", mainName.value.trim());
    return data;
  }

  uploadButton.addEventListener("click", async () => {
    clearErrors();
    const slot = form.querySelector('[data-error-for="upload"]');
    const data = uploadForm(slot);
    if (!data) return;
    uploadButton.disabled = true;
    try {
      const record = await api.upload("/scenes", data);
      scenes = await api.get("/scenes");
      renderScenes(record.id);
      const notes = (record.report || []).length;
      toast(`Scene ${record.name} uploaded` + (notes ? ` (import report: ${notes})` : ""));
      upload.value = "";
      uploadFolder.value = "";
      mainName.value = "";
      mainField.hidden = true;
    } catch (err) {
      const fields = err instanceof ApiError ? err.fields : {};
      if (fields.main) {
        // Several scene files at the top of the folder or archive: ask which.
        mainField.hidden = false;
        const mainSlot = form.querySelector('[data-error-for="main"]');
        mainSlot.textContent = fields.main;
        mainField.classList.add("invalid");
        mainName.focus();
        return;
      }
      const messages = Object.keys(fields).length ? Object.values(fields).join("\n") : err.message;
      slot.textContent = err.status === 413 ? `too large: ${messages}` : messages;
      slot.closest(".field").classList.add("invalid");
    } finally {
      uploadButton.disabled = !may.submit();
    }
  });

  // -- submit ------------------------------------------------------------------
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    clearErrors();
    const body = { scene: sceneSelect.value, method: methodSelect.value, sampler: samplerSelect.value,
      progressive: progressive.checked, denoise: denoise.checked, options: {} };
    for (const [name] of NUMBER_FIELDS) {
      const raw = numbers[name].value.trim();
      if (raw !== "") body[name] = Number(raw);
      else if (numbers[name].validity.badInput) body[name] = numbers[name].value; // let the API say why
    }
    const percent = target.value.trim();
    if (percent !== "") body.target = { rel_error: Number(percent) / 100 };
    for (const control of optionsBox.querySelectorAll("[data-option]")) {
      const name = control.dataset.option;
      if (control.type === "checkbox") body.options[name] = control.checked;
      else if (control.dataset.type === "int" || control.dataset.type === "float") body.options[name] = Number(control.value);
      else body.options[name] = control.value;
    }
    submit.disabled = true;
    try {
      const job = await api.post("/jobs", body);
      toast(`Job ${job.id} submitted`);
      location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      if (err instanceof ApiError && err.status === 422) showErrors(err);
      else replace(formError, h("div.error-box", {}, `Submit failed: ${err.message}`));
    } finally {
      submit.disabled = !may.submit();
    }
  });
  return () => clearTimeout(thumbTimer);
}
