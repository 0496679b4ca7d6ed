// Slot cards, the sorting view and the batch's step list and progress bar (plain JavaScript, no
// framework): what each slot shows live and at the end (verdict, reason, tray, result tables, its
// run's plot). Split from app.js to keep modules small; it uses app.js's helpers (S, el, $, fmt, api,
// blobUrl, programVerifyTable, verdictWord, slotStateWord) and i18n.js (t, reasonNodes): every word
// from the catalogs; the station's own words (reasons, tray names from the config) as they are, or
// translated by their code.
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
    const dots = el("span", { class: "dots", "aria-hidden": "true", title: t("slot.steps_done", { done, need }) });
    for (let i = 0; i < Math.min(need, 40); i++) dots.append(el("span", { class: i < done ? "dot on" : "dot" }));
    card.replaceChildren(...[
      el("header", {}, el("h2", {}, name), el("span", { class: "st" }, slotStateWord(state))),
      el("div", { class: "serial" }, s.serial || t("slot.no_dut"), s.sensor ? el("span", { class: "muted" }, " · " + s.sensor) : null,
        active && s.label_serial ? el("span", { class: "label-serial muted", title: t("slot.label_title") }, " · " + t("slot.label") + " ",
          el("b", {}, s.label_serial)) : null),
      active ? el("div", { class: "live" },
        el("span", { class: "temp" }, s.temp_c === undefined || s.temp_c === null ? "– °C" : fmt(s.temp_c, 1) + " °C"),
        el("span", { class: "segbox" }, t("slot.segments") + " ", el("b", { class: "segments" }, String(s.segments || 0)),
          " · " + t("slot.steps") + " ", dots)) : null,
      active ? el("dl", {},
        el("dt", {}, t("slot.acc")), el("dd", { class: "acc" }, acc),
        el("dt", {}, t("slot.samples")), el("dd", { class: "samples" }, String(s.samples ?? 0)),
      ) : el("div", { class: "muted" }, S.batchId && !S.finalBatch ? t("slot.not_in_batch") : ""),
      active && s.verdict ? verdictBlock(s) : null,
      active && !s.verdict && s.tempHist && s.tempHist.length > 1 ? sparkline(s.tempHist) : null,
      active && s.waiting_for && !S.finalBatch ? el("div", { class: "waiting muted" }, t("slot.waiting_for") + " ",
        el("b", { class: "waiting-for" }, waitingWords(s.waiting_for))) : null,
      // a fault's reason stays on the card after the verdict too, unless the verdict's reason says it
      s.error && (!s.verdict || !(s.reason || "").includes(s.error))
        ? el("div", { class: "fault" }, t("slot.fault") + " ", ...reasonNodes(s.error_code, s.error)) : null,
      active && s.result ? resultTable(s.result) : null,
      active && (s.program || s.verification) ? programVerifyTable(s.program, s.verification) : null,
      active && s.plotUrl ? el("img", { class: "plot-thumb", src: s.plotUrl, alt: s.plotAlt || t("slot.plot_alt", { what: s.serial || name }), onclick: () => showPlot(s.plotUrl) }) : null,
    ].filter((c) => c !== null && c !== undefined && c !== false));
  }
}

// The decision, big enough to read from two metres: verdict word, grade, tray, reason.
function verdictBlock(s) {
  return el("div", { class: "verdict v-" + s.verdict, "data-verdict": s.verdict },
    el("div", { class: "verdict-head" },
      el("span", { class: "verdict-word" }, verdictWord(s.verdict)),
      s.grade ? el("span", { class: "grade" + (gradeWord(s.grade).length > 2 ? " long" : ""), title: t("verdict.grade_title"),
        "data-grade": s.grade }, gradeWord(s.grade)) : null),
    el("div", { class: "reason" }, ...reasonNodes(s.reason_code, s.reason)),
    el("div", { class: "tray-line" }, "→ ", el("b", { class: "tray", "data-tray": s.tray || "" }, s.tray ? trayWord(s.tray) : "–"),
      s.attempt > 1 ? el("span", { class: "attempt" }, " · " + t("verdict.attempt", { n: s.attempt })) : null));
}

// A grade: the product's bins (A, B: the config's names) as they are; the station's own grades of an
// exception ("retest", "reject", "hold", "none": station/decisions/verdicts.py) in the page's language.
function gradeWord(g) { return I18N.has("grade." + g) ? t("grade." + g) : g; }

// A tray's name: the config names it (a site may name its own, in its own language); the built-in
// names (station/decisions/limits.py: "reject", "hold (review / retest)", "retest", "grade A") are
// said in the page's language. The data-tray attribute keeps the station's name.
function trayWord(name) {
  const g = /^grade (\S+)$/.exec(name || "");
  if (g) return t("tray.grade", { grade: g[1] });
  const key = "tray." + String(name || "").toLowerCase().replace(/[^a-z0-9]+/g, "_").replace(/^_|_$/g, "");
  return I18N.has(key) ? t(key) : (name || "");
}

// A step's name: the built-in profiles' (station/profiles.py: "P ambient", "N hot", "cool down",
// "program", "verify hot") in the page's language; a site's own step names as the config wrote them.
function stepName(name) {
  const m = /^(\S+) (ambient|hot)$/.exec(name || "");
  if (m) return t("stepname." + m[2], { position: m[1] });
  const key = "stepname." + String(name || "").toLowerCase().replace(/[^a-z0-9]+/g, "_");
  return I18N.has(key) ? t(key) : (name || "");
}

// What a DUT's step waits for (SlotStatus.waiting_for, the daemon's words): "plate at N", "other DUTs".
function waitingWords(w) {
  const m = /^plate at (\S+)$/.exec(w || "");
  if (m) return t("waiting.plate_at", { position: m[1] });
  const key = "waiting." + String(w || "").toLowerCase().replace(/[^a-z0-9]+/g, "_");  // "other DUTs", "static dwell", ...
  return I18N.has(key) ? t(key) : (w || "");
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
  const label = t("slot.temp_range", { lo: fmt(lo, 1), hi: fmt(hi, 1) }).replace(/[<>&"']/g, (c) => `&#${c.charCodeAt(0)};`);
  box.innerHTML = `<svg viewBox="0 0 ${w} ${h}" class="spark" role="img" aria-label="${label}">`
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
        el("span", { class: "tray-name" }, trayWord(r.tray)),
        el("span", { class: "tray-tags" },
          el("span", { class: "tray-verdict" }, verdictWord(r.verdict)),
          el("span", { class: "tray-count", title: t(slots.length === 1 ? "sorting.one_part" : "sorting.parts", { n: slots.length }) },
            "× " + slots.length))),
      el("div", { class: "tray-slots" }, ...slots.map((e) => el("span", {
        class: "tray-slot v-" + e.verdict, "data-slot": e.slot, "data-verdict": e.verdict,
        title: `${e.slot} ${e.serial || ""}: ${verdictWord(e.verdict)} → ${trayWord(r.tray)}` + (e.reason ? ` · ${e.reason}` : ""),
      }, el("b", { class: "tray-slot-name" }, e.slot), el("small", {}, " " + (e.serial || "")),
      exception && e.reason ? el("span", { class: "tray-why" }, ...reasonNodes(e.reason_code, e.reason, shortReason(e.reason))) : null))));
  }));
  const d = (b && b.decision && b.decision.verdicts) || {};
  $("yield-line").textContent = t("sorting.yield", { pass: d.pass || 0, marginal: d.marginal || 0, fail: d.fail || 0, error: d.error || 0 });
}

// The batch's outcome from its verdicts: all pass (green), some pass (amber), none pass (red),
// in words as well ("0 of 11 pass"); null before any verdict (a running batch, a validation batch).
function batchOutcome(b) {
  const v = (b && b.decision && b.decision.verdicts) || {};
  const judged = ["pass", "marginal", "fail", "error"].reduce((n, k) => n + (v[k] || 0), 0);
  if (!judged) return null;
  const pass = v.pass || 0;
  const kind = pass === judged ? "all" : (pass === 0 ? "none" : "some");
  return { kind, pass, judged, counts: v, words: kind === "all" ? t("outcome.all", { n: judged }) : t("outcome.some", { pass, n: judged }) };
}

// "11 running · 0 done · 1 faulted: s03" - which slot (a tap takes you to its card), and the reasons
// on a line of their own, while the batch runs; at the end the sorting view names them with theirs.
function renderCounts(c, b, final) {
  const faulted = (b.slots || []).filter((sl) => sl.state === "faulted").sort(bySlot);
  const box = $("batch-counts");
  const text = t("counts.line", { running: c.running || 0, done: c.done || 0, faulted: c.faulted || 0 });
  const names = final ? [] : faulted.flatMap((sl, i) => [i ? ", " : "", el("button", {
    type: "button", class: "fault-slot", "data-slot": sl.slot, title: sl.error || t("slot_state.faulted"),
    onclick: () => showSlotCard(sl.slot),
  }, sl.slot)]);
  box.replaceChildren(text, ...(names.length ? [": ", ...names] : []), c.interrupted ? " · " + t("counts.interrupted", { n: c.interrupted }) : "");
  const line = $("batch-faults");
  const live = !final && faulted.length;
  line.classList.toggle("hidden", !live);
  line.replaceChildren(...(live ? faulted.map((sl) => el("button", {
    type: "button", class: "fault-line", "data-slot": sl.slot, title: sl.error || "", onclick: () => showSlotCard(sl.slot),
  }, el("b", {}, sl.slot), " ", ...(sl.error ? reasonNodes(sl.error_code, sl.error, shortReason(sl.error)) : [t("slot_state.faulted")]))) : []));
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
  return el("td", { class: "tdsf clamped", title: t("result.clamped_title") },
    fmt(a.tdsf_ppm_per_c, 1) + " ", el("span", { class: "clamped-flag" }, t("result.clamped")));
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
      // TDB and TDSF are the coefficients' symbols, like their units: the same in every language
      el("thead", {}, el("tr", {}, el("th", {}, t("result.axis")), el("th", {}, "TDB mg/°C"), el("th", {}, "TDSF ppm/°C"))),
      el("tbody", {}, ...rows)));
    // every ± on the page is the part's own 1 sigma (docs/verdicts.md "Uncertainty budget"); the
    // verdict's guard band is k = 2 of it. A line under the table, so a card keeps its width.
    const sig = (key, digits) => ["x", "y", "z"].map((ax) => sigmaText((result.axes[ax] || {})[key], digits)).join(" / ");
    if (["x", "y", "z"].some((ax) => (result.axes[ax] || {}).tdb_sigma_mg_per_c != null)) {
      wrap.append(el("div", { class: "sigmas" },
        t("result.sigmas", { tdb: sig("tdb_sigma_mg_per_c", 4), tdsf: sig("tdsf_sigma_ppm_per_c", 1) })));
    }
    let note = result.method && I18N.has("result.method_" + result.method) ? t("result.method_" + result.method) : (result.method || "");
    if (result.streaming && result.method !== "streaming") {
      note += " · " + t("result.streaming_tdb", { values: ["x", "y", "z"].map((ax) => fmt((result.streaming[ax] || {}).tdb_mg_per_c, 3)).join(" / ") });
    }
    wrap.append(el("div", { class: "method" }, note));
  }
  if (result.sfem) {
    const sf = result.sfem;
    // the record (contracts/sfem_result.py): the step nearest Tref at the top, the model check's words
    const at = sf.temp_c === null || sf.temp_c === undefined ? "" : " " + t("result.sfem_at", { temp: fmt(sf.temp_c, 1) });
    wrap.append(el("div", { class: "sfem" }, t("result.sfem", { at, before: fmt(sf.rmse_before_mg, 2), after: fmt(sf.rmse_after_mg, 2) })));
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
    s.plotAlt = t("slot.plot_run_alt", { what: s.serial || slot, run: s.runId, state: slotStateWord(run.state) });
    s.plotUrl = await blobUrl(s.plotPath || `/api/runs/${s.runId}/plot.png`);
    renderSlots();
  } catch (e) { /* retried on the next poll */ } finally { s.plotLoading = false; }
}

// ---- the batch's steps and progress -----------------------------------------------------------
function traceText(b) {
  const part = [b.part_number, b.part_revision ? t("trace.short_rev", { rev: b.part_revision }) : ""].filter(Boolean).join(" ");
  const bits = [b.work_order ? t("trace.short_wo", { wo: b.work_order }) : "", part ? t("trace.short_part", { part }) : "",
    b.lot ? t("trace.short_lot", { lot: b.lot }) : ""].filter(Boolean);
  return bits.join(" · ");
}

// A step's time: done/failed its duration, running "so far / ~expected", pending "~expected".
function stepTime(st) {
  const exp = Number.isFinite(Number(st.expected_s)) && st.expected_s !== null ? "~" + clock(st.expected_s) : "";
  if (st.state === "running") return clock(st.duration_s) + (exp ? " / " + exp : "");
  if (st.state === "done" || st.state === "failed") return clock(st.duration_s);
  if (st.state === "skipped") return t("step_state.skipped");
  return exp;
}

// The batch's steps with state and duration (`steps` of the status), the running one kept in view.
function renderSteps(b) {
  const list = Array.isArray(b.steps) ? b.steps : [];
  const box = $("steps");
  box.classList.toggle("hidden", !list.length);
  box.replaceChildren(...list.map((st) => el("li", {
    class: "step", "data-state": st.state, "data-kind": st.kind || "step", "data-index": st.index,
    title: t(st.position_name ? "step.title_at" : "step.title", { n: st.index + 1, name: stepName(st.name || st.kind), position: st.position_name,
      state: I18N.has("step_state." + st.state) ? t("step_state." + st.state) : st.state, time: stepTime(st) }),
  }, el("span", { class: "step-n" }, String(st.index + 1)), el("span", { class: "step-name" }, stepName(st.name || st.kind || "")),
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
  $("progress-text").textContent = (known ? `${pct} %` : "") + (final ? (known ? " · " : "") + batchStateWord(b.state) + (out ? ` · ${out.words}` : "")
    : (left !== null && left !== undefined ? " · " + t("progress.left", { time: clock(left) }) : ""));
  $("batch-error").title = b.error || "";  // the kiosk shows it on one line
}
