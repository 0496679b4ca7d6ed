// The batch's status as the page polls it (issue 40): every 2 s and on live events the page asks
// for the compact view only (GET /api/batches/{id}?view=compact: a few KiB at 64 DUTs whatever
// the batch's length; the browser revalidates it with its ETag). What is big or seldom changes is
// fetched once, when it changes, and kept here:
//   - a slot's other fields (serial, label, sensor, run, fault, program and verify, verdict, grade,
//     tray, reason): GET /api/batches/{id}/slots?slot=..., when the slot's `rev` in the compact view
//     moves (its result and plot come from GET /api/runs/{run_id} once the run is stored: cards.js);
//   - the step list: GET /api/batches/{id}/steps, when the running step changes (the compact view
//     carries the running row, `current_step`, with its time so far);
//   - the sorting list is built from the slots' verdicts.
// Uses app.js (S, $, api, message, setBatch, setLamp, showControls, FINAL, VERDICT_FIELDS), cards.js
// and prompt.js.
"use strict";

const SLOT_LIVE = ["state", "segments", "samples", "steps_done"];  // kept when not null (as the full view's were)
const SORTING_FIELDS = ["slot", "serial", "verdict", "grade", "tray", "reason", "reason_code", "attempt"];

// One poll at a time: the live events ask for one too (a step, a verdict, the end: 64 verdicts come
// within a second at the end of a 64-DUT batch), and a poll asked for while one runs is made once
// after it, so neither the compact view nor a slot's fields are asked for twice at once.
let pollRunning = null;
let pollAgain = false;

function pollBatch() {
  if (pollRunning) { pollAgain = true; return pollRunning; }
  pollRunning = (async () => {
    try {
      do { pollAgain = false; await pollOnce(); } while (pollAgain);
    } finally { pollRunning = null; }
  })();
  return pollRunning;
}

async function pollOnce() {
  if (!S.batchId) return;
  const id = S.batchId;
  try {
    const askedAt = performance.now();
    const b = await api(`/api/batches/${id}?view=compact`);
    if (id !== S.batchId) return;  // a batch started meanwhile wins
    await Promise.all([loadSlotDetails(id, b), loadSteps(id, b)]);
    if (id === S.batchId) applyBatch(b, askedAt);
  } catch (e) {
    if (e.status === 404) setBatch(null);
    else message(e.message);
  }
}

// The slots whose `rev` moved since their fields were fetched (all of them for a batch not seen
// yet), in one request; the rev is kept once their fields are applied, so a failed fetch is retried
// at the next poll.
async function loadSlotDetails(id, b) {
  const names = (b.slots || []).map((sl) => sl.slot);
  const revs = (b.slot_live && b.slot_live.rev) || [];
  const stale = names.filter((n, i) => { const s = slotState(n); return s.revBatch !== id || s.rev !== revs[i]; });
  if (!stale.length) return;
  const only = stale.length === names.length ? "" : stale.map((n) => "slot=" + encodeURIComponent(n)).join("&") + "&";
  const got = await api(`/api/batches/${id}/slots?${only}result=false`);
  if (id !== S.batchId) return;
  for (const sl of got) applySlotDetails(sl);
  for (const n of stale) {
    const s = slotState(n);
    s.rev = revs[names.indexOf(n)];
    s.revBatch = id;
  }
}

function applySlotDetails(sl) {
  const s = slotState(sl.slot);
  for (const k of ["serial", "sensor", "program", "verification", "label_serial"]) {
    if (sl[k] !== null && sl[k] !== undefined) s[k] = sl[k];
  }
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
  s.error_code = sl.error_code || null;  // the page says the cause in its language by it (i18n.js reasonNodes)
}

// The step list again when the running step changed (or the batch's state: its end marks the
// steps done, skipped or failed); between two changes only the running row moves.
async function loadSteps(id, b) {
  const cur = b.current_step;
  const key = `${id}|${b.state}|${cur ? cur.index : "-"}`;
  if (S.stepsKey === key) return;
  const steps = await api(`/api/batches/${id}/steps`);
  if (id !== S.batchId) return;
  S.steps = steps;
  S.stepsKey = key;
}

function stepsShown(b) {
  const cur = b.current_step;
  return (S.steps || []).map((st) => (cur && st.index === cur.index ? cur : st));
}

// Which slot to which tray: every slot of the batch with a verdict (the station's sorting list is
// the same, station/daemon/progress.py batch_extras).
function sortingOf(names) {
  return names.map((n) => slotState(n)).filter((s) => s.verdict)
    .map((s) => Object.fromEntries(SORTING_FIELDS.map((k) => [k, s[k] ?? null])));
}

// The station cannot follow its boards (station/daemon/intake_monitor.py): the alarm in words, as a
// banner, from the batch's `overload` (compact view) or, without a running batch, from
// /api/health's `intake` (app.js pollStorage).
function showOverload(from, alarm) {
  S.overloadAlarms = Object.assign(S.overloadAlarms || {}, { [from]: alarm || "" });
  const text = S.overloadAlarms.batch || S.overloadAlarms.health || "";
  $("overload").textContent = text;
  $("overload").classList.toggle("hidden", !text);
}

function applyBatch(b, askedAt = Infinity) {
  $("batch-profile").textContent = b.profile || "";
  $("batch-state").textContent = batchStateWord(b.state);
  $("batch-state").dataset.state = b.state;
  $("batch-trace-text").textContent = traceText(b);
  $("batch-trace").classList.toggle("hidden", !traceText(b));
  const steps = stepsShown(b);
  S.stepCount = (b.step && b.step.count) || steps.length || S.stepCount;
  if (b.step && b.step.index !== null && b.step.index !== undefined && b.step.index >= 0) {  // -1: boards still connecting
    $("batch-step").textContent = `${b.step.index + 1} / ${b.step.count ?? "?"} · ${stepName(b.step.name ?? "")}`;
  }
  if (b.lamp_on !== undefined) setLamp(b.lamp_on, b.lamp_state);
  // e.g. "aborted by Ana at 2026-11-23 14:02:05 UTC"; its code only in the full status (error_code)
  $("batch-error").replaceChildren(...(b.error ? reasonNodes(b.error_code, b.error) : []));
  $("batch-note").textContent = b.note || "";
  $("batch-note").classList.toggle("hidden", !b.note);
  $("batch-elapsed").textContent = clock(b.elapsed_s ?? storedElapsed(b));
  $("batch-waiting").textContent = b.waiting_for ? waitingWords(b.waiting_for) : "–";
  showOverload("batch", b.overload && b.overload.alarm);
  const names = (b.slots || []).map((sl) => sl.slot);
  S.batchSlots = names;
  const live = b.slot_live || {};
  const counts = { running: 0, done: 0, faulted: 0 };
  names.forEach((name, i) => {
    const s = slotState(name);
    for (const k of SLOT_LIVE) {
      const v = (live[k] || [])[i];
      if (v !== null && v !== undefined) s[k] = v;
    }
    s.waiting_for = (live.waiting_for || [])[i] || null;
    const state = (live.state || [])[i];
    if (state in counts) counts[state] += 1;
    else if (state === "interrupted") counts.interrupted = (counts.interrupted || 0) + 1;
    else if (!FINAL.has(state)) counts.running += 1;
    if (["done", "interrupted", "faulted"].includes(s.state) && !s.plotUrl) loadPlot(name);
  });
  const slots = names.map((n) => slotState(n));
  const shown = Object.assign({}, b, { slots, steps, sorting: sortingOf(names) });
  const c = b.counts || counts;  // the station's own count: no DUT runs once the batch ended
  renderCounts(c, shown, FINAL.has(b.state));  // cards.js: names the faulted slots ("1 faulted: s03")
  S.finalBatch = FINAL.has(b.state);
  S.retestable = S.finalBatch && slots.some((s) => RETEST_VERDICTS.has(s.verdict));  // start.js
  const left = b.time_left || {};
  $("step-left").textContent = S.finalBatch ? "–" : clock(left.step_wall_s);
  $("batch-left").textContent = S.finalBatch ? "–" : clock(left.batch_wall_s);
  for (const id of ["time-left-step", "time-left-batch"]) $(id).classList.toggle("hidden", S.finalBatch);
  renderSteps(shown);
  renderProgress(shown, S.finalBatch);
  S.sorting = shown.sorting;
  renderSorting(shown);
  showControls();
  if (b.prompt && promptId(b.prompt) !== undefined) showPrompt(b.prompt);
  else if (!S.prompt || askedAt > S.promptShownAt) hidePrompt();  // a status asked before the prompt came says nothing of it
  if (S.lastState && !FINAL.has(S.lastState) && S.finalBatch) attention("end");  // seen ending, not an old batch
  S.lastState = b.state;
  renderSlots();
}
