// Operator page: plain JavaScript, no framework, no CDN. Live state comes from server-sent events
// (/api/events); the authoritative batch state is also polled, in its compact view, and what is big
// or seldom changes is fetched once when it changes (status.js). The other parts: cards.js (slot
// cards, sorting, steps, progress), start.js (start form, retest, abort), prompt.js and
// orientation.js (the prompt and its picture), attention.js (tone, title flash, mute); every word the
// page shows comes from i18n.js (t(key) from the catalogs in /static/i18n/), which loads first.
"use strict";

const S = {
  token: localStorage.getItem("station.token") || "",
  role: null,
  batchId: Number(localStorage.getItem("station.batch")) || null,
  batchSlots: null,        // slots of the current batch (null: none yet)
  stepCount: null,
  order: [],               // slot names in the station's order
  slots: new Map(),        // slot -> {slot, serial, state, error, segments, temp_c, acc_g, samples, result, plotUrl,
                           //   rev, revBatch: the slot's fields as fetched for that rev of that batch (status.js)}
  prompt: null,
  es: null,
  pollTimer: null,
  finalBatch: true,
  sorting: [],             // [{slot, serial, verdict, grade, tray, reason, attempt}] of the batch
  steps: [],               // the batch's step list as last fetched (status.js loadSteps), and for which
  stepsKey: null,          // batch, state and running step
  operator: "",            // the person at the station: memory and sessionStorage only (start.js)
  formOpen: false,         // the start form opened over an ended batch ("New batch")
  lastState: null,         // the batch state last shown: an end seen live calls for attention
  retestable: false,       // the ended batch has error, fail or marginal slots
  retest: null,            // the start form is a retest of {batchId, slots} (start.js)
};

const VERDICT_FIELDS = ["verdict", "grade", "tray", "reason", "reason_code", "attempt", "limits_name", "limits_version"];
// The verdict's word (PASS, BESTANDEN, 合格): the catalog's, else the station's own (a new verdict).
const verdictWord = (v) => (v && I18N.has("verdict." + v) ? t("verdict." + v) : (v || ""));

const FINAL = new Set(["finished", "aborted", "failed", "interrupted"]);
// A slot's and a batch's state in words (identified: "ready"); a state the catalog does not know as it is.
const slotStateWord = (st) => (I18N.has("slot_state." + st) ? t("slot_state." + st) : st);
const batchStateWord = (st) => (I18N.has("batch_state." + st) ? t("batch_state." + st) : st);

const $ = (id) => document.getElementById(id);

// What a profile does, in words: a built-in one's (station/profiles.py) from the catalog, by name;
// a site's profile in the words its config gives (the site writes them in its own language).
function profileDescription(p) {
  if (p.builtin && I18N.lang !== "en" && I18N.has("profile.desc." + p.name)) return t("profile.desc." + p.name);
  return p.description || "";
}

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
  return I18N.num(v, digits);  // in the page's language (German 23,5)
}

function message(text) { $("message").textContent = text || ""; delete $("message").dataset.kind; }

async function api(path, opts = {}) {
  const headers = Object.assign({}, opts.headers || {});
  if (S.token) headers["Authorization"] = "Bearer " + S.token;
  // who acts (the audit names the person, not only the kiosk's token); percent-encoded: a header
  // carries Latin-1 only, names do not
  if (opts.method && opts.method !== "GET" && S.operator) headers["X-Operator"] = encodeURIComponent(S.operator);
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
  forgetOperator();  // start.js: the next person starts with an empty Operator field
  hidePrompt();
  if (S.es) S.es.close();
  clearInterval(S.pollTimer);
  boot();
}

// ---- batch -----------------------------------------------------------------------------------
function setBatch(id) {
  S.batchId = id;
  if (id) localStorage.setItem("station.batch", String(id)); else localStorage.removeItem("station.batch");
  if (!id) { S.batchSlots = null; S.finalBatch = true; S.retestable = false; }
  $("batch-panel").classList.toggle("hidden", !id);
  $("batch-id").textContent = id || "";
  showControls();
}

// At the end of a batch its verdicts and the sorting view stay on top: the start form collapses to
// "New batch" (and "Retest failed" when some slot failed) until the operator opens it.
function showControls() {
  const ctl = canControl();
  const ended = !!S.batchId && S.finalBatch;
  $("start-panel").classList.toggle("hidden", !ctl || !(!S.batchId || (ended && S.formOpen)));
  $("start-cancel").classList.toggle("hidden", !ended);
  $("abort").classList.toggle("hidden", !S.batchId || S.finalBatch || !ctl);
  $("new-batch").classList.toggle("hidden", !ended || S.formOpen || !ctl);
  $("retest").classList.toggle("hidden", !ended || !S.retestable || !ctl);
  $("batch-panel").classList.toggle("ended", ended);
}

function setLamp(on, state) {
  // state 'unknown': the relay does not answer, the lamp may be on whatever was commanded.
  const unknown = state === "unknown";
  $("lamp").textContent = t(unknown ? "lamp.unknown" : (on ? "lamp.on" : "lamp.off"));
  $("lamp").className = "chip " + (unknown ? "lamp-unknown" : (on ? "lamp-on" : "lamp-off"));
  $("lamp").title = unknown ? t("lamp.unknown_title") : "";
  $("batch-panel").classList.toggle("lamp-alert", unknown || !!on);  // still shown after the end
}

// Program and verify (design 4): programmed (CRC read back), compensation on, verified E per axis.
function programVerifyTable(p, v) {
  const wrap = el("div", { class: "program-verify" });
  if (p) {
    const ok = p.programmed && p.readback_identical !== false;
    wrap.append(el("div", { class: "programmed " + (ok ? "ok" : "bad") },
      ok ? t("program.programmed", { crc: p.crc }) + (p.attempts > 1 ? " " + t("program.tries", { n: p.attempts }) : "")
           + " · " + t(p.comp ? "program.comp_on" : "program.comp_off")
         : t("program.not_programmed", { kind: p.error_kind || t("program.error") })));
  }
  if (v && v.e_after_mg) {
    const rows = ["x", "y", "z"].map((ax) => {
      const a = (v.axes || {})[ax] || {};
      return el("tr", { "data-axis": ax, class: a.passed === false ? "bad" : "" }, el("td", {}, ax),
        el("td", { class: "e-before" }, fmt((v.e_before_mg || {})[ax], 1)), el("td", { class: "e-after" }, fmt(v.e_after_mg[ax], 1)));
    });
    wrap.append(el("table", { class: "results verify" },
      el("thead", {}, el("tr", {}, el("th", {}, t("result.axis")), el("th", {}, t("program.e_before")), el("th", {}, t("program.e_verified")))),
      el("tbody", {}, ...rows)));
    wrap.append(el("div", { class: "verdict " + (v.passed ? "ok" : "bad") }, t(v.passed ? "program.verified" : "program.verify_failed")));
    for (const f of v.flags || []) wrap.append(el("div", { class: "flag" }, f));
  }
  return wrap;
}

// ---- live events -----------------------------------------------------------------------------
function onEvent(ev) {
  // a batch that starts (here, elsewhere, a retest) takes the page over from an ended one
  if (ev.kind === "BatchStateChanged" && ev.state === "running" && ev.batch_id !== S.batchId
      && (!S.batchId || (S.finalBatch && ev.batch_id > S.batchId))) {
    if (S.batchId) clearSlotsForNewBatch();
    S.formOpen = false; S.lastState = null;
    setBatch(ev.batch_id); S.finalBatch = false; pollBatch();
  }
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
      if ((ev.fault_reason || "") !== s.error) s.error_code = null;  // the event has no code: the slot's fields (status.js) bring it
      s.error = ev.fault_reason || "";
      break;
    }
    case "SegmentLogged": {
      const s = slotState(ev.slot);
      s.segments = Math.max(s.segments || 0, (ev.segment && ev.segment.index + 1) || (s.segments || 0) + 1);
      break;
    }
    case "StepStarted":
      $("batch-step").textContent = `${ev.step_index + 1} / ${S.stepCount ?? "?"} · ${stepName(ev.step_name)}`;
      pollBatch();  // the step list and progress move on now, not at the next poll
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
    case "PromptAnswered": if (S.prompt && promptId(S.prompt) === ev.prompt_id) hidePrompt(); break;
    case "LampChanged": setLamp(ev.on); break;
    case "BatchStateChanged":
      $("batch-state").textContent = batchStateWord(ev.state);
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
  S.es.onopen = () => { $("conn").textContent = t("conn.live"); $("conn").className = "conn on"; };
  S.es.onerror = () => { $("conn").textContent = t("conn.reconnecting"); $("conn").className = "conn off"; };
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
    if (!duts.length) list.append(el("p", { class: "muted" }, t("history.no_dut")));
    for (const d of duts) {
      list.append(el("button", { type: "button", class: "btn dut", "data-serial": d.serial, onclick: () => showDut(d.serial) },
        t(d.runs === 1 ? "history.dut_one_run" : "history.dut_runs", { serial: d.serial, n: d.runs })));
    }
    if (duts.length === 1) showDut(duts[0].serial);
  } catch (e) { list.append(el("p", { class: "error" }, e.message)); }
}

function localTime(iso) { return iso ? I18N.dateTime(iso) : "–"; }  // in the page's language

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
        } }, t("history.certificate")), msg));
    }
    if (!runs.length) box.append(el("p", { class: "muted" }, t("history.no_run")));
    for (const r of runs) {
      const plotBox = el("div", { class: "plot-box" });
      const info = el("div", {},
        el("h3", {}, t("history.run_head", { id: r.id, state: r.state ? slotStateWord(r.state) : "" })),
        el("div", { class: "muted" }, t("history.run_where", { batch: r.batch_id ?? "–", slot: r.slot ?? "–", profile: r.profile ?? "" })),
        el("div", { class: "muted" }, `${localTime(r.started_at)} → ${localTime(r.finished_at)}`),
        r.verdict ? el("div", { class: "run-verdict v-" + r.verdict, "data-verdict": r.verdict },
          `${verdictWord(r.verdict)}${r.grade ? " · " + t("verdict.grade", { grade: gradeWord(r.grade) }) : ""}`
          + (r.attempt === 0 ? " · " + t("verdict.no_attempt") : " · " + t("verdict.attempt", { n: r.attempt ?? "?" }))
          + (r.limits_name ? " · " + t("verdict.limits", { name: r.limits_name, version: r.limits_version }) : "")
          + (r.reason ? " · " : ""), ...(r.reason ? reasonNodes(r.reason_code, r.reason) : [])) : null,
        r.fault_reason ? el("div", { class: "fault" }, t("slot.fault") + " ", ...reasonNodes(r.fault_code, r.fault_reason)) : null,
        (r.thermal || r.sfem) ? resultTable(storedResult(r)) : el("div", { class: "muted" }, t("result.none")),
        el("div", { class: "actions" },
          el("button", { type: "button", class: "btn plot", onclick: async () => showPlot(await blobUrl(`/api/runs/${r.id}/plot.png`)) }, t("history.plot")),
          el("button", { type: "button", class: "btn csv", onclick: async () => {
            const url = await blobUrl(`/api/runs/${r.id}/log.csv`);
            const a = el("a", { href: url, download: `${serial}-run${r.id}.csv` }); document.body.append(a); a.click(); a.remove();
          } }, t("history.log_csv")),
          window.diagnoseRun ? el("button", { type: "button", class: "btn diag", onclick: () => window.diagnoseRun(r.id, serial) }, t("history.diagnose")) : null));
      box.append(el("article", { class: "run-card st-" + (r.state || ""), "data-run": r.id }, info, plotBox));
      blobUrl(`/api/runs/${r.id}/plot.png`).then((url) => plotBox.append(
        el("img", { class: "plot-inline", src: url, alt: t("history.plot_alt", { id: r.id }), onclick: () => showPlot(url) }))).catch(() => {});
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

// ---- the station's database ----------------------------------------------------------------
// /api/health never waits on the database: it says whether the database answers and what waits
// in the station's journal to be forwarded. Tests go on through an outage; the operator sees why
// a new batch is refused and that the records are kept on the station.
function storageText(h) {
  const waiting = (h.forwarding && h.forwarding.events) || 0;
  const batches = Object.keys((h.forwarding && h.forwarding.batches) || {}).filter((b) => b !== "0");
  const kept = waiting ? " " + t(batches.length ? "storage.waiting_batches" : "storage.waiting", { n: waiting, batches: batches.join(", ") }) : "";
  if (h.db && h.db.startsWith("error")) return [t("storage.down", { why: h.db.slice(7).split(";")[0] }) + kept, true];
  if (waiting) return [t("storage.back") + kept, false];
  return ["", false];
}

async function pollStorage() {
  try {
    const r = await fetch("/api/health", { cache: "no-store" });
    const h = await r.json();
    showOverload("health", h.intake && h.intake.alarm);  // status.js
    const [text, down] = storageText(h);
    $("storage").textContent = text;
    $("storage").classList.toggle("down", down);
    $("storage").classList.toggle("hidden", !text);
  } catch (e) { /* the page's own connection state says offline */ }
}

// ---- start-up --------------------------------------------------------------------------------
async function boot() {
  $("auth").classList.toggle("hidden", !!S.token);
  $("whoami").replaceChildren();
  if (!S.token) {
    $("auth-msg").textContent = t("auth.sign_in_hint");
    setBatch(null);
    $("batch-panel").classList.add("hidden");
    return;
  }
  try {
    const me = await api("/api/me");
    S.role = me.role;
    // the token's name is the config's (the site's words); its role in the page's language
    const role = I18N.has("role." + me.role) ? t("role." + me.role) : me.role;
    $("whoami").replaceChildren(el("span", { class: "who-name", title: `${me.name} (${role})` },
      el("span", { class: "site-words" }, me.name), ` (${role})`),
      el("button", { type: "button", class: "btn small", id: "sign-out", onclick: signOut }, t("auth.sign_out")));
    const [profiles, slots, batches] = await Promise.all([api("/api/profiles"), api("/api/slots"), api("/api/batches?limit=1&view=compact")]);
    const sel = $("profile");
    // a built-in profile's description in the page's language; a site's own as its config says it
    sel.replaceChildren(...profiles.map((p) => el("option", { value: p.name, class: p.builtin ? null : "site-words" },
      profileDescription(p) ? `${p.name} — ${profileDescription(p)}` : p.name)));
    S.profiles = new Map(profiles.map((p) => [p.name, p]));
    describeProfile();
    renderSlotPicks(slots);
    S.order = slots.map((s) => s.slot);
    for (const s of slots) {
      const st = slotState(s.slot);
      if (s.serial) st.serial = s.serial;
      if (s.sensor) st.sensor = s.sensor;
      st.state = s.state;
      st.error = s.fault_reason || "";
      st.error_code = s.error_code || null;
    }
    // the newest batch, ended ones too: after a reload its verdicts and sorting are still on top
    if (batches.length) S.batchId = batches[0].id;
    message("");
  } catch (e) {
    if (e.status === 401) {
      S.token = "";
      localStorage.removeItem("station.token");
      $("auth").classList.remove("hidden");
      $("auth-msg").textContent = t("auth.rejected", { why: e.message });
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
  I18N.ready.then(() => { pollStorage(); setInterval(pollStorage, 3000); });  // its words need the catalog
  $("save-token").addEventListener("click", saveToken);
  $("token").addEventListener("keydown", (e) => { if (e.key === "Enter") saveToken(); });
  $("search-go").addEventListener("click", search);
  $("search").addEventListener("keydown", (e) => { if (e.key === "Enter") search(); });
  for (const tab of document.querySelectorAll(".tab")) tab.addEventListener("click", () => showView(tab.dataset.view));
  I18N.ready.then(boot);  // the catalog first: every view is built in the page's language
});
