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
  sorting: [],             // [{slot, serial, verdict, grade, tray, reason, attempt}] of the batch
};

const VERDICT_FIELDS = ["verdict", "grade", "tray", "reason", "attempt", "limits_name", "limits_version"];
const VERDICT_WORD = { pass: "PASS", marginal: "MARGINAL", fail: "FAIL", error: "ERROR" };

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
    card.className = "slot-card st-" + state + (s.verdict && inBatch(name) ? " has-verdict v-" + s.verdict : "");
    card.dataset.state = state;
    if (s.verdict && inBatch(name)) card.dataset.verdict = s.verdict; else delete card.dataset.verdict;
    const active = inBatch(name) && S.batchId;
    const acc = Array.isArray(s.acc_g) ? s.acc_g.map((v) => fmt(v, 3)).join("  ") : "–";
    // one dot per profile step, lit for the steps this DUT has actually completed (not segments)
    const need = S.stepCount || 4;
    const done = s.steps_done ?? 0;
    const dots = el("span", { class: "dots", "aria-hidden": "true", title: `${done} of ${need} steps done` });
    for (let i = 0; i < Math.min(need, 40); i++) dots.append(el("span", { class: i < done ? "dot on" : "dot" }));
    card.replaceChildren(...[
      el("header", {}, el("h2", {}, name), el("span", { class: "st" }, STATE_LABEL[state] || state)),
      el("div", { class: "serial" }, s.serial || "no DUT", s.sensor ? el("span", { class: "muted" }, " · " + s.sensor) : null),
      active ? el("div", { class: "live" },
        el("span", { class: "temp" }, s.temp_c === undefined || s.temp_c === null ? "– °C" : fmt(s.temp_c, 1) + " °C"),
        el("span", { class: "segbox" }, "Segments ", el("b", { class: "segments" }, String(s.segments || 0)), " · Steps ", dots)) : null,
      active ? el("dl", {},
        el("dt", {}, "Acc x y z (g)"), el("dd", { class: "acc" }, acc),
        el("dt", {}, "Samples"), el("dd", { class: "samples" }, String(s.samples ?? 0)),
      ) : el("div", { class: "muted" }, S.batchId && !S.finalBatch ? "not in this batch" : ""),
      active && s.verdict ? verdictBlock(s) : null,
      active && !s.verdict && s.tempHist && s.tempHist.length > 1 ? sparkline(s.tempHist) : null,
      active && s.waiting_for && !S.finalBatch ? el("div", { class: "waiting muted" }, "waiting for ", el("b", { class: "waiting-for" }, s.waiting_for)) : null,
      s.error && !s.verdict ? el("div", { class: "fault" }, "Fault: " + s.error) : null,
      active && s.result ? resultTable(s.result) : null,
      active && (s.program || s.verification) ? programVerifyTable(s.program, s.verification) : null,
      active && s.plotUrl ? el("img", { class: "plot-thumb", src: s.plotUrl, alt: s.plotAlt || "plot of " + (s.serial || name), onclick: () => showPlot(s.plotUrl) }) : null,
    ].filter((c) => c !== null && c !== undefined && c !== false));
  }
}

// The decision, big enough to read from two metres: verdict word, grade, tray, reason.
function verdictBlock(s) {
  return el("div", { class: "verdict v-" + s.verdict, "data-verdict": s.verdict },
    el("div", { class: "verdict-head" },
      el("span", { class: "verdict-word" }, VERDICT_WORD[s.verdict] || s.verdict),
      s.grade ? el("span", { class: "grade" + (s.grade.length > 2 ? " long" : ""), title: "grade" }, s.grade) : null),
    el("div", { class: "reason" }, s.reason || ""),
    el("div", { class: "tray-line" }, "→ ", el("b", { class: "tray" }, s.tray || "–"),
      s.attempt > 1 ? el("span", { class: "attempt" }, ` · attempt ${s.attempt}`) : null));
}

// Live temperature of one slot (the last few minutes), an SVG line with its range.
function sparkline(hist) {
  const w = 360, h = 60;
  const ts = hist.map((p) => p[1]);
  const lo = Math.min(...ts), hi = Math.max(...ts);
  const span = Math.max(hi - lo, 1);
  const t0 = hist[0][0], t1 = hist[hist.length - 1][0] || t0 + 1;
  const pts = hist.map(([t, v]) => `${((t - t0) / Math.max(t1 - t0, 1e-9) * w).toFixed(1)},${(h - 4 - (v - lo) / span * (h - 8)).toFixed(1)}`).join(" ");
  // numbers only go into the markup; the HTML parser puts <svg> in the SVG namespace by itself
  const box = el("div", { class: "spark-box" });
  box.innerHTML = `<svg viewBox="0 0 ${w} ${h}" class="spark" role="img" aria-label="temperature ${fmt(lo, 1)} to ${fmt(hi, 1)} °C">`
    + `<polyline points="${pts}"></polyline></svg>`;
  box.append(el("span", { class: "muted" }, `${fmt(lo, 1)}–${fmt(hi, 1)} °C`));
  return box;
}

function clock(sec) {
  if (sec === null || sec === undefined || Number.isNaN(Number(sec))) return "–";
  const s = Math.max(0, Math.round(Number(sec)));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
  return (h ? h + ":" + String(m).padStart(2, "0") : String(m)) + ":" + String(r).padStart(2, "0");
}

// Which slot goes to which tray: one row per tray, the slots in it.
function renderSorting(b) {
  const box = $("sorting");
  const list = S.sorting || [];
  box.classList.toggle("hidden", !list.length);
  if (!list.length) return;
  const trays = new Map();
  for (const e of list) {
    const key = e.tray || e.grade || e.verdict;
    if (!trays.has(key)) trays.set(key, []);
    trays.get(key).push(e);
  }
  const rank = { pass: 0, marginal: 1, fail: 2, error: 3 };
  const rows = [...trays.entries()].sort((a, b2) => (rank[a[1][0].verdict] - rank[b2[1][0].verdict]) || a[0].localeCompare(b2[0]));
  $("trays").replaceChildren(...rows.map(([tray, es]) => el("div", { class: "tray-row v-" + es[0].verdict, "data-tray": tray },
    el("div", { class: "tray-name" }, tray),
    el("div", { class: "tray-slots" }, ...es.map((e) => el("span", { class: "tray-slot", "data-slot": e.slot, title: e.reason || "" },
      e.slot, el("small", {}, " " + (e.serial || ""))))))));
  const d = (b && b.decision && b.decision.verdicts) || {};
  $("yield-line").textContent = `${d.pass || 0} pass · ${d.marginal || 0} marginal · ${d.fail || 0} fail · ${d.error || 0} error`;
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

// A positive TDSF is clamped to 0 by the method (martinez2022): it was not observable in this run.
// A bare "0.0" would read as a measured zero, so the cell says so, as the API (tdsf_clamped) and
// the certificate do.
function tdsfCell(a) {
  if (!a.tdsf_clamped) return el("td", { class: "tdsf" }, fmt(a.tdsf_ppm_per_c, 1));
  return el("td", { class: "tdsf clamped", title: "positive TDSF clamped to 0: not observable in this run" },
    fmt(a.tdsf_ppm_per_c, 1) + " ", el("span", { class: "clamped-flag" }, "(clamped: not observable)"));
}

function resultTable(result) {
  const wrap = el("div", { class: "result" });
  if (result.axes) {
    const rows = ["x", "y", "z"].map((ax) => {
      const a = result.axes[ax] || {};
      return el("tr", { "data-axis": ax }, el("td", {}, ax), el("td", { class: "tdb" }, fmt(a.tdb_mg_per_c, 3)),
        tdsfCell(a));
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

// Program and verify (design 4): programmed (CRC read back), compensation on, verified E per axis.
function programVerifyTable(p, v) {
  const wrap = el("div", { class: "program-verify" });
  if (p) {
    const ok = p.programmed && p.readback_identical !== false;
    wrap.append(el("div", { class: "programmed " + (ok ? "ok" : "bad") },
      ok ? `Programmed · CRC ${p.crc}` + (p.attempts > 1 ? ` (${p.attempts} tries)` : "") + " · compensation " + (p.comp ? "on" : "OFF")
         : `Not programmed: ${p.error_kind || "error"}`));
  }
  if (v && v.e_after_mg) {
    const rows = ["x", "y", "z"].map((ax) => {
      const a = (v.axes || {})[ax] || {};
      return el("tr", { "data-axis": ax, class: a.passed === false ? "bad" : "" }, el("td", {}, ax),
        el("td", { class: "e-before" }, fmt((v.e_before_mg || {})[ax], 1)), el("td", { class: "e-after" }, fmt(v.e_after_mg[ax], 1)));
    });
    wrap.append(el("table", { class: "results verify" },
      el("thead", {}, el("tr", {}, el("th", {}, "axis"), el("th", {}, "E before mg"), el("th", {}, "E verified mg"))),
      el("tbody", {}, ...rows)));
    wrap.append(el("div", { class: "verdict " + (v.passed ? "ok" : "bad") }, v.passed ? "Verified" : "Verification failed"));
    for (const f of v.flags || []) wrap.append(el("div", { class: "flag" }, f));
  }
  return wrap;
}

function showPlot(url) {
  $("plot-img").src = url;
  $("plot-dialog").showModal();
}

// The plot of THIS slot's run in this batch (by run id, from the batch status): never the serial's
// latest run, so an interrupted or faulted DUT shows its own data.
async function loadPlot(slot) {
  const s = slotState(slot);
  if (!s.runId || s.plotUrl || s.plotLoading) return;
  s.plotLoading = true;
  try {
    const run = await api(`/api/runs/${s.runId}`);
    // Not stored to its end yet (samples, state, result still being written): the next poll retries,
    // so the card never keeps a plot of half a run. A run's end is stored after its result.
    if (!run.finished_at) return;
    if (run.thermal || run.sfem) s.result = storedResult(run);
    s.plotAlt = `plot of ${s.serial || slot} run ${s.runId} (${run.state})`;
    s.plotUrl = await blobUrl(s.plotPath || `/api/runs/${s.runId}/plot.png`);
    renderSlots();
  } catch (e) { /* retried on the next poll */ } finally { s.plotLoading = false; }
}

// The chosen profile in words: its description, step count, and what it yields.
function describeProfile() {
  const p = S.profiles && S.profiles.get($("profile").value);
  const box = $("profile-desc");
  if (!box) return;
  if (!p) { box.textContent = ""; return; }
  const yields = { thermal: "TDB/TDSF calibration result", sfem: "SFEM result", none: "no calibration result (logs data only)" };
  box.textContent = `${p.description || p.name} · ${p.n_steps ?? "?"} steps · ${yields[p.analysis] || p.analysis || ""}`;
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

function setLamp(on, state) {
  // state 'unknown': the relay does not answer, the lamp may be on whatever was commanded.
  const unknown = state === "unknown";
  $("lamp").textContent = unknown ? "UNKNOWN" : (on ? "ON" : "OFF");
  $("lamp").className = "chip " + (unknown ? "lamp-unknown" : (on ? "lamp-on" : "lamp-off"));
  $("lamp").title = unknown ? "lamp relay not answering: lamp state unknown" : "";
}

function applyBatch(b) {
  $("batch-profile").textContent = b.profile || "";
  $("batch-state").textContent = b.state;
  $("batch-state").dataset.state = b.state;
  S.stepCount = (b.step && b.step.count) || S.stepCount;
  if (b.step && b.step.index !== null && b.step.index !== undefined) {
    $("batch-step").textContent = `${b.step.index + 1} / ${b.step.count ?? "?"} · ${b.step.name ?? ""}`;
  }
  if (b.lamp_on !== undefined) setLamp(b.lamp_on, b.lamp_state);
  $("batch-error").textContent = b.error || "";  // e.g. "aborted by Ana at 2026-11-23 14:02:05 UTC"
  $("batch-note").textContent = b.note || "";
  $("batch-note").classList.toggle("hidden", !b.note);
  $("batch-elapsed").textContent = clock(b.elapsed_s);
  $("batch-waiting").textContent = b.waiting_for || "–";
  S.batchSlots = (b.slots || []).map((sl) => sl.slot);
  const counts = { running: 0, done: 0, faulted: 0 };
  for (const sl of b.slots || []) {
    const s = slotState(sl.slot);
    for (const k of ["serial", "state", "segments", "samples", "sensor", "program", "verification", "steps_done"]) if (sl[k] !== null && sl[k] !== undefined) s[k] = sl[k];
    s.waiting_for = sl.waiting_for || null;
    if (sl.run_id && sl.run_id !== s.runId) { s.runId = sl.run_id; delete s.plotUrl; delete s.result; }
    s.plotPath = sl.plot_url || null;
    const pv = sl.program_verify;  // a stored batch: the run's program_verify row
    if (pv && !sl.program) {
      s.program = { programmed: pv.programmed, crc: pv.crc, readback_identical: pv.readback_identical, comp: pv.comp_on,
        attempts: pv.attempts, error_kind: pv.error_kind };
      if (pv.verified !== null && pv.verified !== undefined) {
        s.verification = { passed: pv.verified, e_before_mg: pv.e_before_mg, e_after_mg: pv.e_after_mg, flags: pv.flags };
      }
    }
    for (const k of VERDICT_FIELDS) s[k] = sl[k] ?? null;
    s.error = sl.error || "";
    if (sl.state in counts) counts[sl.state] += 1;
    else if (sl.state === "interrupted") counts.interrupted = (counts.interrupted || 0) + 1;
    else if (!FINAL.has(sl.state)) counts.running += 1;
    if (["done", "interrupted", "faulted"].includes(s.state) && !s.plotUrl) loadPlot(sl.slot);
  }
  const c = b.counts || counts;  // the station's own count: no DUT runs once the batch ended
  $("batch-counts").textContent = `${c.running || 0} running · ${c.done || 0} done · ${c.faulted || 0} faulted`
    + (c.interrupted ? ` · ${c.interrupted} interrupted` : "");
  S.finalBatch = FINAL.has(b.state);
  const left = b.time_left || {};
  $("step-left").textContent = S.finalBatch ? "–" : clock(left.step_wall_s);
  $("batch-left").textContent = S.finalBatch ? "–" : clock(left.batch_wall_s);
  for (const id of ["time-left-step", "time-left-batch"]) $(id).classList.toggle("hidden", S.finalBatch);
  S.sorting = b.sorting || [];
  renderSorting(b);
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
      delete s.result; delete s.plotUrl; delete s.temp_c; delete s.acc_g; delete s.tempHist; delete s.program; delete s.verification;
      delete s.runId; delete s.plotPath; delete s.waiting_for; s.steps_done = 0;
      for (const k of VERDICT_FIELDS) s[k] = null;
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
        if (typeof v.temp_c === "number") {
          s.tempHist = s.tempHist || [];
          s.tempHist.push([Date.now() / 1000, v.temp_c]);
          if (s.tempHist.length > 600) s.tempHist.splice(0, s.tempHist.length - 600);
        }
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
    case "DutVerdict": pollBatch(); break;
    case "DutProgrammed": slotState(ev.slot).program = ev.program; break;
    case "DutVerified": slotState(ev.slot).verification = ev.verification; break;
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
    if (runs.some((r) => r.result_seq != null || r.verdict)) {
      // the calibration certificate of the serial's result run (PDF, station/records/certificate.py)
      const msg = el("span", { class: "muted cert-msg" });
      box.append(el("div", { class: "actions" },
        el("button", { type: "button", class: "btn certificate", "data-serial": serial, onclick: async () => {
          msg.textContent = "";
          try {
            const url = await blobUrl(`/api/duts/${encodeURIComponent(serial)}/certificate.pdf`);
            const a = el("a", { href: url, download: `certificate-${serial}.pdf` }); document.body.append(a); a.click(); a.remove();
          } catch (e) { msg.textContent = e.message; }
        } }, "Certificate (PDF)"), msg));
    }
    if (!runs.length) box.append(el("p", { class: "muted" }, "No run stored."));
    for (const r of runs) {
      const plotBox = el("div", { class: "plot-box" });
      const info = el("div", {},
        el("h3", {}, `Run ${r.id} · ${r.state ?? ""}`),
        el("div", { class: "muted" }, `batch ${r.batch_id ?? "–"} · slot ${r.slot ?? "–"} · ${r.profile ?? ""}`),
        el("div", { class: "muted" }, `${when(r.started_at)} → ${when(r.finished_at)}`),
        r.verdict ? el("div", { class: "run-verdict v-" + r.verdict, "data-verdict": r.verdict },
          `${VERDICT_WORD[r.verdict] || r.verdict}${r.grade ? " · grade " + r.grade : ""} · attempt ${r.attempt ?? "?"}`
          + (r.reason ? " · " + r.reason : "") + (r.limits_name ? ` · limits ${r.limits_name} v${r.limits_version}` : "")) : null,
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
  for (const v of ["live", "history", "records"]) {
    $("view-" + v).classList.toggle("hidden", v !== name);
    $("tab-" + v).classList.toggle("active", v === name);
  }
  if (name === "records" && window.loadRecords) window.loadRecords();  // records.js
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
    S.profiles = new Map(profiles.map((p) => [p.name, p]));
    describeProfile();
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
  $("profile").addEventListener("change", describeProfile);
  $("abort").addEventListener("click", abortBatch);
  $("pick-all").addEventListener("click", () => pickAll(true));
  $("pick-none").addEventListener("click", () => pickAll(false));
  $("new-batch").addEventListener("click", () => {
    setBatch(null);
    for (const s of S.slots.values()) {
      delete s.result; delete s.plotUrl; delete s.tempHist; s.segments = 0; s.error = "";
      delete s.runId; delete s.plotPath; delete s.waiting_for; s.steps_done = 0;
      for (const k of VERDICT_FIELDS) s[k] = null;
    }
    S.sorting = [];
    renderSorting(null);
    api("/api/slots").then((slots) => { for (const s of slots) slotState(s.slot).state = s.state; renderSlots(); }).catch(() => {});
  });
  $("prompt-confirm").addEventListener("click", confirmPrompt);
  $("search-go").addEventListener("click", search);
  $("search").addEventListener("keydown", (e) => { if (e.key === "Enter") search(); });
  for (const t of document.querySelectorAll(".tab")) t.addEventListener("click", () => showView(t.dataset.view));
  $("operator").value = localStorage.getItem("station.operator") || "";
  boot();
});
