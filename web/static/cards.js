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
    el("div", { class: "tray-name" }, tray, el("span", { class: "tray-verdict" }, VERDICT_WORD[es[0].verdict] || es[0].verdict || "")),
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
function renderProgress(b, final) {
  let f = Number(b.progress);
  if (b.progress === null || b.progress === undefined || !Number.isFinite(f)) {
    const steps = Array.isArray(b.steps) ? b.steps : [];
    f = steps.length ? steps.filter((s) => s.state === "done").length / steps.length : 0;  // a failed batch: what it did
  }
  f = Math.min(1, Math.max(0, f));
  const pct = Math.floor(f * 100);
  $("progress-bar").style.width = (f * 100).toFixed(1) + "%";
  $("progress").setAttribute("aria-valuenow", String(pct));
  $("progress").dataset.state = b.state;
  const left = (b.time_left || {}).batch_wall_s;
  $("progress-text").textContent = `${pct} %` + (final ? ` · ${b.state}` : (left !== null && left !== undefined ? ` · ${clock(left)} left` : ""));
}
