// Slot cards, the sorting view and the batch's step list and progress bar (plain JavaScript, no
// framework): what each slot shows live and at the end (verdict, reason, tray, result tables, its
// run's plot). Split from app.js to keep modules small; it uses app.js's helpers (S, el, $, fmt, api,
// blobUrl, programVerifyTable).
"use strict";

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
      el("div", { class: "serial" }, s.serial || "no DUT", s.sensor ? el("span", { class: "muted" }, " · " + s.sensor) : null,
        active && s.label_serial ? el("span", { class: "label-serial muted", title: "serial on the part's label" }, " · label ",
          el("b", {}, s.label_serial)) : null),
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
      // a fault's reason stays on the card after the verdict too, unless the verdict's reason says it
      s.error && (!s.verdict || !(s.reason || "").includes(s.error)) ? el("div", { class: "fault" }, "Fault: " + s.error) : null,
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

// Exceptions first: what needs a person's hands (error, fail, hold) before what goes on.
const VERDICT_RANK = { error: 0, fail: 1, marginal: 2, pass: 3 };
const verdictRank = (v) => VERDICT_RANK[v] ?? 4;
const slotRank = (n) => (S.order.includes(n) ? S.order.indexOf(n) : 1e6);
const bySlot = (a, b) => slotRank(a.slot) - slotRank(b.slot) || String(a.slot).localeCompare(String(b.slot), undefined, { numeric: true });

// A reason without what the slot beside it already says: its end ("faulted: ", the verdict word says
// it) and the link ("serial /dev/pts/7: link lost: ..." -> "link lost: ..."); a label mismatch in a
// few words. The card and the title keep the whole text.
function shortReason(r) {
  const s = String(r || "").replace(/^faulted: /, "").replace(/^(?:serial \S+|can \S+ node \d+): /, "");
  const m = /^label serial '(.*?)' does not match the board's own serial '(.*?)'/.exec(s);
  if (m) return `label ${m[1]} ≠ board ${m[2]}`;
  const cannot = / could not (?:.*: )?(turn the plate to \S+: .*)$/.exec(s);  // who said it is in the tooltip
  if (cannot) return `could not ${cannot[1]}`;
  return s.replace(/^step '[^']*': (?=plate never arrived|its output never faced)/, "").replace(/ ?\+-/g, "±");
}

// Which slot goes to which tray: one row per tray and verdict, exceptions first (error, fail,
// marginal/hold, then pass), each slot with its verdict colour; an exception's slot with its
// reason, so that every slot's verdict and what to do with it show on the 800x480 kiosk.
function renderSorting(b) {
  const box = $("sorting");
  const list = S.sorting || [];
  box.classList.toggle("hidden", !list.length);
  if (!list.length) return;
  const trays = new Map();
  for (const e of list) {
    const tray = e.tray || e.grade || e.verdict || "–";
    const key = tray + "\u0000" + (e.verdict || "");
    if (!trays.has(key)) trays.set(key, { tray, verdict: e.verdict, slots: [] });
    trays.get(key).slots.push(e);
  }
  const rows = [...trays.values()].sort((a, c) => (verdictRank(a.verdict) - verdictRank(c.verdict)) || a.tray.localeCompare(c.tray));
  $("trays").replaceChildren(...rows.map((r) => {
    const exception = r.verdict !== "pass";
    const slots = r.slots.slice().sort(bySlot);
    return el("div", { class: "tray-row v-" + r.verdict + (exception ? " exception" : ""), "data-tray": r.tray, "data-verdict": r.verdict },
      el("div", { class: "tray-head" },
        el("span", { class: "tray-name" }, r.tray),
        el("span", { class: "tray-tags" },
          el("span", { class: "tray-verdict" }, VERDICT_WORD[r.verdict] || r.verdict || ""),
          el("span", { class: "tray-count", title: `${slots.length} part${slots.length === 1 ? "" : "s"}` }, "× " + slots.length))),
      el("div", { class: "tray-slots" }, ...slots.map((e) => el("span", {
        class: "tray-slot v-" + e.verdict, "data-slot": e.slot, "data-verdict": e.verdict,
        title: `${e.slot} ${e.serial || ""}: ${VERDICT_WORD[e.verdict] || e.verdict} → ${r.tray}` + (e.reason ? ` · ${e.reason}` : ""),
      }, el("b", { class: "tray-slot-name" }, e.slot), el("small", {}, " " + (e.serial || "")),
      exception && e.reason ? el("span", { class: "tray-why" }, shortReason(e.reason)) : null))));
  }));
  const d = (b && b.decision && b.decision.verdicts) || {};
  $("yield-line").textContent = `${d.pass || 0} pass · ${d.marginal || 0} marginal · ${d.fail || 0} fail · ${d.error || 0} error`;
}

// The batch's outcome from its verdicts: all pass (green), some pass (amber), none pass (red),
// in words as well ("0 of 11 pass"); null before any verdict (a running batch, a validation batch).
function batchOutcome(b) {
  const v = (b && b.decision && b.decision.verdicts) || {};
  const judged = ["pass", "marginal", "fail", "error"].reduce((n, k) => n + (v[k] || 0), 0);
  if (!judged) return null;
  const pass = v.pass || 0;
  const kind = pass === judged ? "all" : (pass === 0 ? "none" : "some");
  return { kind, pass, judged, counts: v, words: kind === "all" ? `all ${judged} pass` : `${pass} of ${judged} pass` };
}

// "11 running · 0 done · 1 faulted: s03" - which slot (a tap takes you to its card), and the reasons
// on a line of their own, while the batch runs; at the end the sorting view names them with theirs.
function renderCounts(c, b, final) {
  const faulted = (b.slots || []).filter((sl) => sl.state === "faulted").sort(bySlot);
  const box = $("batch-counts");
  const text = `${c.running || 0} running · ${c.done || 0} done · ${c.faulted || 0} faulted`;
  const names = final ? [] : faulted.flatMap((sl, i) => [i ? ", " : "", el("button", {
    type: "button", class: "fault-slot", "data-slot": sl.slot, title: sl.error || "faulted",
    onclick: () => showSlotCard(sl.slot),
  }, sl.slot)]);
  box.replaceChildren(text, ...(names.length ? [": ", ...names] : []), c.interrupted ? ` · ${c.interrupted} interrupted` : "");
  const line = $("batch-faults");
  const live = !final && faulted.length;
  line.classList.toggle("hidden", !live);
  line.replaceChildren(...(live ? faulted.map((sl) => el("button", {
    type: "button", class: "fault-line", "data-slot": sl.slot, title: sl.error || "", onclick: () => showSlotCard(sl.slot),
  }, el("b", {}, sl.slot), " " + (shortReason(sl.error) || "faulted"))) : []));
}

// A stored batch (the daemon no longer holds it) has no clock of its own: its start to its end.
function storedElapsed(b) {
  const t0 = Date.parse(b.created_at || ""), t1 = Date.parse(b.ended_at || "");
  return Number.isFinite(t0) && Number.isFinite(t1) && t1 >= t0 ? (t1 - t0) / 1000 : null;
}

function showSlotCard(slot) {
  const card = document.querySelector(`.slot-card[data-slot="${CSS.escape(slot)}"]`);
  if (!card) return;
  card.scrollIntoView({ block: "start", behavior: "smooth" });
  card.classList.remove("flash");
  void card.offsetWidth;  // restart the animation
  card.classList.add("flash");
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

function sigmaText(sigma, digits) {
  return sigma === null || sigma === undefined ? "–" : fmt(sigma, digits);
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
    // every ± on the page is the part's own 1 sigma (docs/verdicts.md "Uncertainty budget"); the
    // verdict's guard band is k = 2 of it. A line under the table, so a card keeps its width.
    const sig = (key, digits) => ["x", "y", "z"].map((ax) => sigmaText((result.axes[ax] || {})[key], digits)).join(" / ");
    if (["x", "y", "z"].some((ax) => (result.axes[ax] || {}).tdb_sigma_mg_per_c != null)) {
      wrap.append(el("div", { class: "sigmas" },
        `± 1σ (this part's): TDB ${sig("tdb_sigma_mg_per_c", 4)} · TDSF ${sig("tdsf_sigma_ppm_per_c", 1)}`));
    }
    let note = (result.method || "") + (result.method === "offline" ? " fit" : "");
    if (result.streaming && result.method !== "streaming") {
      note += " · streaming TDB " + ["x", "y", "z"].map((ax) => fmt((result.streaming[ax] || {}).tdb_mg_per_c, 3)).join(" / ");
    }
    wrap.append(el("div", { class: "method" }, note));
  }
  if (result.sfem) {
    const sf = result.sfem;
    // the record (contracts/sfem_result.py): the step nearest Tref at the top, the model check's words
    const at = sf.temp_c === null || sf.temp_c === undefined ? "" : ` at ${fmt(sf.temp_c, 1)} °C`;
    wrap.append(el("div", { class: "sfem" }, `SFEM${at}: RMSE ${fmt(sf.rmse_before_mg, 2)} → ${fmt(sf.rmse_after_mg, 2)} mg`));
    const check = sf.model_check || {};
    if (check.words && check.words !== "not testable") {
      wrap.append(el("div", { class: "sfem-check" + (check.misses_effect ? " warn" : "") }, check.words));
    }
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

// ---- the batch's steps and progress -----------------------------------------------------------
function traceText(b) {
  const part = [b.part_number, b.part_revision ? "rev " + b.part_revision : ""].filter(Boolean).join(" ");
  const bits = [b.work_order ? "WO " + b.work_order : "", part ? "part " + part : "", b.lot ? "lot " + b.lot : ""].filter(Boolean);
  return bits.join(" · ");
}

// A step's time: done/failed its duration, running "so far / ~expected", pending "~expected".
function stepTime(st) {
  const exp = Number.isFinite(Number(st.expected_s)) && st.expected_s !== null ? "~" + clock(st.expected_s) : "";
  if (st.state === "running") return clock(st.duration_s) + (exp ? " / " + exp : "");
  if (st.state === "done" || st.state === "failed") return clock(st.duration_s);
  if (st.state === "skipped") return "skipped";
  return exp;
}

// The batch's steps with state and duration (`steps` of the status), the running one kept in view.
function renderSteps(b) {
  const list = Array.isArray(b.steps) ? b.steps : [];
  const box = $("steps");
  box.classList.toggle("hidden", !list.length);
  box.replaceChildren(...list.map((st) => el("li", {
    class: "step", "data-state": st.state, "data-kind": st.kind || "step", "data-index": st.index,
    title: `step ${st.index + 1}: ${st.name || st.kind}${st.position_name ? " at " + st.position_name : ""} · ${st.state} · ${stepTime(st)}`,
  }, el("span", { class: "step-n" }, String(st.index + 1)), el("span", { class: "step-name" }, st.name || st.kind || ""),
  el("span", { class: "step-time" }, stepTime(st)))));
  const cur = box.querySelector('.step[data-state="running"]');
  if (cur && box.scrollWidth > box.clientWidth + 2) box.scrollLeft = Math.max(0, cur.offsetLeft - box.clientWidth / 3);
}

// Overall progress (`progress` 0..1) and the batch's time left (only decreases: the station's).
// At the end the bar shows the outcome: its fill split by verdict (pass green, marginal amber, fail
// red, error pink) and the words "finished · 0 of 11 pass"; the state chip takes the outcome's
// colour (a finished batch in which nothing passed is red, never green).
function renderProgress(b, final) {
  let f = Number(b.progress), known = true;
  if (b.progress === null || b.progress === undefined || !Number.isFinite(f)) {
    const steps = Array.isArray(b.steps) ? b.steps : [];
    if (steps.length) f = steps.filter((s) => s.state === "done").length / steps.length;  // a failed batch: what it did
    else if (final) { f = 1; known = b.state === "finished"; }  // a stored batch (no step list): its outcome, whole width
    else f = 0;
  }
  f = Math.min(1, Math.max(0, f));
  const pct = Math.floor(f * 100);
  const bar = $("progress-bar");
  bar.style.width = (f * 100).toFixed(1) + "%";
  $("progress").setAttribute("aria-valuenow", String(pct));
  $("progress").dataset.state = b.state;
  const out = final ? batchOutcome(b) : null;
  bar.replaceChildren(...(out ? ["pass", "marginal", "fail", "error"].filter((k) => out.counts[k]).map((k) => {
    const seg = el("span", { class: "outcome-seg v-" + k, "data-verdict": k });
    seg.style.flexGrow = String(out.counts[k]);
    return seg;
  }) : []));
  for (const id of ["progress", "batch-state"]) {
    if (out) $(id).dataset.outcome = out.kind; else delete $(id).dataset.outcome;
  }
  $("batch-outcome-kv").classList.toggle("hidden", !out);
  $("batch-outcome").textContent = out ? out.words : "";
  if (out) $("batch-outcome").dataset.outcome = out.kind;
  const left = (b.time_left || {}).batch_wall_s;
  $("progress-text").textContent = (known ? `${pct} %` : "") + (final ? (known ? " · " : "") + b.state + (out ? ` · ${out.words}` : "")
    : (left !== null && left !== undefined ? ` · ${clock(left)} left` : ""));
  $("batch-error").title = b.error || "";  // the kiosk shows it on one line
}
