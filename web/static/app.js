// Operator page: plain JavaScript, no framework, no CDN. Live state comes from server-sent events
// (/api/events); the authoritative batch state is also polled from /api/batches/{id}.
"use strict";

const S = {
  token: localStorage.getItem("station.token") || "",
  role: null,
  batchId: Number(localStorage.getItem("station.batch")) || null,
  batchSlots: null,        // slots of the current batch (null: none yet)
  stepCount: null,
  order: [],               // slot names in the station's order
  slots: new Map(),        // slot -> {slot, serial, state, error, segments, temp_c, acc_g, samples, result, plotUrl}
  prompt: null,
  es: null,
  pollTimer: null,
  finalBatch: true,
};

const FINAL = new Set(["finished", "aborted", "failed", "interrupted"]);
const STATE_LABEL = { identified: "ready", disconnected: "no DUT", busy: "running", idle: "idle" };

const $ = (id) => document.getElementById(id);

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) e.setAttribute(k, v);
  }
  for (const c of children) {
    if (c === null || c === undefined || c === false) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

function fmt(v, digits) {
  if (v === null || v === undefined || Number.isNaN(Number(v))) return "–";
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

const canControl = () => S.role === "operator" || S.role === "admin";

// ---- token -----------------------------------------------------------------------------------
function saveToken() {
  S.token = $("token").value.trim();
  localStorage.setItem("station.token", S.token);
  $("token").value = "";
  boot();
}

function signOut() {
  S.token = "";
  S.role = null;
  localStorage.removeItem("station.token");
  if (S.es) S.es.close();
  clearInterval(S.pollTimer);
  boot();
}

// ---- slots -----------------------------------------------------------------------------------
function slotState(name) {
  if (!S.slots.has(name)) S.slots.set(name, { slot: name, segments: 0 });
  return S.slots.get(name);
}

function inBatch(name) { return !S.batchSlots || S.batchSlots.includes(name); }

function renderSlots() {
  const box = $("slots");
  const rank = (n) => (S.order.includes(n) ? S.order.indexOf(n) : 1e6);
  const names = [...S.slots.keys()].sort((a, b) => rank(a) - rank(b) || a.localeCompare(b, undefined, { numeric: true }));
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
    const active = inBatch(name) && S.batchId;
    const acc = Array.isArray(s.acc_g) ? s.acc_g.map((v) => fmt(v, 3)).join("  ") : "–";
    const need = S.stepCount || 4;
    const dots = el("span", { class: "dots", "aria-hidden": "true" });
    for (let i = 0; i < need; i++) dots.append(el("span", { class: i < (s.segments || 0) ? "dot on" : "dot" }));
    card.replaceChildren(...[
      el("header", {}, el("h2", {}, name), el("span", { class: "st" }, STATE_LABEL[state] || state)),
      el("div", { class: "serial" }, s.serial || "no DUT", s.sensor ? el("span", { class: "muted" }, " · " + s.sensor) : null),
      active ? el("div", { class: "live" },
        el("span", { class: "temp" }, s.temp_c === undefined || s.temp_c === null ? "– °C" : fmt(s.temp_c, 1) + " °C"),
        el("span", { class: "segbox" }, "Segments ", el("b", { class: "segments" }, String(s.segments || 0)), dots)) : null,
      active ? el("dl", {},
        el("dt", {}, "Acc x y z (g)"), el("dd", { class: "acc" }, acc),
        el("dt", {}, "Samples"), el("dd", { class: "samples" }, String(s.samples ?? 0)),
      ) : el("div", { class: "muted" }, S.batchId && !S.finalBatch ? "not in this batch" : ""),
      s.error ? el("div", { class: "fault" }, "Fault: " + s.error) : null,
      active && s.result ? resultTable(s.result) : null,
      active && s.plotUrl ? el("img", { class: "plot-thumb", src: s.plotUrl, alt: "plot of " + (s.serial || name), onclick: () => showPlot(s.plotUrl) }) : null,
    ].filter((c) => c !== null && c !== undefined && c !== false));
  }
}

function axesOf(o) {
  if (!o || typeof o !== "object") return null;
  if (o.axes && o.axes.x) return o.axes;
  if (o.x) return o;
  return null;
}

// A result in one shape: {axes: {x,y,z}, method, streaming: {x,y,z} | null, sfem}
function liveResult(ev) {
  const th = ev.thermal || {};
  return { axes: axesOf(th), method: th.axes_method || "offline", streaming: axesOf(th.streaming), sfem: ev.sfem };
}

function storedResult(run) {
  const by = run.thermal_by_method || {};
  return { axes: axesOf(run.thermal), method: run.thermal_method, streaming: axesOf(by.streaming), sfem: run.sfem };
}

function resultTable(result) {
  const wrap = el("div", { class: "result" });
  if (result.axes) {
    const rows = ["x", "y", "z"].map((ax) => {
      const a = result.axes[ax] || {};
      return el("tr", { "data-axis": ax }, el("td", {}, ax), el("td", { class: "tdb" }, fmt(a.tdb_mg_per_c, 3)),
        el("td", { class: "tdsf" }, fmt(a.tdsf_ppm_per_c, 1)));
    });
    wrap.append(el("table", { class: "results" },
      el("thead", {}, el("tr", {}, el("th", {}, "axis"), el("th", {}, "TDB mg/°C"), el("th", {}, "TDSF ppm/°C"))),
      el("tbody", {}, ...rows)));
    let note = (result.method || "") + (result.method === "offline" ? " fit" : "");
    if (result.streaming && result.method !== "streaming") {
      note += " · streaming TDB " + ["x", "y", "z"].map((ax) => fmt((result.streaming[ax] || {}).tdb_mg_per_c, 3)).join(" / ");
    }
    wrap.append(el("div", { class: "method" }, note));
  }
  if (result.sfem) {
    const sf = result.sfem;
    const t = (sf.temperatures && sf.temperatures[0] && sf.temperatures[0].fit) || sf.fit || sf;
    wrap.append(el("div", { class: "sfem" }, `SFEM: RMSE ${fmt(t.rmse_before_mg, 2)} → ${fmt(t.rmse_after_mg, 2)} mg`));
  }
  return wrap;
}

function showPlot(url) {
  $("plot-img").src = url;
  $("plot-dialog").showModal();
}

async function loadPlot(slot) {
  const s = slotState(slot);
  if (!s.serial || s.plotUrl || s.plotLoading) return;
  s.plotLoading = true;
  try {
    const runs = await api(`/api/duts/${encodeURIComponent(s.serial)}/runs`);
    const run = runs.find((r) => r.batch_id === S.batchId);
    if (!run || !(run.thermal || run.sfem)) return;  // not stored yet: the next poll retries
    s.runId = run.id;
    s.result = storedResult(run);
    s.plotUrl = await blobUrl(`/api/runs/${run.id}/plot.png`);
    renderSlots();
  } catch (e) { /* retried on the next poll */ } finally { s.plotLoading = false; }
}

// ---- batch -----------------------------------------------------------------------------------
function setBatch(id) {
  S.batchId = id;
  if (id) localStorage.setItem("station.batch", String(id)); else localStorage.removeItem("station.batch");
  if (!id) { S.batchSlots = null; S.finalBatch = true; }
  $("batch-panel").classList.toggle("hidden", !id);
  $("batch-id").textContent = id || "";
  showControls();
}

function showControls() {
  $("start-panel").classList.toggle("hidden", !(S.finalBatch && canControl()));
  $("abort").classList.toggle("hidden", S.finalBatch || !canControl());
  $("new-batch").classList.toggle("hidden", !S.finalBatch || !S.batchId || !canControl());
}

function setLamp(on) {
  $("lamp").textContent = on ? "ON" : "OFF";
  $("lamp").className = "chip " + (on ? "lamp-on" : "lamp-off");
}

function applyBatch(b) {
  $("batch-profile").textContent = b.profile || "";
  $("batch-state").textContent = b.state;
  $("batch-state").dataset.state = b.state;
  S.stepCount = (b.step && b.step.count) || S.stepCount;
  if (b.step && b.step.index !== null && b.step.index !== undefined) {
    $("batch-step").textContent = `${b.step.index + 1} / ${b.step.count ?? "?"} · ${b.step.name ?? ""}`;
  }
  if (b.lamp_on !== undefined) setLamp(b.lamp_on);
  $("batch-error").textContent = b.error || "";
  S.batchSlots = (b.slots || []).map((sl) => sl.slot);
  const counts = { running: 0, done: 0, faulted: 0 };
  for (const sl of b.slots || []) {
    const s = slotState(sl.slot);
    for (const k of ["serial", "state", "segments", "samples", "sensor"]) if (sl[k] !== null && sl[k] !== undefined) s[k] = sl[k];
    s.error = sl.error || "";
    if (sl.state in counts) counts[sl.state] += 1; else counts.running += 1;
    if (s.state === "done" && !s.plotUrl) loadPlot(sl.slot);
  }
  $("batch-counts").textContent = `${counts.running} running · ${counts.done} done · ${counts.faulted} faulted`;
  S.finalBatch = FINAL.has(b.state);
  showControls();
  if (b.prompt && b.prompt.prompt_id !== undefined) showPrompt(b.prompt);
  else hidePrompt();
  renderSlots();
}

async function pollBatch() {
  if (!S.batchId) return;
  try {
    applyBatch(await api(`/api/batches/${S.batchId}`));
  } catch (e) {
    if (e.status === 404) setBatch(null);
    else message(e.message);
  }
}

function pickAll(on) { for (const i of document.querySelectorAll("#slot-picks input")) i.checked = on; }

async function startBatch() {
  const picks = [...document.querySelectorAll("#slot-picks input:checked")].map((i) => i.value);
  const all = document.querySelectorAll("#slot-picks input").length;
  const body = {
    profile: $("profile").value,
    operator: $("operator").value.trim() || "operator",
    slots: picks.length === all ? null : picks,
  };
  if (body.slots && !body.slots.length) { message("Choose at least one slot."); return; }
  localStorage.setItem("station.operator", body.operator);
  $("start").disabled = true;
  try {
    const r = await api("/api/batches", { method: "POST", body });
    for (const s of S.slots.values()) {
      delete s.result; delete s.plotUrl; delete s.temp_c; delete s.acc_g;
      s.segments = 0; s.samples = 0; s.error = "";
    }
    S.batchSlots = body.slots || [...S.slots.keys()];
    S.finalBatch = false;
    setBatch(r.id);
    message("");
    await pollBatch();
  } catch (e) {
    message("Could not start: " + e.message);
  } finally {
    $("start").disabled = false;
  }
}

// Abort takes two taps (no blocking browser dialog on a kiosk): the first arms the button for 4 s.
let abortArmed = null;

function disarmAbort() {
  clearTimeout(abortArmed);
  abortArmed = null;
  $("abort").classList.remove("armed");
  $("abort").textContent = "Abort";
}

async function abortBatch() {
  if (!S.batchId) return;
  if (!abortArmed) {
    $("abort").classList.add("armed");
    $("abort").textContent = "Tap again to abort";
    abortArmed = setTimeout(disarmAbort, 4000);
    return;
  }
  disarmAbort();
  try {
    await api(`/api/batches/${S.batchId}/abort`, { method: "POST" });
    message(`Batch ${S.batchId} aborted.`);
    await pollBatch();
  } catch (e) { message("Abort failed: " + e.message); }
}

// ---- prompts ---------------------------------------------------------------------------------
function showPrompt(p) {
  if (S.prompt && S.prompt.prompt_id === p.prompt_id && !$("prompt-banner").classList.contains("hidden")) return;
  S.prompt = p;
  $("prompt-text").textContent = p.text;
  $("prompt-banner").classList.remove("hidden");
  $("prompt-confirm").disabled = !canControl();
}

function hidePrompt() {
  S.prompt = null;
  $("prompt-banner").classList.add("hidden");
}

async function confirmPrompt() {
  if (!S.prompt || !S.batchId) return;
  $("prompt-confirm").disabled = true;
  try {
    await api(`/api/batches/${S.batchId}/prompt`, {
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
  if (ev.kind === "BatchStateChanged" && ev.state === "running" && !S.batchId) { setBatch(ev.batch_id); S.finalBatch = false; pollBatch(); }
  if (ev.batch_id !== undefined && ev.batch_id !== S.batchId && ev.kind !== "LiveSummary" && ev.kind !== "Snapshot") return;
  switch (ev.kind) {
    case "Snapshot":
      for (const sl of ev.slots || []) {
        const s = slotState(sl.slot || sl.name);
        if (sl.serial) s.serial = sl.serial;
        if (sl.sensor) s.sensor = sl.sensor;
        if (!S.batchId || !inBatch(sl.slot)) s.state = sl.state;
      }
      break;
    case "LiveSummary":
      for (const [name, v] of Object.entries(ev.slots || {})) {
        if (v.batch_id !== S.batchId) continue;
        const s = slotState(name);
        s.temp_c = v.temp_c; s.acc_g = v.acc_g;
        if (v.serial) s.serial = v.serial;
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
      s.segments = Math.max(s.segments || 0, (ev.segment && ev.segment.index + 1) || (s.segments || 0) + 1);
      break;
    }
    case "StepStarted":
      $("batch-step").textContent = `${ev.step_index + 1} / ${S.stepCount ?? "?"} · ${ev.step_name}`;
      break;
    case "DutResult": {
      const s = slotState(ev.slot);
      if (!s.result) s.result = liveResult(ev);
      if (ev.serial) s.serial = ev.serial;
      setTimeout(() => loadPlot(ev.slot), 700);
      break;
    }
    case "PromptRaised": showPrompt(ev); break;
    case "PromptAnswered": if (S.prompt && S.prompt.prompt_id === ev.prompt_id) hidePrompt(); break;
    case "LampChanged": setLamp(ev.on); break;
    case "BatchStateChanged":
      $("batch-state").textContent = ev.state;
      $("batch-state").dataset.state = ev.state;
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
        `${d.serial} · ${d.runs} run${d.runs === 1 ? "" : "s"}`));
    }
    if (duts.length === 1) showDut(duts[0].serial);
  } catch (e) { list.append(el("p", { class: "error" }, e.message)); }
}

function when(iso) { return iso ? new Date(iso).toLocaleString() : "–"; }

let showDutSeq = 0;

async function showDut(serial) {
  const seq = ++showDutSeq;  // a later call (another tap) wins; an earlier one drops its answer
  const box = $("dut-runs");
  box.replaceChildren(el("h2", {}, serial));
  try {
    const runs = await api(`/api/duts/${encodeURIComponent(serial)}/runs`);
    if (seq !== showDutSeq) return;
    box.replaceChildren(el("h2", {}, serial));
    if (!runs.length) box.append(el("p", { class: "muted" }, "No run stored."));
    for (const r of runs) {
      const plotBox = el("div", { class: "plot-box" });
      const info = el("div", {},
        el("h3", {}, `Run ${r.id} · ${r.state ?? ""}`),
        el("div", { class: "muted" }, `batch ${r.batch_id ?? "–"} · slot ${r.slot ?? "–"} · ${r.profile ?? ""}`),
        el("div", { class: "muted" }, `${when(r.started_at)} → ${when(r.finished_at)}`),
        r.fault_reason ? el("div", { class: "fault" }, "Fault: " + r.fault_reason) : null,
        (r.thermal || r.sfem) ? resultTable(storedResult(r)) : el("div", { class: "muted" }, "no result"),
        el("div", { class: "actions" },
          el("button", { type: "button", class: "btn plot", onclick: async () => showPlot(await blobUrl(`/api/runs/${r.id}/plot.png`)) }, "Plot"),
          el("button", { type: "button", class: "btn csv", onclick: async () => {
            const url = await blobUrl(`/api/runs/${r.id}/log.csv`);
            const a = el("a", { href: url, download: `${serial}-run${r.id}.csv` }); document.body.append(a); a.click(); a.remove();
          } }, "Log CSV"),
          window.diagnoseRun ? el("button", { type: "button", class: "btn diag", onclick: () => window.diagnoseRun(r.id, serial) }, "Diagnose") : null));
      box.append(el("article", { class: "run-card st-" + (r.state || ""), "data-run": r.id }, info, plotBox));
      blobUrl(`/api/runs/${r.id}/plot.png`).then((url) => plotBox.append(
        el("img", { class: "plot-inline", src: url, alt: `plot of run ${r.id}`, onclick: () => showPlot(url) }))).catch(() => {});
    }
  } catch (e) { if (seq === showDutSeq) box.append(el("p", { class: "error" }, e.message)); }
}

function showView(name) {
  for (const v of ["live", "history"]) {
    $("view-" + v).classList.toggle("hidden", v !== name);
    $("tab-" + v).classList.toggle("active", v === name);
  }
}

// ---- start-up --------------------------------------------------------------------------------
async function boot() {
  $("auth").classList.toggle("hidden", !!S.token);
  $("whoami").replaceChildren();
  if (!S.token) { $("auth-msg").textContent = "Sign in with your token to operate the station."; return; }
  try {
    const me = await api("/api/me");
    S.role = me.role;
    $("whoami").replaceChildren(`${me.name} (${me.role})`,
      el("button", { type: "button", class: "btn small", onclick: signOut }, "Sign out"));
    const [profiles, slots, batches] = await Promise.all([api("/api/profiles"), api("/api/slots"), api("/api/batches?limit=1")]);
    const sel = $("profile");
    sel.replaceChildren(...profiles.map((p) => el("option", { value: p.name }, p.description ? `${p.name} — ${p.description}` : p.name)));
    const picks = $("slot-picks");
    picks.replaceChildren(...slots.map((s) => el("label", { class: "slot-pick" },
      el("input", { type: "checkbox", value: s.slot, checked: s.state !== "faulted" && s.state !== "disconnected" ? "checked" : null }), s.slot)));
    S.order = slots.map((s) => s.slot);
    for (const s of slots) {
      const st = slotState(s.slot);
      if (s.serial) st.serial = s.serial;
      if (s.sensor) st.sensor = s.sensor;
      st.state = s.state;
      st.error = s.fault_reason || "";
    }
    if (!S.batchId && batches.length && !FINAL.has(batches[0].state)) S.batchId = batches[0].id;
    message("");
  } catch (e) {
    if (e.status === 401) {
      S.token = "";
      localStorage.removeItem("station.token");
      $("auth").classList.remove("hidden");
      $("auth-msg").textContent = "Token rejected: " + e.message;
    } else message(e.message);
    return;
  }
  connect();
  setBatch(S.batchId);
  if (S.batchId) await pollBatch();
  renderSlots();
  clearInterval(S.pollTimer);
  S.pollTimer = setInterval(pollBatch, 2000);
}

document.addEventListener("DOMContentLoaded", () => {
  $("save-token").addEventListener("click", saveToken);
  $("token").addEventListener("keydown", (e) => { if (e.key === "Enter") saveToken(); });
  $("start").addEventListener("click", startBatch);
  $("abort").addEventListener("click", abortBatch);
  $("pick-all").addEventListener("click", () => pickAll(true));
  $("pick-none").addEventListener("click", () => pickAll(false));
  $("new-batch").addEventListener("click", () => {
    setBatch(null);
    for (const s of S.slots.values()) { delete s.result; delete s.plotUrl; s.segments = 0; s.error = ""; }
    api("/api/slots").then((slots) => { for (const s of slots) slotState(s.slot).state = s.state; renderSlots(); }).catch(() => {});
  });
  $("prompt-confirm").addEventListener("click", confirmPrompt);
  $("search-go").addEventListener("click", search);
  $("search").addEventListener("keydown", (e) => { if (e.key === "Enter") search(); });
  for (const t of document.querySelectorAll(".tab")) t.addEventListener("click", () => showView(t.dataset.view));
  $("operator").value = localStorage.getItem("station.operator") || "";
  boot();
});
