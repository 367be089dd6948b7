// splatmark console: a small single-page app over the /v1 API. No framework, no build step:
// everything the browser runs is this file (served from the binary), and every value shown is
// inserted as text, never as HTML.
"use strict";

const KEY = "splatmark.api_key";
const main = () => document.getElementById("main");

// ---------- helpers ----------

/** Element `tag` with attributes (on* keys become listeners) and children (strings are text). */
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "text") el.textContent = v;
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat(Infinity)) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

function card(title, ...children) {
  return h("section", { class: "card" }, title ? h("h2", {}, title) : null, ...children);
}

function show(...nodes) {
  const m = main();
  m.replaceChildren(...nodes);
}

function key() { return sessionStorage.getItem(KEY); }

class ApiError extends Error {
  constructor(status, problem) {
    super((problem && (problem.detail || problem.title)) || `HTTP ${status}`);
    this.status = status;
  }
}

/** Calls the API with the session's key; JSON in and out unless `raw`. */
async function api(path, { method = "GET", body, json, raw } = {}) {
  const headers = { Authorization: `Bearer ${key()}` };
  if (json !== undefined) { headers["Content-Type"] = "application/json"; body = JSON.stringify(json); }
  const r = await fetch(path, { method, headers, body });
  if (!r.ok) {
    let p = null;
    try { p = await r.json(); } catch (_) { /* not a problem document */ }
    if (r.status === 401) { sessionStorage.removeItem(KEY); }
    throw new ApiError(r.status, p);
  }
  if (raw) return r;
  return r.status === 204 ? null : r.json();
}

function errorBox(e) { return h("p", { class: "error", role: "alert", text: `Error: ${e.message}` }); }

function fmtBytes(n) {
  if (n >= 1 << 20) return `${(n / (1 << 20)).toFixed(1)} MiB`;
  if (n >= 1 << 10) return `${(n / (1 << 10)).toFixed(1)} KiB`;
  return `${n} B`;
}

function fmtP(p) { return p === undefined || p === null ? "–" : p < 1e-3 ? p.toExponential(2) : p.toFixed(4); }

/** Offers `blob` as a download named `name`. */
function download(blob, name) {
  const url = URL.createObjectURL(blob);
  const a = h("a", { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ---------- sign-in ----------

function signIn(next) {
  const input = h("input", { type: "password", id: "api-key", autocomplete: "off", placeholder: "API key" });
  const out = h("div");
  const form = h("form", {
    id: "signin-form",
    onsubmit: async (ev) => {
      ev.preventDefault();
      sessionStorage.setItem(KEY, input.value.trim());
      try {
        await api("/v1/assets?limit=1");
        location.hash = next && next !== "#/signin" ? next : "#/assets";
        route();
      } catch (e) {
        sessionStorage.removeItem(KEY);
        out.replaceChildren(errorBox(e));
      }
    },
  }, h("label", {}, "API key ", input), h("button", { type: "submit", id: "signin" }, "Sign in"), out);
  show(card("Sign in", h("p", { class: "muted" },
    "Paste an API key (the server's bootstrap admin token, or a key an admin created). It is kept in this tab's session storage only."), form));
  input.focus();
}

// ---------- assets ----------

async function assetsPage() {
  const list = h("div", {}, h("p", { class: "muted" }, "Loading…"));
  const progress = h("progress", { id: "upload-progress", max: 100, value: 0, hidden: true });
  const status = h("div", { id: "upload-status" });
  const scene = h("input", { type: "file", id: "upload-scene", accept: ".ply,.splat,.spz,.sog" });
  const cams = h("input", { type: "file", id: "upload-cameras", accept: ".json,.npy" });
  const form = h("form", {
    id: "upload-form",
    onsubmit: (ev) => {
      ev.preventDefault();
      if (!scene.files.length) { status.replaceChildren(errorBox(new Error("choose a scene file"))); return; }
      const fd = new FormData();
      fd.append("scene", scene.files[0]);
      if (cams.files.length) fd.append("cameras", cams.files[0]);
      // XMLHttpRequest reports upload progress; fetch does not.
      const xhr = new XMLHttpRequest();
      xhr.open("POST", "/v1/assets");
      xhr.setRequestHeader("Authorization", `Bearer ${key()}`);
      progress.hidden = false;
      xhr.upload.onprogress = (e) => {
        if (e.lengthComputable) {
          progress.value = (100 * e.loaded) / e.total;
          status.textContent = `Uploading ${fmtBytes(e.loaded)} of ${fmtBytes(e.total)}`;
        }
      };
      xhr.onerror = () => status.replaceChildren(errorBox(new Error("the upload failed (network)")));
      xhr.onload = () => {
        let body = null;
        try { body = JSON.parse(xhr.responseText); } catch (_) { /* empty */ }
        if (xhr.status === 201) {
          status.replaceChildren("Stored: ", h("a", { href: `#/asset/${body.id}`, id: "uploaded-link" }, body.id));
          progress.value = 100;
          loadList();
        } else {
          status.replaceChildren(errorBox(new ApiError(xhr.status, body)));
        }
      };
      xhr.send(fd);
    },
  }, h("label", {}, "Scene (.ply, compressed .ply, .splat, .spz, bundled .sog) ", scene),
     h("label", {}, "Cameras (optional: cameras.json, transforms.json, poses_bounds.npy) ", cams),
     h("button", { type: "submit", id: "upload" }, "Upload"), progress, status);

  async function loadList() {
    try {
      const page = await api("/v1/assets?limit=100");
      if (!page.items.length) { list.replaceChildren(h("p", { class: "muted" }, "No assets yet.")); return; }
      list.replaceChildren(h("table", { id: "asset-table" },
        h("tr", {}, ["asset", "kind", "file", "Gaussians", "format", "created"].map((t) => h("th", {}, t))),
        page.items.map((a) => h("tr", {},
          h("td", { class: "mono" }, h("a", { href: `#/asset/${a.id}` }, a.id)),
          h("td", {}, a.kind), h("td", {}, a.file_name || "–"), h("td", {}, a.gaussians.toLocaleString()),
          h("td", {}, a.format), h("td", {}, a.created_at)))));
    } catch (e) { list.replaceChildren(errorBox(e)); }
  }
  show(card("Upload a scene", form), card("Assets", list));
  loadList();
}

// ---------- jobs ----------

/** A live panel of job `id`: state, phase, step / total, ETA; polls until the job ends. */
function jobPanel(id) {
  const bar = h("progress", { max: 1, value: 0, id: "job-progress" });
  const line = h("p", { id: "job-status" }, "Queued…");
  const result = h("div", { id: "job-result" });
  const cancel = h("button", { class: "secondary", type: "button", onclick: async () => {
    try { await api(`/v1/jobs/${id}`, { method: "DELETE" }); } catch (e) { result.replaceChildren(errorBox(e)); }
  } }, "Cancel");
  const panel = card(`Job ${id}`, bar, line, cancel, result);
  let started = false;
  async function poll() {
    // Stop once the panel has left the page (another page was opened).
    if (started && !panel.isConnected) return;
    started = true;
    try {
      const j = await api(`/v1/jobs/${id}`);
      bar.max = j.total || 1;
      bar.value = j.step || 0;
      const eta = j.eta_seconds != null ? ` · ETA ${Math.round(j.eta_seconds)} s` : "";
      line.textContent = `${j.state}${j.phase ? ` · ${j.phase}` : ""} · step ${j.step || 0} of ${j.total || "?"}${eta}` +
        (j.attempts > 1 ? ` · attempt ${j.attempts} of ${j.max_attempts}` : "");
      line.dataset.state = j.state;
      if (j.state === "done") {
        cancel.remove();
        bar.value = bar.max;
        result.replaceChildren("Watermarked asset: ",
          h("a", { href: `#/asset/${j.result_asset_id}`, id: "job-result-link" }, j.result_asset_id));
        return;
      }
      if (["failed", "dead", "cancelled"].includes(j.state)) {
        cancel.remove();
        if (j.error) result.replaceChildren(h("p", { class: "error", text: j.error }));
        return;
      }
    } catch (e) { result.replaceChildren(errorBox(e)); }
    setTimeout(poll, 1000);
  }
  setTimeout(poll, 0);
  return panel;
}

/** The jobs started on `asset`, newest first; "watch" opens a job's live panel in `where` (a
 * queued or running one opens there by itself), so a job can be found again after leaving. */
function jobsList(asset, where) {
  const list = h("div", { id: "job-list" }, h("p", { class: "muted" }, "Loading…"));
  api(`/v1/assets/${asset.id}/jobs`).then(({ jobs }) => {
    if (!jobs.length) { list.replaceChildren(h("p", { class: "muted" }, "No job yet.")); return; }
    list.replaceChildren(h("table", { id: "jobs-table" },
      h("tr", {}, ["started", "state", "payload", "progress", ""].map((t) => h("th", {}, t))),
      jobs.map((j) => h("tr", {},
        h("td", {}, j.created_at), h("td", { "data-state": j.state }, j.state), h("td", {}, `${j.bits} bits`),
        h("td", {}, `step ${j.step || 0} of ${j.total || "?"}`),
        h("td", {}, j.result_asset_id ? h("a", { href: `#/asset/${j.result_asset_id}` }, "result") : null, " ",
          h("button", { type: "button", class: "secondary", onclick: () => where.replaceChildren(jobPanel(j.id)) }, "watch"))))));
    const live = jobs.find((j) => j.state === "queued" || j.state === "running");
    if (live && !where.firstChild) where.replaceChildren(jobPanel(live.id));
  }).catch((e) => list.replaceChildren(errorBox(e)));
  return card("Jobs", list);
}

function watermarkForm(asset, where) {
  const bits = h("select", { id: "wm-bits" }, [32, 48, 64].map((b) => h("option", { value: b }, `${b} bits`)));
  const steps = h("input", { type: "text", id: "wm-steps", placeholder: "default (350)", inputmode: "numeric" });
  const options = h("textarea", { id: "wm-options", rows: 3, cols: 60, placeholder: '{"orbit": {"count": 24, "width": 512, "height": 512}}' });
  const out = h("div");
  return card("Watermark this scene", h("form", {
    id: "wm-form",
    onsubmit: async (ev) => {
      ev.preventDefault();
      const json = { bits: Number(bits.value) };
      try {
        if (options.value.trim()) json.options = JSON.parse(options.value);
      } catch (e) { out.replaceChildren(errorBox(new Error(`the options are not JSON: ${e.message}`))); return; }
      if (steps.value.trim()) json.options = { ...(json.options || {}), steps: Number(steps.value) };
      try {
        const j = await api(`/v1/assets/${asset.id}/watermark`, { method: "POST", json });
        where.replaceChildren(jobPanel(j.id));
      } catch (e) { out.replaceChildren(errorBox(e)); }
    },
  }, h("p", { class: "muted" }, "The message is drawn at random and sealed with the key; the job trains on orbit views (or the cameras uploaded with the scene)."),
     h("label", {}, "Payload ", bits), h("label", {}, "Steps ", steps),
     h("details", {}, h("summary", { id: "wm-advanced" }, "Advanced: job options (JSON, as in the API's watermark request)"), options),
     h("button", { type: "submit", id: "wm-start" }, "Start job"), out));
}

// ---------- asset page and attribution viewer ----------

const WHY = [
  ["role", "Carrier: holds the watermark (takes only L_wm). Compensator: a split child that repairs what the carrier changes (takes only L_vis). Untouched: neither."],
  ["r", "R₁ geometric stability · R₂ appearance safety · R₃ redundancy certainty (the Trio-Experts' reliabilities, 0–1)"],
  ["uncertainty", "U₁..U₃: each expert's uncertainty"],
  ["quality", "S₁..S₃: each expert's quality score"],
  ["utility", "u = (R₁R₂R₃)^⅓, the score SBAG ranks carriers by"],
  ["visibility", "v: how much the training views see it"],
  ["feasible", "whether its parent was in SBAG's feasible set"],
  ["seed", "true: picked in the top-B seed set WM₀; false: added by proximity"],
  ["mask_wm", "channel mask on the watermark route (dc, rest, opacity, rotation, scale)"],
  ["mask_vis", "channel mask on the visual route (same order)"],
  ["parent", "its Gaussian in the scene as uploaded (child 0 = itself)"],
  ["wm_grad_share", "its share of the whole watermark gradient over the finetuning"],
];

function fmtVal(v) {
  if (Array.isArray(v)) return v.map(fmtVal).join(", ");
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toPrecision(4);
  return v === null || v === undefined ? "–" : String(v);
}

function viewer(asset) {
  const VIEWS = 8, SIZE = 384;
  let layer = "roles", view = 0, url = null;
  const img = h("img", { id: "attr-image", alt: "attribution picture", width: SIZE, height: SIZE });
  const caption = h("p", { class: "muted", id: "attr-caption" });
  const why = h("div", { class: "why", id: "why" }, h("p", { class: "muted" }, "Click a pixel of the picture: the Gaussian it shows most, and why it is what it is."));
  const buttons = ["view", "roles", "heat", "diff"].map((l) => h("button", {
    type: "button", class: "secondary", id: `layer-${l}`, "aria-pressed": String(l === layer),
    onclick: () => { layer = l; buttons.forEach((b) => b.setAttribute("aria-pressed", String(b.id === `layer-${l}`))); load(); },
  }, { view: "Render", roles: "Roles", heat: "Watermark gradient", diff: "Difference ×10" }[l]));
  const slider = h("input", { type: "range", min: 0, max: VIEWS - 1, value: 0, id: "attr-view",
    oninput: () => { view = Number(slider.value); load(); } });
  // Each load has a number; a slower, older one never replaces a newer picture. `data-ready`
  // is "1" once the newest picture is decoded and shown (what the browser test waits for).
  let loads = 0;
  async function load() {
    const mine = ++loads;
    img.dataset.ready = "0";
    caption.textContent = "Rendering…";
    try {
      const r = await api(`/v1/assets/${asset.id}/attribution/picture?layer=${layer}&view=${view}&views=${VIEWS}&size=${SIZE}`, { raw: true });
      const blob = await r.blob();
      if (mine !== loads) return;
      const next = URL.createObjectURL(blob);
      img.src = next;
      await img.decode().catch(() => {});
      if (url) URL.revokeObjectURL(url);
      url = next;
      if (mine !== loads) return;
      img.dataset.layer = layer;
      img.dataset.ready = "1";
      caption.textContent = `View ${view + 1} of ${VIEWS} (orbit), ${layer}`;
    } catch (e) { if (mine === loads) caption.replaceChildren(errorBox(e)); }
  }
  img.addEventListener("click", async (ev) => {
    const rect = img.getBoundingClientRect();
    const x = Math.floor(((ev.clientX - rect.left) / rect.width) * SIZE);
    const y = Math.floor(((ev.clientY - rect.top) / rect.height) * SIZE);
    why.replaceChildren(h("p", { class: "muted" }, "Looking…"));
    try {
      const p = await api(`/v1/assets/${asset.id}/attribution/pick?view=${view}&views=${VIEWS}&size=${SIZE}&x=${x}&y=${y}`);
      if (p.index === null) { why.replaceChildren(h("p", {}, `Pixel (${x}, ${y}) shows only the background.`)); return; }
      const rec = p.record;
      why.replaceChildren(h("h2", { id: "why-title" }, `Gaussian ${p.index}: ${rec.role}`),
        h("p", { class: "muted" }, `Pixel (${x}, ${y}); it contributes ${(100 * p.weight).toFixed(1)} % of that pixel (α·T). Child ${rec.child} of Gaussian ${rec.parent}.`),
        h("dl", {}, WHY.map(([k, text]) => [h("dt", {}, `${k}: ${fmtVal(rec[k])}`), h("dd", { class: "muted" }, text)])));
    } catch (e) { why.replaceChildren(errorBox(e)); }
  });
  load();
  return card("Where the message lives",
    h("p", { class: "legend" }, "Roles:", h("span", { class: "swatch-carrier" }), "carrier",
      h("span", { class: "swatch-compensator" }), "compensator", h("span", { class: "swatch-untouched" }), "untouched",
      " · heatmap: black → red → yellow → white by share of the watermark gradient"),
    h("div", { class: "noprint" }, buttons, " View ", slider),
    h("div", { class: "row viewer" }, h("div", {}, img, caption), why));
}

async function assetPage(id) {
  show(card(null, h("p", { class: "muted" }, "Loading…")));
  let a;
  try { a = await api(`/v1/assets/${id}`); } catch (e) { show(card("Asset", errorBox(e))); return; }
  const jobs = h("div", { id: "jobs" });
  const meta = card(`Asset ${a.id}`, h("table", { id: "asset-meta" },
    [["kind", a.kind], ["file", a.file_name || "–"], ["format", a.format], ["size", fmtBytes(a.size)],
     ["Gaussians", a.gaussians.toLocaleString()], ["SH degree", a.sh_degree], ["created", a.created_at],
     ["sha256", a.sha256], ["cameras", a.cameras_format || "none (orbit views)"]]
      .map(([k, v]) => h("tr", {}, h("th", {}, k), h("td", { class: k === "sha256" ? "mono" : "" }, String(v))))),
    h("p", {}, "Download: ", ["ply", "compressed_ply", "splat", "spz"]
      // SOG is read-only: offered only for an asset stored as SOG.
      .concat(a.format === "sog" ? ["sog"] : []).map((f) => h("button", {
      type: "button", class: "secondary", id: `dl-${f}`,
      onclick: async () => {
        try {
          const r = await api(`/v1/assets/${a.id}/file?format=${f}`, { raw: true });
          download(await r.blob(), `${a.id}.${f === "compressed_ply" ? "compressed.ply" : f}`);
        } catch (e) { meta.append(errorBox(e)); }
      } }, f))));
  const parts = [meta];
  if (a.kind === "original") {
    parts.push(card("Versions", a.watermarked.length
      ? h("ul", { id: "versions" }, a.watermarked.map((w) => h("li", {}, h("a", { href: `#/asset/${w}` }, w))))
      : h("p", { class: "muted" }, "No watermarked version yet.")));
    parts.push(watermarkForm(a, jobs), jobs, jobsList(a, jobs));
  } else {
    parts.push(card("Made from", h("a", { href: `#/asset/${a.parent_id}`, id: "parent-link" }, a.parent_id),
      a.source_job_id ? h("span", { class: "muted" }, ` by job ${a.source_job_id}`) : null));
    const summary = h("div", { id: "attr-summary" });
    parts.push(card("Attribution", summary));
    api(`/v1/assets/${a.id}/attribution/summary`).then((s) => summary.replaceChildren(
      h("pre", { class: "mono", text: JSON.stringify(s, null, 2) }))).catch((e) => summary.replaceChildren(errorBox(e)));
    parts.push(viewer(a));
    if (a.report) {
      parts.push(card("Embedding report", h("details", {}, h("summary", {}, "The job's report (JSON)"),
        h("pre", { id: "report", text: JSON.stringify(a.report, null, 2) }))));
    }
  }
  show(...parts);
}

// ---------- verification ----------

function explainP(res) {
  const b = res.best;
  const head = res.detected
    ? "The watermark was found."
    : "No watermark was found at the required confidence.";
  const p = b ? b.p_value_corrected : null;
  return `${head} The decoder read ${res.images} image(s) and compared the bits it decoded with the bits each registered ` +
    `watermark carries. If the images carried none of them, each bit would match by chance, like a coin toss; the p-value ` +
    `is the probability of matching at least as many bits as the best candidate did by chance alone` +
    (p !== null ? ` (here ${fmtP(p)}, corrected for the ${res.candidates_tested} candidate(s) tested)` : "") +
    `. The server declares a detection only when that probability is below ${fmtP(res.fpr)}: an unmarked image is ` +
    `wrongly declared marked at most that often. A small p-value is evidence of the watermark; a large one says the ` +
    `images do not show it clearly enough (another view, a larger or less compressed image may).` +
    (res.untestable && res.untestable.count > 0
      ? ` ${res.untestable.count} registered watermark(s) were not tested: they were written with a decoder this ` +
        `server no longer holds (the operator can restore it in the weights folder's archive/).`
      : "");
}

function verifyPage() {
  const files = [];
  const listEl = h("ul", { id: "verify-files" });
  const input = h("input", { type: "file", id: "verify-images", multiple: true, accept: "image/png,image/jpeg" });
  const asset = h("input", { type: "text", id: "verify-asset", placeholder: "any registered asset" });
  const out = h("div", { id: "verify-result" });
  const addFiles = (fl) => { for (const f of fl) files.push(f); listEl.replaceChildren(...files.map((f) => h("li", {}, `${f.name} (${fmtBytes(f.size)})`))); };
  input.addEventListener("change", () => addFiles(input.files));
  const drop = h("div", { class: "drop", id: "drop" }, "Drop rendered images (PNG or JPEG) here, or ", input);
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); addFiles(e.dataTransfer.files); });
  const form = h("form", {
    id: "verify-form",
    onsubmit: async (ev) => {
      ev.preventDefault();
      if (!files.length) { out.replaceChildren(errorBox(new Error("add at least one image"))); return; }
      const fd = new FormData();
      for (const f of files) fd.append("image", f);
      if (asset.value.trim()) fd.append("asset_id", asset.value.trim());
      out.replaceChildren(h("p", { class: "muted" }, "Decoding…"));
      try {
        const res = await api("/v1/verify", { method: "POST", body: fd });
        out.replaceChildren(verdict(res));
      } catch (e) { out.replaceChildren(errorBox(e)); }
    },
  }, drop, listEl, h("label", {}, "Asset (optional) ", asset), h("button", { type: "submit", id: "verify" }, "Verify"));
  show(card("Verify images", h("p", { class: "muted" }, "Submit renders of a disputed scene; they are tested against every registered watermark (or one asset's)."), form), out);
}

function verdict(res) {
  const rows = (res.results || []).map((r) => h("tr", {},
    h("td", { class: "mono" }, r.asset_id), h("td", {}, `${r.matches} / ${r.bits}`),
    h("td", {}, `${(100 * r.bit_accuracy).toFixed(1)} %`), h("td", {}, fmtP(r.p_value)),
    h("td", {}, fmtP(r.p_value_corrected)), h("td", {}, r.threshold), h("td", { class: r.detected ? "ok" : "" }, r.detected ? "yes" : "no")));
  return card("Verification record",
    h("p", { class: `verdict ${res.detected ? "ok" : "bad"}`, id: "verdict" }, res.detected ? "Detected" : "Not detected"),
    h("p", { id: "verdict-explained" }, explainP(res)),
    h("table", { id: "candidates" }, h("tr", {}, ["asset", "bits matching", "bit accuracy", "p-value", "corrected", "threshold", "detected"].map((t) => h("th", {}, t))), rows),
    h("p", { class: "muted" }, `Verification ${res.verification_id} · audit row ${res.audit_id} · ${res.images} image(s) · FPR ${fmtP(res.fpr)}`),
    h("p", { class: "noprint" },
      h("button", { type: "button", id: "verify-download", onclick: () => download(new Blob([JSON.stringify(res, null, 2)], { type: "application/json" }), `verification-${res.verification_id}.json`) }, "Download record (JSON)"), " ",
      h("button", { type: "button", class: "secondary", onclick: () => window.print() }, "Print")));
}

// ---------- audit ----------

function auditPage() {
  const fields = ["asset_id", "action", "actor", "since", "until"].map((n) => h("input", { type: "text", id: `audit-${n}`, name: n, placeholder: n === "since" || n === "until" ? "2026-12-01T00:00:00Z" : n }));
  const out = h("div", { id: "audit-rows" });
  const chain = h("p", { id: "audit-chain" });
  async function load(ev) {
    if (ev) ev.preventDefault();
    const q = new URLSearchParams();
    fields.forEach((f) => { if (f.value.trim()) q.set(f.name, f.value.trim()); });
    q.set("limit", "200");
    try {
      const page = await api(`/v1/audit?${q}`);
      out.replaceChildren(h("table", { id: "audit-table" },
        h("tr", {}, ["#", "at", "actor", "action", "asset", "details", "hash"].map((t) => h("th", {}, t))),
        page.items.map((r) => h("tr", { "data-action": r.action },
          h("td", {}, r.id), h("td", {}, r.at), h("td", { class: "mono" }, r.actor), h("td", {}, r.action),
          h("td", { class: "mono" }, r.asset_id || "–"),
          h("td", {}, r.action === "verify"
            ? h("span", { class: r.details.detected ? "ok" : "bad" }, `${r.details.detected ? "detected" : "not detected"}` +
              (r.details.best_asset ? ` · best ${r.details.best_asset} · p ${fmtP(r.details.best_p_value_corrected)}` : "") + ` · ${r.details.images} image(s)`)
            : h("span", { class: "mono" }, JSON.stringify(r.details))),
          h("td", { class: "mono" }, r.hash.slice(0, 12) + "…")))));
    } catch (e) { out.replaceChildren(errorBox(e)); }
  }
  const check = h("button", { type: "button", class: "secondary", id: "audit-verify", onclick: async () => {
    try {
      const c = await api("/v1/audit/verify");
      chain.replaceChildren(h("span", { class: c.ok ? "ok" : "bad" }, c.ok
        ? `The chain holds: ${c.rows} rows, each hashing the one before it (head ${String(c.head_hash).slice(0, 16)}…).`
        : `The chain is broken at row ${c.first_bad_id}.`));
    } catch (e) { chain.replaceChildren(errorBox(e)); }
  } }, "Check the hash chain");
  show(card("Audit log", h("form", { id: "audit-form", onsubmit: load }, h("div", { class: "row" }, fields), h("button", { type: "submit" }, "Filter"), " ", check), chain), out);
  load();
}

// ---------- routing ----------

function route() {
  const hash = location.hash || "#/assets";
  document.getElementById("signout").hidden = !key();
  document.querySelectorAll("header nav a").forEach((a) => a.classList.toggle("active", hash.startsWith(a.getAttribute("href"))));
  if (!key()) { signIn(hash); return; }
  const m = hash.match(/^#\/asset\/([0-9a-f-]{36})$/);
  if (m) assetPage(m[1]);
  else if (hash === "#/verify") verifyPage();
  else if (hash === "#/audit") auditPage();
  else assetsPage();
}

window.addEventListener("hashchange", route);
window.addEventListener("DOMContentLoaded", () => {
  document.getElementById("signout").addEventListener("click", () => { sessionStorage.removeItem(KEY); location.hash = "#/signin"; route(); });
  route();
});
