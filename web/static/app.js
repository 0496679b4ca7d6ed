// Operator page: plain JavaScript, no framework, no CDN. Live state comes from server-sent events
// (/api/events); the authoritative batch state is also polled from /api/batches/{id}.
"use strict";

const S = {
  token: localStorage.getItem("station.token") || "",
  batchId: Number(localStorage.getItem("station.batch")) || null,
  slots: new Map(),        // slot -> {slot, serial, state, error, segments, temp_c, acc_g, samples, result}
  prompt: null,
  es: null,
  pollTimer: null,
  finalBatch: false,
};

const $ = (id) => document.getElementById(id);

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null) e.setAttribute(k, v);
  }
  for (const c of children) {
    if (c === null || c === undefined) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

function fmt(v, digits) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  return Number(v).toFixed(digits);
}

function message(text) { $("message").textContent = text || ""; }

async function api(path, opts = {}) {
  const headers = Object.assign({}, opts.headers || {});
  if (S.token) headers["Authorization"] = "Bearer " + S.token;
  if (opts.body !== undefined) headers["Content-Type"] = "application/json";
  const resp = await fetch(path, {
    method: opts.method || "GET",
    headers,
    body: opts.body !== undefined ? JSON.stringify(opts.body) : undefined,
  });
  if (!resp.ok) {
    let detail = resp.status + " " + resp.statusText;
    try { const j = await resp.json(); if (j.detail) detail = j.detail; } catch (_) { /* not json */ }
    const err = new Error(detail);
    err.status = resp.status;
    throw err;
  }
  if (opts.raw) return resp;
  const type = resp.headers.get("content-type") || "";
  return type.includes("json") ? resp.json() : resp.text();
}

async function blobUrl(path) {
  const resp = await api(path, { raw: true });
  return URL.createObjectURL(await resp.blob());
}

// ---- token -----------------------------------------------------------------------------------
function saveToken() {
  S.token = $("token").value.trim();
  localStorage.setItem("station.token", S.token);
  $("token").value = "";
  boot();
}

// ---- slots -----------------------------------------------------------------------------------
function slotState(name) {
  if (!S.slots.has(name)) S.slots.set(name, { slot: name, segments: 0 });
  return S.slots.get(name);
}

function renderSlots() {
  const box = $("slots");
  const names = [...S.slots.keys()].sort((a, b) => a.localeCompare(b, undefined, { numeric: true }));
  for (const name of names) {
    const s = S.slots.get(name);
    let card = box.querySelector(`.slot-card[data-slot="${CSS.escape(name)}"]`);
    if (!card) {
      card = el("article", { class: "slot-card", "data-slot": name });
      box.append(card);
    }
    const state = s.state || "idle";
    card.className = "slot-card st-" + state;
    card.dataset.state = state;
    const acc = Array.isArray(s.acc_g) ? s.acc_g.map((v) => fmt(v, 3)).join(" / ") : "–";
    card.replaceChildren(
      el("h2", {}, el("span", {}, name), el("span", { class: "state" }, state)),
      el("div", { class: "serial" }, s.serial || "no DUT"),
      el("div", { class: "big" }, s.temp_c === undefined ? "– °C" : fmt(s.temp_c, 1) + " °C"),
      el("dl", {},
        el("dt", {}, "Step"), el("dd", {}, s.step_name || (s.step_index ?? "–")),
        el("dt", {}, "Segments"), el("dd", { class: "segments" }, String(s.segments || 0)),
        el("dt", {}, "Acc x/y/z g"), el("dd", {}, acc),
        el("dt", {}, "Samples"), el("dd", {}, s.samples ?? "–"),
      ),
      s.error ? el("div", { class: "fault" }, "Fault: " + s.error) : null,
      s.result ? resultTable(s.result) : null,
      s.plotUrl ? el("img", { class: "plot-thumb", src: s.plotUrl, alt: "plot of " + (s.serial || name), onclick: () => showPlot(s.plotUrl) }) : null,
    );
  }
}

function axesOf(o) {
  if (!o || typeof o !== "object") return null;
  if (o.axes && o.axes.x) return o.axes;
  if (o.x) return o;
  return null;
}

function resultTable(result) {
  // result.thermal: the daemon's DutResult thermal ({axes, streaming, offline}) or stored per-axis
  // values ({x, y, z}); result.by_method: stored results per method.
  const th = result.thermal || {};
  const by = result.by_method || {};
  const methods = [];
  for (const m of ["streaming", "offline"]) {
    const axes = axesOf(th[m]) || axesOf(by[m]);
    if (axes) methods.push([m, axes]);
  }
  if (!methods.length && axesOf(th)) methods.push(["result", axesOf(th)]);
  const rows = [];
  for (const [m, axes] of methods) {
    for (const ax of ["x", "y", "z"]) {
      const a = axes[ax] || {};
      rows.push(el("tr", {}, el("td", {}, m + " " + ax), el("td", {}, fmt(a.tdb_mg_per_c, 3)), el("td", {}, fmt(a.tdsf_ppm_per_c, 1))));
    }
  }
  const table = el("table", { class: "results" },
    el("thead", {}, el("tr", {}, el("th", {}, "method/axis"), el("th", {}, "TDB mg/°C"), el("th", {}, "TDSF ppm/°C"))),
    el("tbody", {}, ...rows));
  const wrap = el("div", { class: "result" }, table);
  if (result.sfem) {
    const sf = result.sfem;
    const rb = sf.rmse_before_mg ?? (sf.fit && sf.fit.rmse_before_mg);
    const ra = sf.rmse_after_mg ?? (sf.fit && sf.fit.rmse_after_mg);
    wrap.append(el("div", { class: "sfem" }, `SFEM: RMSE ${fmt(rb, 2)} → ${fmt(ra, 2)} mg`));
  }
  return wrap;
}

function showPlot(url) {
  $("plot-img").src = url;
  $("plot-dialog").showModal();
}

async function loadPlot(slot) {
  const s = slotState(slot);
  if (!s.serial || s.plotUrl) return;
  try {
    const runs = await api(`/api/duts/${encodeURIComponent(s.serial)}/runs`);
    const run = runs.find((r) => !S.batchId || r.batch_id === S.batchId) || runs[0];
    if (!run) return;
    s.runId = run.id;
    if (run.thermal || run.sfem) s.result = { thermal: run.thermal, sfem: run.sfem, by_method: run.thermal_by_method };
    s.plotUrl = await blobUrl(`/api/runs/${run.id}/plot.png`);
    renderSlots();
  } catch (e) { /* results may not be stored yet; retried on the next poll */ }
}

// ---- batch -----------------------------------------------------------------------------------
function setBatch(id) {
  S.batchId = id;
  if (id) localStorage.setItem("station.batch", String(id)); else localStorage.removeItem("station.batch");
  $("batch-panel").classList.toggle("hidden", !id);
  $("start-panel").classList.toggle("hidden", !!id && !S.finalBatch);
  $("batch-id").textContent = id || "";
}

const FINAL = new Set(["finished", "aborted", "failed", "interrupted"]);

function applyBatch(b) {
  $("batch-profile").textContent = b.profile || "";
  $("batch-state").textContent = b.state;
  $("batch-state").dataset.state = b.state;
  if (b.step) $("batch-step").textContent = [b.step.index, b.step.name].filter((x) => x !== null && x !== undefined).join(" · ");
  $("batch-error").textContent = b.error || "";
  for (const sl of b.slots || []) {
    const s = slotState(sl.slot);
    for (const k of ["serial", "state", "segments"]) if (sl[k] !== null && sl[k] !== undefined) s[k] = sl[k];
    s.error = sl.error || s.error;
    if (b.step) { s.step_index = b.step.index; s.step_name = b.step.name; }
    if (sl.result && !s.result) s.result = sl.result;
    if (s.state === "done" && !s.plotUrl) loadPlot(sl.slot);
  }
  S.finalBatch = FINAL.has(b.state);
  $("abort").classList.toggle("hidden", S.finalBatch);
  $("new-batch").classList.toggle("hidden", !S.finalBatch);
  $("start-panel").classList.toggle("hidden", !S.finalBatch);
  if (b.prompt && b.prompt.prompt_id !== undefined) showPrompt(b.prompt);
  else if (S.finalBatch) hidePrompt();
  renderSlots();
}

async function pollBatch() {
  if (!S.batchId) return;
  try {
    applyBatch(await api(`/api/batches/${S.batchId}`));
    const p = await api(`/api/batches/${S.batchId}/prompt`);
    if (p) showPrompt(p); else hidePrompt();
  } catch (e) {
    if (e.status === 404) { setBatch(null); }
    else message(e.message);
  }
}

async function startBatch() {
  const picks = [...document.querySelectorAll("#slot-picks input:checked")].map((i) => i.value);
  const all = document.querySelectorAll("#slot-picks input").length;
  const body = {
    profile: $("profile").value,
    operator: $("operator").value.trim() || "operator",
    slots: picks.length === all ? null : picks,
  };
  localStorage.setItem("station.operator", body.operator);
  if (body.slots && !body.slots.length) { message("Choose at least one slot."); return; }
  $("start").disabled = true;
  try {
    const r = await api("/api/batches", { method: "POST", body });
    for (const s of S.slots.values()) { delete s.result; delete s.plotUrl; s.segments = 0; s.error = ""; }
    S.finalBatch = false;
    setBatch(r.id);
    message(`Batch ${r.id} started.`);
    await pollBatch();
  } catch (e) {
    message("Could not start: " + e.message);
  } finally {
    $("start").disabled = false;
  }
}

async function abortBatch() {
  if (!S.batchId || !confirm("Abort batch " + S.batchId + "? The lamp is switched off.")) return;
  try {
    await api(`/api/batches/${S.batchId}/abort`, { method: "POST" });
    message(`Batch ${S.batchId} aborted.`);
    await pollBatch();
  } catch (e) { message("Abort failed: " + e.message); }
}

// ---- prompts ---------------------------------------------------------------------------------
function showPrompt(p) {
  S.prompt = p;
  $("prompt-text").textContent = p.text;
  $("prompt-banner").classList.remove("hidden");
  $("prompt-confirm").disabled = false;
}

function hidePrompt() {
  S.prompt = null;
  $("prompt-banner").classList.add("hidden");
}

async function confirmPrompt() {
  if (!S.prompt || !S.batchId) return;
  $("prompt-confirm").disabled = true;
  try {
    await api(`/api/batches/${S.prompt.batch_id || S.batchId}/prompt`, {
      method: "POST", body: { prompt_id: S.prompt.prompt_id, answer: "done" },
    });
    hidePrompt();
  } catch (e) {
    message("Confirm failed: " + e.message);
    $("prompt-confirm").disabled = false;
  }
}

// ---- live events -----------------------------------------------------------------------------
function onEvent(ev) {
  if (ev.batch_id !== undefined && S.batchId && ev.batch_id !== S.batchId && ev.kind !== "LiveSummary") return;
  switch (ev.kind) {
    case "Snapshot":
      for (const sl of ev.slots || []) { const s = slotState(sl.slot || sl.name); if (sl.serial) s.serial = sl.serial; if (!s.state && sl.state) s.state = sl.state; }
      break;
    case "LiveSummary":
      for (const [name, v] of Object.entries(ev.slots || {})) {
        if (S.batchId && v.batch_id !== S.batchId) continue;
        Object.assign(slotState(name), { temp_c: v.temp_c, acc_g: v.acc_g, samples: v.samples, serial: v.serial || slotState(name).serial });
      }
      break;
    case "SlotStateChanged": {
      const s = slotState(ev.slot);
      s.state = ev.state; if (ev.serial) s.serial = ev.serial;
      s.error = ev.fault_reason || "";
      break;
    }
    case "SegmentLogged": {
      const s = slotState(ev.slot);
      s.segments = (s.segments || 0) + 1;
      break;
    }
    case "StepStarted":
      $("batch-step").textContent = ev.step_index + " · " + ev.step_name;
      for (const s of S.slots.values()) { s.step_index = ev.step_index; s.step_name = ev.step_name; }
      break;
    case "DutResult": {
      const s = slotState(ev.slot);
      s.result = { thermal: ev.thermal, sfem: ev.sfem };
      if (ev.serial) s.serial = ev.serial;
      setTimeout(() => loadPlot(ev.slot), 700);
      break;
    }
    case "PromptRaised": showPrompt(ev); break;
    case "PromptAnswered": if (S.prompt && S.prompt.prompt_id === ev.prompt_id) hidePrompt(); break;
    case "LampChanged": $("lamp").textContent = ev.on ? "ON" : "off"; break;
    case "BatchStateChanged":
      $("batch-state").textContent = ev.state;
      pollBatch();
      break;
    case "Alarm":
      $("alarm").textContent = ev.text;
      $("alarm").classList.remove("hidden");
      setTimeout(() => $("alarm").classList.add("hidden"), 30000);
      break;
    default: break;
  }
  renderSlots();
}

function connect() {
  if (S.es) S.es.close();
  if (!S.token) return;
  S.es = new EventSource("/api/events?token=" + encodeURIComponent(S.token));
  S.es.onopen = () => { $("conn").textContent = "live"; $("conn").className = "conn on"; };
  S.es.onerror = () => { $("conn").textContent = "reconnecting"; $("conn").className = "conn off"; };
  S.es.onmessage = (m) => { try { onEvent(JSON.parse(m.data)); } catch (e) { console.error(e); } };
}

// ---- history ---------------------------------------------------------------------------------
async function search() {
  const q = $("search").value.trim();
  const list = $("dut-list");
  list.replaceChildren();
  $("dut-runs").replaceChildren();
  try {
    const duts = await api("/api/duts?serial_like=" + encodeURIComponent(q));
    if (!duts.length) list.append(el("p", { class: "muted" }, "No DUT found."));
    for (const d of duts) {
      list.append(el("button", { type: "button", class: "btn dut", "data-serial": d.serial, onclick: () => showDut(d.serial) },
        `${d.serial} (${d.runs} run${d.runs === 1 ? "" : "s"})`));
    }
  } catch (e) { list.append(el("p", { class: "error" }, e.message)); }
}

async function showDut(serial) {
  const box = $("dut-runs");
  box.replaceChildren(el("h2", {}, serial));
  try {
    const runs = await api(`/api/duts/${encodeURIComponent(serial)}/runs`);
    for (const r of runs) {
      const card = el("article", { class: "run-card", "data-run": r.id },
        el("h3", {}, `Run ${r.id} · batch ${r.batch_id ?? "–"} · slot ${r.slot ?? "–"} · ${r.state ?? ""}`),
        el("div", { class: "muted" }, `${r.profile ?? ""} ${r.started_at ?? ""} ${r.fault_reason ? "· " + r.fault_reason : ""}`));
      if (r.thermal || r.sfem) card.append(resultTable({ thermal: r.thermal, sfem: r.sfem, by_method: r.thermal_by_method }));
      const actions = el("div", { class: "panel" });
      actions.append(el("button", { type: "button", class: "btn", onclick: async () => showPlot(await blobUrl(`/api/runs/${r.id}/plot.png`)) }, "Plot"));
      actions.append(el("button", { type: "button", class: "btn", onclick: async () => {
        const url = await blobUrl(`/api/runs/${r.id}/log.csv`);
        const a = el("a", { href: url, download: `${serial}-run${r.id}.csv` }); document.body.append(a); a.click(); a.remove();
      } }, "Log CSV"));
      card.append(actions);
      box.append(card);
    }
  } catch (e) { box.append(el("p", { class: "error" }, e.message)); }
}

function showView(name) {
  for (const v of ["live", "history"]) {
    $("view-" + v).classList.toggle("hidden", v !== name);
    $("tab-" + v).classList.toggle("active", v === name);
  }
}

// ---- start-up --------------------------------------------------------------------------------
async function boot() {
  $("whoami").textContent = S.token ? "token saved" : "no token: paste one to operate";
  if (!S.token) return;
  try {
    const [profiles, slots] = await Promise.all([api("/api/profiles"), api("/api/slots")]);
    const sel = $("profile");
    sel.replaceChildren(...profiles.map((p) => el("option", { value: p.name }, p.description ? `${p.name} — ${p.description}` : p.name)));
    const picks = $("slot-picks");
    picks.replaceChildren(...slots.map((s) => el("label", { class: "slot-pick" },
      el("input", { type: "checkbox", value: s.slot, checked: "checked" }), s.slot)));
    for (const s of slots) { const st = slotState(s.slot); if (s.serial) st.serial = s.serial; if (!st.state && s.state) st.state = s.state; }
    renderSlots();
    message("");
  } catch (e) {
    message(e.status === 401 ? "Token rejected: " + e.message : e.message);
    return;
  }
  connect();
  setBatch(S.batchId);
  if (S.batchId) await pollBatch();
  clearInterval(S.pollTimer);
  S.pollTimer = setInterval(pollBatch, 2000);
}

document.addEventListener("DOMContentLoaded", () => {
  $("save-token").addEventListener("click", saveToken);
  $("token").addEventListener("keydown", (e) => { if (e.key === "Enter") saveToken(); });
  $("start").addEventListener("click", startBatch);
  $("abort").addEventListener("click", abortBatch);
  $("new-batch").addEventListener("click", () => { setBatch(null); S.finalBatch = true; $("start-panel").classList.remove("hidden"); $("batch-panel").classList.add("hidden"); });
  $("prompt-confirm").addEventListener("click", confirmPrompt);
  $("search-go").addEventListener("click", search);
  $("search").addEventListener("keydown", (e) => { if (e.key === "Enter") search(); });
  for (const t of document.querySelectorAll(".tab")) t.addEventListener("click", () => showView(t.dataset.view));
  $("operator").value = localStorage.getItem("station.operator") || "";
  boot();
});
