// Starting a batch: who runs it, what is tested (work order, part, revision, lot) and the serial on
// each part's label, typed or scanned. Barcode scanners type like a keyboard and end with Enter, so
// Enter in a field moves to the next field and never starts a batch by accident; only the Start
// button does. The operator's name is required and is a person's, not the station's: it lives in
// memory and sessionStorage only and is forgotten on sign-out (a shared kiosk must not hand the last
// name to the next person). Also Retest failed and Abort. Uses app.js (S, el, $, api, message,
// setBatch, pollBatch, showControls) and i18n.js (t).
"use strict";

const TRACE_FIELDS = [["work-order", "work_order"], ["part-number", "part_number"], ["part-revision", "part_revision"], ["lot", "lot"]];
// The verdicts "Retest failed" takes again (station/daemon/batches.py RETEST_VERDICTS): error, fail,
// and marginal, whose tray is "hold (review / retest)": a retest is the way out of hold.
const RETEST_VERDICTS = new Set(["error", "fail", "marginal"]);

function operatorName() { return (S.operator || "").trim(); }

function setOperator(name, typing = false) {
  S.operator = (name || "").trim();
  if (S.operator) sessionStorage.setItem("station.operator", S.operator);
  else sessionStorage.removeItem("station.operator");
  if (!typing && $("operator").value.trim() !== S.operator) $("operator").value = S.operator;
  $("operator").classList.remove("invalid");
  $("operator").removeAttribute("aria-invalid");
  if (S.operator && $("message").dataset.kind === "operator-required") message("");
}

// Sign-out (and an old page's stored name): nothing of the person stays in the browser.
function forgetOperator() {
  S.operator = "";
  sessionStorage.removeItem("station.operator");
  localStorage.removeItem("station.operator");  // the old page kept the last name here for the next person
  $("operator").value = "";
}

function requireOperator(what) {
  const name = operatorName() || $("operator").value.trim();
  if (name) { setOperator(name); return name; }
  $("operator").classList.add("invalid");
  $("operator").setAttribute("aria-invalid", "true");
  message(t(what === "retest" ? "start.operator_required_retest" : "start.operator_required_start"));
  $("message").dataset.kind = "operator-required";  // cleared once a name is typed (setOperator)
  return "";
}

// The chosen profile in words: its description, step count, and what it yields.
function describeProfile() {
  const p = S.profiles && S.profiles.get($("profile").value);
  const box = $("profile-desc");
  if (!box) return;
  if (!p) { box.textContent = ""; return; }
  const yields = I18N.has("profile.yields_" + p.analysis) ? t("profile.yields_" + p.analysis) : (p.analysis || "");
  box.replaceChildren(el("span", { class: p.builtin ? "" : "site-words" }, profileDescription(p) || p.name),
    ` · ${t("profile.steps", { n: p.n_steps ?? "?" })} · ${yields}`);
}

// One row per slot: the tick box and the label serial of the part in it. A ready slot is ticked; a
// faulted one (its board did not answer at the last batch's end: link lost, port gone) shows why and
// can still be ticked: the batch's connect tries it again. `retest` (a Set): the retest form, only
// those slots ticked and choosable, their labels empty to be scanned again. Without it the form is
// a new batch's (and leaves a retest).
function renderSlotPicks(slots, retest = null) {
  if (!retest) setRetest(null);
  $("slot-picks").replaceChildren(...slots.map((s) => {
    const on = retest ? retest.has(s.slot) : s.state !== "faulted" && s.state !== "disconnected";
    const label = el("input", { type: "text", class: "label-serial scan", "data-slot": s.slot, maxlength: "64", autocomplete: "off",
      placeholder: t("start.label_serial"), "aria-label": t("start.label_serial_of", { slot: s.slot }), disabled: on ? null : "disabled" });
    const box = el("input", { type: "checkbox", value: s.slot, checked: on ? "checked" : null,
      disabled: retest && !on ? "disabled" : null, onchange: () => { label.disabled = !box.checked; } });
    const row = el("div", { class: "slot-row", "data-state": s.state || "" }, el("label", { class: "slot-pick" }, box, s.slot), label);
    // why a slot is not ready: its fault, or an identity a batch would refuse (a serial two boards
    // report, an empty one): the operator sees it before pressing Start
    const why = s.state === "faulted" ? s.fault_reason : s.identity_problem;
    if (!why) return row;
    return el("div", { class: "slot-cell" }, row, el("div", { class: "muted slot-why", "data-slot": s.slot, title: why },
      ...reasonNodes(s.state === "faulted" ? s.error_code : null, why)));
  }));
}

function pickAll(on) {
  for (const i of document.querySelectorAll("#slot-picks input[type=checkbox]:not(:disabled)")) {
    i.checked = on;
    i.dispatchEvent(new Event("change"));
  }
}

// The scan order: operator, work order, part, revision, lot, then the chosen slots' labels, then Start.
function scanOrder() {
  return [$("operator"), ...TRACE_FIELDS.map(([id]) => $(id)).filter((i) => !i.disabled),
    ...document.querySelectorAll("#slot-picks input.label-serial:not(:disabled)"), $("start")];
}

function onScanKey(e) {
  if (e.key !== "Enter" || !e.target.classList.contains("scan")) return;
  e.preventDefault();  // a scanner's Enter is the end of a code, never "start the batch"
  if (e.target.id === "operator") setOperator(e.target.value);
  const order = scanOrder();
  const next = order[order.indexOf(e.target) + 1];
  if (next) { next.focus(); if (next.select) next.select(); }
}

function startBody(picks, all) {
  const body = { profile: $("profile").value, operator: operatorName(), slots: picks.length === all ? null : picks };
  for (const [id, key] of TRACE_FIELDS) body[key] = $(id).value.trim();
  const labels = {};
  for (const i of document.querySelectorAll("#slot-picks input.label-serial:not(:disabled)")) {
    if (i.value.trim()) labels[i.dataset.slot] = i.value.trim();
  }
  body.labels = labels;
  return body;
}

// What the page forgets of the last batch when a new one starts on the same slots.
function clearSlotsForNewBatch() {
  for (const s of S.slots.values()) {
    delete s.result; delete s.plotUrl; delete s.temp_c; delete s.acc_g; delete s.tempHist; delete s.program; delete s.verification;
    delete s.runId; delete s.plotPath; delete s.waiting_for; delete s.label_serial; delete s.rev; s.steps_done = 0;
    for (const k of VERDICT_FIELDS) s[k] = null;
    s.segments = 0; s.samples = 0; s.error = "";
  }
}

async function began(id, slots) {
  clearSlotsForNewBatch();
  S.batchSlots = slots;
  S.finalBatch = false;
  S.formOpen = false;
  S.lastState = null;
  setBatch(id);
  message("");
  await pollBatch();
  refreshSlotStates();  // a slot left out of this batch shows its own state, not the last batch's
}

function refreshSlotStates(picks = false) {
  return api("/api/slots").then((slots) => {
    if (picks) renderSlotPicks(slots);
    for (const s of slots) if (!inBatch(s.slot)) slotState(s.slot).state = s.state;
    renderSlots();
  }).catch(() => {});
}

async function startBatch() {
  if (S.retest) { await startRetest(); return; }
  const picks = [...document.querySelectorAll("#slot-picks input[type=checkbox]:checked")].map((i) => i.value);
  const all = document.querySelectorAll("#slot-picks input[type=checkbox]").length;
  if (!requireOperator("start")) { $("operator").focus(); return; }
  const body = startBody(picks, all);
  if (body.slots && !body.slots.length) { message(t("start.choose_slot")); return; }
  $("start").disabled = true;
  try {
    const r = await api("/api/batches", { method: "POST", body });
    for (const i of document.querySelectorAll("#slot-picks input.label-serial")) i.value = "";  // the next parts have other labels
    await began(r.id, body.slots || [...S.slots.keys()]);
  } catch (e) {
    message(t("start.could_not_start", { why: e.message }));
  } finally {
    $("start").disabled = false;
  }
}

// "Retest failed": the start form for the slots of the ended batch that ended error, fail or marginal,
// read from the station (a fresh tab knows nothing else): only those ticked, their labels empty to be
// scanned again (a label mismatch is mended so), the operator's name required, the profile, work
// order, part and lot of that batch kept (shown, not editable). Start sends
// POST /api/batches/{id}/retest {operator, labels, slots}.
function setRetest(rt) {
  S.retest = rt;
  const on = !!rt;
  $("profile").disabled = on;
  for (const [id] of TRACE_FIELDS) $(id).disabled = on;
  $("start").textContent = t(on ? "start.start_retest" : "start.start");
  $("start-mode").textContent = on ? t("start.retest_of", { batch: rt.batchId, slots: rt.slots.join(", "), verdicts: rt.verdicts }) : "";
  $("start-mode").classList.toggle("hidden", !on);
}

async function retestFailed() {
  if (!S.batchId || !S.finalBatch) return;
  $("retest").disabled = true;
  try {
    // the batch's header and its slots' verdicts (not the whole status: no results, no transitions)
    const [b, ended, slots] = await Promise.all([api(`/api/batches/${S.batchId}?view=compact`),
      api(`/api/batches/${S.batchId}/slots?result=false`), api("/api/slots")]);
    const again = ended.filter((sl) => RETEST_VERDICTS.has(sl.verdict));
    if (!again.length) { message(t("start.nothing_to_retest", { batch: b.id })); return; }
    $("profile").value = b.profile;
    describeProfile();
    for (const [id, key] of TRACE_FIELDS) $(id).value = b[key] || "";
    renderSlotPicks(slots, new Set(again.map((sl) => sl.slot)));
    setRetest({ batchId: b.id, slots: again.map((sl) => sl.slot),
      verdicts: [...new Set(again.map((sl) => (I18N.has("verdict_name." + sl.verdict) ? t("verdict_name." + sl.verdict) : sl.verdict)))].join(", ") });
    message("");
    S.formOpen = true;
    showControls();
    window.scrollTo(0, 0);
    const first = document.querySelector("#slot-picks input.label-serial:not(:disabled)");
    (operatorName() ? first : $("operator")).focus();
  } catch (e) {
    message(t("start.could_not_retest", { why: e.message }));
  } finally {
    $("retest").disabled = false;
  }
}

async function startRetest() {
  const rt = S.retest;
  const picks = [...document.querySelectorAll("#slot-picks input[type=checkbox]:checked")].map((i) => i.value);
  if (!requireOperator("retest")) { $("operator").focus(); return; }
  if (!picks.length) { message(t("start.choose_slot")); return; }
  const labels = {};
  for (const i of document.querySelectorAll("#slot-picks input.label-serial:not(:disabled)")) {
    if (i.value.trim()) labels[i.dataset.slot] = i.value.trim();
  }
  $("start").disabled = true;
  try {
    const r = await api(`/api/batches/${rt.batchId}/retest`, { method: "POST", body: { operator: operatorName(), labels, slots: picks } });
    for (const i of document.querySelectorAll("#slot-picks input.label-serial")) i.value = "";
    setRetest(null);
    await began(r.id, picks);
  } catch (e) {
    message(t("start.could_not_retest", { why: e.message }));
  } finally {
    $("start").disabled = false;
  }
}

// "New batch": the form opens above the ended batch, whose verdicts stay below until Start.
function openStartForm() {
  S.formOpen = true;
  showControls();
  refreshSlotStates(true);  // the picks as the slots are now (a slot ready again after a fault is ticked)
  window.scrollTo(0, 0);
  (operatorName() ? $("work-order") : $("operator")).focus();
}

function closeStartForm() {
  S.formOpen = false;
  if (S.retest) setRetest(null);
  showControls();
}

// Abort takes two taps (no blocking browser dialog on a kiosk): the first arms the button for 4 s.
let abortArmed = null;

function disarmAbort() {
  clearTimeout(abortArmed);
  abortArmed = null;
  $("abort").classList.remove("armed");
  $("abort").textContent = t("batch.abort");
}

async function abortBatch() {
  if (!S.batchId) return;
  if (!abortArmed) {
    $("abort").classList.add("armed");
    $("abort").textContent = t("batch.abort_again");
    abortArmed = setTimeout(disarmAbort, 4000);
    return;
  }
  disarmAbort();
  try {
    await api(`/api/batches/${S.batchId}/abort`, { method: "POST" });
    message(t("batch.aborted", { batch: S.batchId }));
    await pollBatch();
  } catch (e) { message(t("batch.abort_failed", { why: e.message })); }
}

document.addEventListener("DOMContentLoaded", () => {
  localStorage.removeItem("station.operator");
  S.operator = sessionStorage.getItem("station.operator") || "";
  $("operator").value = S.operator;
  $("operator").addEventListener("input", () => setOperator($("operator").value, true));
  $("start-panel").addEventListener("keydown", onScanKey);
  $("start").addEventListener("click", startBatch);
  $("profile").addEventListener("change", describeProfile);
  $("pick-all").addEventListener("click", () => pickAll(true));
  $("pick-none").addEventListener("click", () => pickAll(false));
  $("new-batch").addEventListener("click", openStartForm);
  $("start-cancel").addEventListener("click", closeStartForm);
  $("retest").addEventListener("click", retestFailed);
  $("abort").addEventListener("click", abortBatch);
});
