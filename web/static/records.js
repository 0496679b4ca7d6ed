// Records view (issue 13): yield and SPC charts (drawn here as SVG from /api/spc, no library) and
// the audit trail (admin). Uses app.js's globals (api, blobUrl, el, fmt, S); loaded after it.
"use strict";

const REC = { parameters: [], loaded: false };

async function loadAudit() {
  const table = document.getElementById("audit-table");
  const status = document.getElementById("audit-status");
  table.replaceChildren();
  if (S.role !== "admin") { status.textContent = "The audit trail is for admin tokens."; return; }
  try {
    const rows = await api("/api/audit?limit=50");
    status.textContent = rows.length ? "" : "No audited action yet.";
    table.append(el("tr", {}, ...["time", "station", "who", "action", "target", "detail"].map((h) => el("th", {}, h))));
    for (const a of rows) {
      table.append(el("tr", { "data-action": a.action },
        el("td", {}, new Date(a.at).toLocaleString()), el("td", {}, a.station), el("td", {}, a.actor),
        el("td", {}, a.action), el("td", {}, a.target),
        el("td", { class: "detail" }, Object.entries(a.detail || {}).map(([k, v]) => `${k}: ${JSON.stringify(v)}`).join(", "))));
    }
  } catch (e) { status.textContent = e.message; }
}

// ---- SPC charts (SVG) ---------------------------------------------------------------------------
// The SVG namespace, as the HTML parser gave it to the page's own <svg id="svg-ns"> (no URL literal
// in the page's files: tests/test_web_api.py keeps them free of any http address).
const SVGNS = document.getElementById("svg-ns").namespaceURI;

function svgEl(tag, attrs, text) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

function num(v, d = 3) { return v === null || v === undefined ? "–" : Number(v).toPrecision(d); }

// One chart: x from 0..n-1 (or bins), y scaled to the data and every horizontal line given.
function chart(title, { ys, xs, lines = [], bars = null, flagged = new Set(), xlabels = null, unit = "" }) {
  const W = 460, H = 220, L = 56, R = 10, T = 22, B = 30;
  const svg = svgEl("svg", { viewBox: `0 0 ${W} ${H}`, class: "spc-chart", role: "img", "aria-label": title });
  const vals = [...ys, ...lines.map((l) => l.y).filter((y) => y !== null && y !== undefined)];
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (!(hi > lo)) { lo -= 1; hi += 1; }
  const pad = (hi - lo) * 0.08; lo -= pad; hi += pad;
  const n = xs ? xs.length : ys.length;
  const sx = xlabels  // categories: centred in equal cells; a series: first to last point edge to edge
    ? (i) => L + ((i + 0.5) * (W - L - R)) / n
    : (i) => L + (n <= 1 ? (W - L - R) / 2 : (i * (W - L - R)) / (n - 1));
  const sy = (y) => T + ((hi - y) * (H - T - B)) / (hi - lo);
  svg.append(svgEl("text", { x: L, y: 14, class: "spc-title" }, title));
  svg.append(svgEl("rect", { x: L, y: T, width: W - L - R, height: H - T - B, class: "spc-frame" }));
  if (!bars) {
    for (const f of [0, 0.5, 1]) {
      const y = lo + f * (hi - lo);
      svg.append(svgEl("text", { x: L - 4, y: sy(y) + 3, class: "spc-tick", "text-anchor": "end" }, num(y)));
    }
  }
  svg.append(svgEl("text", { x: 4, y: T + 8, class: "spc-tick" }, unit));
  if (bars) {
    const bw = (W - L - R) / bars.counts.length;
    const bx = (v) => L + ((v - bars.lo) * (W - L - R)) / (bars.hi - bars.lo);
    const top = Math.max(1, ...bars.counts);
    svg.append(svgEl("text", { x: L - 4, y: T + 8, class: "spc-tick", "text-anchor": "end" }, String(top)));
    svg.append(svgEl("text", { x: L - 4, y: H - B, class: "spc-tick", "text-anchor": "end" }, "0"));
    bars.counts.forEach((c, i) => svg.append(svgEl("rect", {
      x: L + i * bw + 1, width: Math.max(1, bw - 2), y: T + (1 - c / top) * (H - T - B), height: (c / top) * (H - T - B),
      class: "spc-bar" })));
    for (const l of lines) {
      if (l.x === null || l.x === undefined) continue;
      svg.append(svgEl("line", { x1: bx(l.x), x2: bx(l.x), y1: T, y2: H - B, class: "spc-line " + l.cls }));
      svg.append(svgEl("text", { x: bx(l.x) + 2, y: T + 10, class: "spc-label" }, l.label));
    }
    svg.append(svgEl("text", { x: L, y: H - 8, class: "spc-tick" }, num(bars.lo)));
    svg.append(svgEl("text", { x: W - R, y: H - 8, class: "spc-tick", "text-anchor": "end" }, num(bars.hi)));
    return svg;
  }
  for (const l of lines) {
    if (l.y === null || l.y === undefined) continue;
    svg.append(svgEl("line", { x1: L, x2: W - R, y1: sy(l.y), y2: sy(l.y), class: "spc-line " + l.cls }));
    svg.append(svgEl("text", { x: W - R - 2, y: sy(l.y) - 3, class: "spc-label", "text-anchor": "end" }, `${l.label} ${num(l.y)}`));
  }
  if (ys.length > 1 && !xlabels) {
    svg.append(svgEl("polyline", { points: ys.map((y, i) => `${sx(i)},${sy(y)}`).join(" "), class: "spc-trace" }));
  }
  ys.forEach((y, i) => svg.append(svgEl("circle", { cx: sx(i), cy: sy(y), r: 3, class: flagged.has(i) ? "spc-dot ooc" : "spc-dot" })));
  if (xlabels) xlabels.forEach((t, i) => svg.append(svgEl("text", { x: sx(i), y: H - 12, class: "spc-tick", "text-anchor": "middle" }, t)));
  return svg;
}

async function spcShow(parameter) {
  const status = document.getElementById("spc-status");
  const charts = document.getElementById("spc-charts");
  const summary = document.getElementById("spc-summary");
  const sel = document.getElementById("spc-parameter");
  try {
    const q = parameter ? "?parameter=" + encodeURIComponent(parameter) : "";
    const r = await api("/api/spc" + q);
    if (!r.parameter) { status.textContent = "No judged run yet."; return; }
    status.textContent = "";
    sel.replaceChildren(...r.parameters.map((p) => el("option", { value: p }, p)));
    sel.value = r.parameter;
    const c = r.chart, cap = r.capability;
    summary.replaceChildren(
      el("span", { class: "spc-fig", "data-fig": "n" }, `n ${cap.n}`),
      el("span", { class: "spc-fig", "data-fig": "cpk" }, `Cpk ${num(cap.cpk)}`),
      el("span", { class: "spc-fig", "data-fig": "ppk" }, `Ppk ${num(cap.ppk)}`),
      el("span", { class: "spc-fig" }, `mean ${num(cap.mean)} ${r.unit}`),
      el("span", { class: "spc-fig" }, `σ within ${num(cap.sigma_within)}`),
      el("span", { class: "spc-fig" }, `limits ${num(cap.low)} .. ${num(cap.high)}`),
      el("span", { class: "spc-fig", "data-fig": "ooc" }, `out of control ${c.out_of_control.length}`),
      el("span", { class: "spc-fig" }, `out of spec ${cap.out_of_spec}`));
    const ys = r.points.map((p) => p.value);
    const spec = [{ y: cap.low, label: "LSL", cls: "spec" }, { y: cap.high, label: "USL", cls: "spec" }];
    const h = r.histogram;
    charts.replaceChildren(
      chart(`Individuals: ${r.parameter}`, { ys, unit: r.unit, flagged: new Set(c.out_of_control), lines: [
        { y: c.mean, label: "mean", cls: "centre" }, { y: c.ucl, label: "UCL", cls: "ctl" }, { y: c.lcl, label: "LCL", cls: "ctl" }, ...spec] }),
      chart("Moving range", { ys: c.moving_ranges.length ? c.moving_ranges : [0], unit: r.unit, lines: [
        { y: c.mr_bar, label: "MR̄", cls: "centre" }, { y: c.mr_ucl, label: "UCL", cls: "ctl" }] }),
      chart("Histogram", { ys: [0], unit: "count", bars: { counts: h.counts, lo: h.edges[0], hi: h.edges[h.edges.length - 1] },
        lines: [{ x: cap.low, label: "LSL", cls: "spec" }, { x: cap.high, label: "USL", cls: "spec" }, { x: cap.mean, label: "mean", cls: "centre" }] }),
      chart("Mean per slot", { ys: r.slots.map((s) => s.mean), xlabels: r.slots.map((s) => s.slot), unit: r.unit, lines: spec }));
    const table = document.getElementById("yield-table");
    table.replaceChildren(el("tr", {}, ...["yield by", "group", "judged", "pass", "marginal", "fail", "error", "yield"].map((t) => el("th", {}, t))));
    for (const by of ["batch", "day", "product", "station"]) {
      for (const y of r.yield[by] || []) {
        table.append(el("tr", { "data-by": by }, el("td", {}, by), el("td", {}, y.key), el("td", {}, y.judged), el("td", {}, y.passed),
          el("td", {}, y.marginal), el("td", {}, y.failed), el("td", {}, y.errors), el("td", {}, y.yield_pct === null ? "–" : fmt(y.yield_pct, 1) + " %")));
      }
    }
  } catch (e) { status.textContent = e.message; }
}

function spcInit() {
  const go = document.getElementById("spc-go");
  if (!go) return;
  go.addEventListener("click", () => spcShow(document.getElementById("spc-parameter").value));
  document.getElementById("spc-parameter").addEventListener("change", (e) => spcShow(e.target.value));
  document.getElementById("spc-csv").addEventListener("click", async () => {
    const p = document.getElementById("spc-parameter").value;
    const url = await blobUrl("/api/spc.csv" + (p ? "?parameter=" + encodeURIComponent(p) : ""));
    const a = el("a", { href: url, download: `spc-${p || "all"}.csv` }); document.body.append(a); a.click(); a.remove();
  });
}

window.loadSpc = () => spcShow(document.getElementById("spc-parameter").value || undefined);
document.addEventListener("DOMContentLoaded", spcInit);

// ---- replays (station replay) ----------------------------------------------------------------------
async function loadReplays() {
  const table = document.getElementById("replay-table");
  const status = document.getElementById("replay-status");
  table.replaceChildren();
  try {
    const rows = await api("/api/replays?limit=20");
    status.textContent = rows.length ? "" : "No replay yet.";
    if (!rows.length) return;
    table.append(el("tr", {}, ...["batch", "when", "source", "DUTs", "unchanged", "changed", "verdicts changed", "plate"]
      .map((h) => el("th", {}, h))));
    for (const r of rows) {
      const s = r.summary || {};
      const verdicts = (s.verdicts_changed || []).map((v) => `${v.serial} ${v.before} → ${v.after}`).join(", ");
      const tr = el("tr", { class: "clickable", "data-batch": String(r.batch_id), "data-changed": String(s.changed ?? "") },
        el("td", {}, String(r.batch_id)), el("td", {}, r.created_at ? new Date(r.created_at).toLocaleString() : "–"),
        el("td", {}, r.replay_of), el("td", {}, String(s.duts ?? "–")), el("td", {}, String(s.unchanged ?? "–")),
        el("td", { class: s.changed ? "bad" : "" }, String(s.changed ?? (r.state === "running" ? "running" : "–"))),
        el("td", {}, verdicts || "none"),
        el("td", {}, r.plate_agrees === null || r.plate_agrees === undefined ? "–" : (r.plate_agrees ? "agrees" : "DISAGREES")));
      tr.addEventListener("click", () => showReplay(r.batch_id));
      table.append(tr);
    }
  } catch (e) { status.textContent = e.message; }
}

async function showReplay(batchId) {
  const box = document.getElementById("replay-detail");
  box.replaceChildren();
  try {
    const r = await api(`/api/replays/${batchId}`);
    const d = r.diff;
    if (!d) { box.append(el("p", { class: "muted" }, "This replay has not finished.")); return; }
    box.append(el("h3", {}, `Replay batch ${batchId}: ${d.summary.unchanged} unchanged, ${d.summary.changed} changed ` +
      `(before = ${d.before}; tolerance rtol ${d.rtol}, atol ${d.atol})`));
    const t = el("table", { class: "records-table", id: "replay-changes" });
    t.append(el("tr", {}, ...["slot", "serial", "samples", "what changed (before → after)"].map((h) => el("th", {}, h))));
    for (const u of d.duts) {
      const what = u.changes.map((c) => `${c.key} ${fmtv(c.before)} → ${fmtv(c.after)}`).join("; ");
      t.append(el("tr", { "data-serial": u.serial },
        el("td", {}, u.slot), el("td", {}, u.serial),
        el("td", {}, u.samples_identical === null ? "–" : (u.samples_identical ? "identical" : "DIFFERENT")),
        el("td", { class: u.changed ? "bad" : "" }, what || "unchanged")));
    }
    box.append(t);
  } catch (e) { box.append(el("p", { class: "muted" }, e.message)); }
}

function fmtv(v) { return typeof v === "number" ? Number(v).toPrecision(6) : String(v); }

async function loadRecords() {
  await Promise.all([loadAudit(), loadReplays(), window.loadSpc ? window.loadSpc() : null]);
}

window.loadRecords = loadRecords;
