// Records view: filters, SPC per product and limits version (run rules named on the
// points, Cpk from n >= 25 with its interval), the failure Pareto, each with a CSV of what is shown
// (drawn here as SVG, no library), replays and the audit trail (admin). Uses app.js's globals (api,
// blobUrl, el, fmt, S); loaded after it. Its messages and the audit's columns come from i18n.js (t);
// the charts' statistical labels (UCL, Cpk, run rules, ...) are not translated yet.
"use strict";

async function loadAudit() {
  const table = document.getElementById("audit-table");
  const status = document.getElementById("audit-status");
  table.replaceChildren();
  if (S.role !== "admin") { status.textContent = t("records.audit_admin_only"); return; }
  try {
    const rows = await api("/api/audit?limit=50");
    status.textContent = rows.length ? "" : t("records.no_audit");
    table.append(el("tr", {}, ...["time", "station", "who", "action", "target", "detail"].map((h) => el("th", {}, t("audit." + h)))));
    for (const a of rows) {
      table.append(el("tr", { "data-action": a.action },
        el("td", {}, I18N.dateTime(a.at)), el("td", {}, a.station), el("td", {}, a.actor),
        el("td", {}, a.action), el("td", {}, a.target),
        el("td", { class: "detail" }, Object.entries(a.detail || {}).map(([k, v]) => `${k}: ${JSON.stringify(v)}`).join(", "))));
    }
  } catch (e) { status.textContent = e.message; }
}

// ---- SPC and failure Pareto (SVG drawn here from /api/records/spc and /api/records/pareto) -----------
// The SVG namespace, as the HTML parser gave it to the page's own <svg id="svg-ns"> (no URL literal
// in the page's files: tests/test_web_api.py keeps them free of any http address).
const SVGNS = document.getElementById("svg-ns").namespaceURI;
// What is shown (its CSV query) and a counter per view: an answer older than the last request is dropped
const REC_STATE = { group: null, parameter: null, spcCsv: null, paretoCsv: null, spcSeq: 0, paretoSeq: 0 };

function svgEl(tag, attrs, text) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

const given = (v) => v !== null && v !== undefined;
function num(v, d = 3) { return given(v) ? Number(v).toPrecision(d) : "–"; }
function cell(v) { return given(v) ? String(v) : ""; }  // the CSV's spelling: numbers in full, no limit = empty
const when = (at) => (at || "").replace("T", " ").replace("Z", "");  // "2026-11-20 08:00:00" (UTC)

function frame(title, W, H, box) {
  const svg = svgEl("svg", { viewBox: `0 0 ${W} ${H}`, class: "spc-chart", role: "img", "aria-label": title });
  svg.append(svgEl("text", { x: box.L, y: 14, class: "spc-title" }, title));
  svg.append(svgEl("rect", { x: box.L, y: box.T, width: W - box.L - box.R, height: H - box.T - box.B, class: "spc-frame" }));
  return svg;
}

function yScale(vals, T, bottom) {
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (!(hi > lo)) { lo -= 1; hi += 1; }
  const pad = (hi - lo) * 0.08; lo -= pad; hi += pad;
  return { lo, hi, y: (v) => T + ((hi - v) * (bottom - T)) / (hi - lo) };
}

function yTicks(svg, s, L) {
  for (const f of [0, 0.5, 1]) {
    const v = s.lo + f * (s.hi - s.lo);
    svg.append(svgEl("text", { x: L - 4, y: s.y(v) + 3, class: "spc-tick", "text-anchor": "end" }, num(v)));
  }
}

// Horizontal lines with their labels at the right end; labels closer than 10 px are spread apart.
function hlines(svg, s, L, Rx, lines) {
  const labels = [];
  for (const l of lines.filter((l) => given(l.y))) {
    svg.append(svgEl("line", { x1: L, x2: Rx, y1: s.y(l.y), y2: s.y(l.y), class: "spc-line " + l.cls }));
    labels.push({ y: s.y(l.y) - 3, text: `${l.label} ${num(l.y)}` });
  }
  labels.sort((a, b) => a.y - b.y);
  for (let i = 1; i < labels.length; i++) labels[i].y = Math.max(labels[i].y, labels[i - 1].y + 10);
  for (const l of labels) svg.append(svgEl("text", { x: Rx - 2, y: l.y, class: "spc-label", "text-anchor": "end" }, l.text));
}

function pointText(p, unit) {
  const rules = p.flags.map((f) => `${f.rule} (${f.name})`).join(", ");
  return `${p.serial} · run ${p.run_id} · #${p.index} · ${when(p.at)} UTC · ${p.value} ${unit} · ${p.spec}` +
    (rules ? ` · rules ${rules}` : "");
}

// The individuals chart: x = run index in the group, dates as tick labels; each point against its own limits.
function individualsChart(r) {
  const W = 760, H = 270, box = { L: 56, R: 12, T: 22, B: 50 };
  const pts = r.points, c = r.chart, n = pts.length, unit = r.label.replace(/^.*\(|\)$/g, "");
  const svg = frame(`Individuals: ${r.label}`, W, H, box);
  svg.classList.add("wide");
  const specs = pts.flatMap((p) => [p.low, p.high]).filter(given);
  const s = yScale([...pts.map((p) => p.value), ...specs, ...[c.ucl, c.lcl].filter(given)], box.T, H - box.B);
  const x = (i) => box.L + 8 + (n <= 1 ? (W - box.L - box.R - 16) / 2 : (i * (W - box.L - box.R - 16)) / (n - 1));
  yTicks(svg, s, box.L);
  hlines(svg, s, box.L, W - box.R, [{ y: c.ucl, label: "UCL", cls: "ctl" }, { y: c.mean, label: "mean", cls: "centre" },
    { y: c.lcl, label: "LCL", cls: "ctl" }]);
  for (const [k, name] of [["high", "USL"], ["low", "LSL"]]) {  // the spec limits as each run had them (a step if they changed)
    const seg = pts.map((p, i) => (given(p[k]) ? `${x(i)},${s.y(p[k])}` : null)).filter(Boolean);
    if (!seg.length) continue;
    svg.append(svgEl("polyline", { points: seg.join(" "), class: "spc-line spec", "data-spec": name }));
    const last = pts[n - 1][k];
    if (given(last)) svg.append(svgEl("text", { x: box.L + 4, y: s.y(last) - 3, class: "spc-label spec" }, `${name} ${num(last)}`));
  }
  if (n > 1) svg.append(svgEl("polyline", { points: pts.map((p, i) => `${x(i)},${s.y(p.value)}`).join(" "), class: "spc-trace" }));
  const ticks = Math.min(n, 6);
  for (let k = 0; k < ticks; k++) {  // x axis: run index, and the judging date under it
    const i = ticks === 1 ? 0 : Math.round((k * (n - 1)) / (ticks - 1));
    const tx = x(i), ty = H - box.B;
    svg.append(svgEl("line", { x1: tx, x2: tx, y1: ty, y2: ty + 4, class: "spc-frame" }));
    const anchor = ticks > 1 && k === 0 ? "start" : (ticks > 1 && k === ticks - 1 ? "end" : "middle");
    svg.append(svgEl("text", { x: tx, y: ty + 15, class: "spc-tick x-tick", "text-anchor": anchor }, `#${pts[i].index}`));
    svg.append(svgEl("text", { x: tx, y: ty + 27, class: "spc-tick x-date", "text-anchor": anchor }, (pts[i].at || "").slice(0, 10)));
  }
  svg.append(svgEl("text", { x: (W + box.L) / 2, y: H - 6, class: "spc-tick", "text-anchor": "middle" }, "run # in this group · judged date (UTC)"));
  pts.forEach((p, i) => {
    const rules = p.flags.filter((f) => f.rule !== "MR").map((f) => f.rule);
    const mr = p.flags.some((f) => f.rule === "MR");
    const cx = x(i), cy = s.y(p.value);
    const g = svgEl("g", { class: "spc-pt" + (p.out_of_spec ? " oos" : "") + (rules.length ? " rule" : "") + (mr ? " mr" : ""),
      "data-index": String(p.index), "data-run": String(p.run_id), "data-rules": p.flags.map((f) => f.rule).join(","), tabindex: "0" });
    if (rules.length) g.append(svgEl("path", { d: `M${cx},${cy - 6}L${cx + 6},${cy}L${cx},${cy + 6}L${cx - 6},${cy}Z`, class: "spc-mark rule" }));
    else if (mr) g.append(svgEl("path", { d: `M${cx},${cy - 6}L${cx + 6},${cy + 5}L${cx - 6},${cy + 5}Z`, class: "spc-mark mr" }));
    else g.append(svgEl("circle", { cx, cy, r: 3.2, class: "spc-dot" }));
    if (p.out_of_spec) g.append(svgEl("circle", { cx, cy, r: 8, class: "spc-oos-ring" }));
    if (rules.length && n <= 60) g.append(svgEl("text", { x: cx, y: cy - 9, class: "spc-rule-label", "text-anchor": "middle" }, rules.join(",")));
    g.append(svgEl("title", {}, pointText(p, unit)));
    const show = () => { document.getElementById("spc-point").textContent = pointText(p, unit); };
    g.addEventListener("click", show);
    g.addEventListener("focus", show);
    svg.append(g);
  });
  return svg;
}

// A small chart: ys at equal steps (or categories), horizontal lines, or histogram bars.
function chart(title, { ys, lines = [], bars = null, xlabels = null, unit = "" }) {
  const W = 460, H = 220, box = { L: 56, R: 10, T: 22, B: 30 };
  const svg = frame(title, W, H, box);
  svg.append(svgEl("text", { x: 4, y: box.T + 8, class: "spc-tick" }, unit));
  if (bars) {
    const bw = (W - box.L - box.R) / bars.counts.length, top = Math.max(1, ...bars.counts), hh = H - box.T - box.B;
    const bx = (v) => box.L + ((v - bars.lo) * (W - box.L - box.R)) / (bars.hi - bars.lo);
    svg.append(svgEl("text", { x: box.L - 4, y: box.T + 8, class: "spc-tick", "text-anchor": "end" }, String(top)));
    bars.counts.forEach((c, i) => svg.append(svgEl("rect", { x: box.L + i * bw + 1, width: Math.max(1, bw - 2),
      y: box.T + (1 - c / top) * hh, height: (c / top) * hh, class: "spc-bar" })));
    for (const l of lines.filter((l) => given(l.x))) {
      svg.append(svgEl("line", { x1: bx(l.x), x2: bx(l.x), y1: box.T, y2: H - box.B, class: "spc-line " + l.cls }));
      svg.append(svgEl("text", { x: bx(l.x) + 2, y: box.T + 10, class: "spc-label" }, l.label));
    }
    svg.append(svgEl("text", { x: box.L, y: H - 8, class: "spc-tick" }, num(bars.lo)));
    svg.append(svgEl("text", { x: W - box.R, y: H - 8, class: "spc-tick", "text-anchor": "end" }, num(bars.hi)));
    return svg;
  }
  const s = yScale([...ys, ...lines.map((l) => l.y).filter(given)], box.T, H - box.B);
  const n = ys.length;
  const sx = xlabels ? (i) => box.L + ((i + 0.5) * (W - box.L - box.R)) / n
    : (i) => box.L + (n <= 1 ? (W - box.L - box.R) / 2 : (i * (W - box.L - box.R)) / (n - 1));
  yTicks(svg, s, box.L);
  hlines(svg, s, box.L, W - box.R, lines);
  if (n > 1 && !xlabels) svg.append(svgEl("polyline", { points: ys.map((y, i) => `${sx(i)},${s.y(y)}`).join(" "), class: "spc-trace" }));
  ys.forEach((y, i) => svg.append(svgEl("circle", { cx: sx(i), cy: s.y(y), r: 3, class: "spc-dot" })));
  const every = xlabels ? Math.ceil(xlabels.length / 10) : 1;  // at most ~10 category labels: they must not overlap
  if (xlabels) xlabels.forEach((t, i) => { if (i % every === 0) svg.append(svgEl("text", { x: sx(i), y: H - 12, class: "spc-tick", "text-anchor": "middle" }, t)); });
  return svg;
}

// ---- filters: the query of every records answer (and of its CSV) ------------------------------------
function filterQuery() {
  const q = new URLSearchParams();
  for (const [k, id] of [["from", "f-from"], ["to", "f-to"], ["product", "f-product"], ["station", "f-station"], ["work_order", "f-work-order"]]) {
    const v = document.getElementById(id).value;
    if (v) q.set(k, v);
  }
  return q;
}

function fillSelect(id, options, allLabel) {
  const sel = document.getElementById(id), keep = sel.value;
  sel.replaceChildren(el("option", { value: "" }, allLabel),
    ...options.map((o) => el("option", { value: o.value }, `${o.label} (${o.runs})`)));
  sel.value = options.some((o) => o.value === keep) ? keep : "";
}

function cpkFig(cap) {
  if (!given(cap.cpk)) {
    const why = (cap.reason || "").startsWith("n=") ? `${cap.reason}: not computed` : `not computed: ${cap.reason}`;
    return el("span", { class: "spc-fig", "data-fig": "cpk" }, `Cpk ${why}`);
  }
  const ci = `(95 % CI ${num(cap.cpk_ci_low)}–${num(cap.cpk_ci_high)})`;
  if (!cap.below_target) return el("span", { class: "spc-fig", "data-fig": "cpk" }, `Cpk ${num(cap.cpk)} ${ci}`);
  return el("span", { class: "spc-fig cpk-low " + (cap.cpk < 1.0 ? "red" : "amber"), "data-fig": "cpk" },
    `Cpk ${num(cap.cpk)} ${ci} below ${cap.target}`);
}

async function spcShow(opts = {}) {
  const status = document.getElementById("spc-status");
  const q = filterQuery();
  const group = opts.group !== undefined ? opts.group : REC_STATE.group;
  const parameter = opts.parameter !== undefined ? opts.parameter : REC_STATE.parameter;
  if (group) q.set("group", group);
  if (parameter) q.set("parameter", parameter);
  const seq = ++REC_STATE.spcSeq;
  let r;
  try {
    r = await api("/api/records/spc?" + q.toString());
  } catch (e) {
    if (seq !== REC_STATE.spcSeq) return;
    if (e.status === 404 && (group || parameter)) return spcShow({ group: null, parameter: opts.keepParameter ? parameter : null });
    status.textContent = e.message;  // e.g. a 'from' after 'to': nothing stale stays on the screen
    for (const id of ["spc-charts", "spc-summary", "spc-points", "yield-table"]) document.getElementById(id).replaceChildren();
    REC_STATE.spcCsv = null;
    return;
  }
  if (seq !== REC_STATE.spcSeq) return;
  fillSelect("f-product", r.options.products, "all products");
  fillSelect("f-station", r.options.stations, "all stations");
  fillSelect("f-work-order", r.options.work_orders, "all work orders");
  const gsel = document.getElementById("spc-group"), psel = document.getElementById("spc-parameter");
  gsel.replaceChildren(...r.groups.map((g) => el("option", { value: g.key }, `${g.label} (${g.runs} runs)`)));
  psel.replaceChildren(...r.parameters.map((p) => el("option", { value: p }, r.parameter_labels[p] || p)));
  const charts = document.getElementById("spc-charts"), summary = document.getElementById("spc-summary");
  const table = document.getElementById("spc-points");
  REC_STATE.group = r.group ? r.group.key : null;
  REC_STATE.parameter = r.parameter || null;
  const shown = new URLSearchParams(filterQuery());
  if (r.group) shown.set("group", r.group.key);
  if (r.parameter) shown.set("parameter", r.parameter);
  REC_STATE.spcCsv = "/api/records/spc.csv?" + shown.toString();
  document.getElementById("spc-csv").setAttribute("data-src", REC_STATE.spcCsv);
  if (!r.group || !r.parameter) {
    status.textContent = t("records.no_judged_run");
    for (const n of [charts, summary, table]) n.replaceChildren();
    document.getElementById("spc-points-count").textContent = "0";
    return;
  }
  status.textContent = "";
  gsel.value = r.group.key; psel.value = r.parameter;
  const c = r.chart, cap = r.capability, unit = r.label.replace(/^.*\(|\)$/g, "");
  summary.replaceChildren(...[
    el("span", { class: "spc-fig", "data-fig": "group" }, r.group.label),
    el("span", { class: "spc-fig", "data-fig": "n" }, `n ${cap.n}`),
    cpkFig(cap),
    el("span", { class: "spc-fig", "data-fig": "ppk" }, `Ppk ${num(cap.ppk)}`),
    el("span", { class: "spc-fig" }, `mean ${num(cap.mean)} ${unit}`),
    el("span", { class: "spc-fig" }, `σ within ${num(cap.sigma_within)}`),
    el("span", { class: "spc-fig", "data-fig": "limits" }, `limits ${num(cap.low)} .. ${num(cap.high)}`),
    el("span", { class: "spc-fig", "data-fig": "flagged" }, `flagged ${c.flagged.length}` +
      (Object.keys(c.rule_counts).length ? ` (${Object.entries(c.rule_counts).map(([k, v]) => `${k}: ${v}`).join(", ")})` : "")),
    el("span", { class: "spc-fig", "data-fig": "oos" }, `out of spec (own limits) ${cap.out_of_spec}`),
    given(cap.cpk) && Object.keys(c.rule_counts).some((k) => k !== "MR")
      ? el("span", { class: "spc-fig warn", "data-fig": "control" }, "not in control: the Cpk describes no stable process") : null,
  ].filter(Boolean));
  const h = r.histogram;
  charts.replaceChildren(individualsChart(r),
    chart(`Moving range: ${r.label}`, { ys: c.moving_ranges.length ? c.moving_ranges : [0], unit, lines: [
      { y: c.mr_bar, label: "MR̄", cls: "centre" }, { y: c.mr_ucl, label: "UCL", cls: "ctl" }] }),
    chart("Histogram", { ys: [0], unit: "count", bars: { counts: h.counts, lo: h.edges[0], hi: h.edges[h.edges.length - 1] },
      lines: [{ x: cap.low, label: "LSL", cls: "spec" }, { x: cap.high, label: "USL", cls: "spec" }, { x: cap.mean, label: "mean", cls: "centre" }] }),
    chart("Mean per slot", { ys: r.slots.map((s) => s.mean), xlabels: r.slots.map((s) => s.slot), unit,
      lines: [{ y: cap.low, label: "LSL", cls: "spec" }, { y: cap.high, label: "USL", cls: "spec" }] }));
  document.getElementById("spc-legend").replaceChildren(
    "Marks: ● point  ◆ run rule (its numbers above it, up to 60 points)  ▲ moving range above D4·MR̄  ◯ ring: outside its own run's limits. Rules: ",
    ...Object.entries(r.rules).flatMap(([k, v]) => [el("span", { class: "rule-name" }, `${k}: ${v};`), " "]));
  table.replaceChildren(el("tr", {}, ...r.columns.map((t) => el("th", {}, t))));
  for (const p of r.points) {
    table.append(el("tr", { "data-run": String(p.run_id), class: p.out_of_spec ? "oos" : "" },
      ...[p.index, p.run_id, p.batch_id, p.station, p.slot, p.serial, p.at, p.value, cell(p.low), cell(p.high), p.spec,
        p.outcome || "", p.flags.map((f) => `${f.rule}: ${f.name}`).join("; ")].map((v) => el("td", {}, cell(v)))));
  }
  document.getElementById("spc-points-count").textContent = String(r.points.length);
  const yt = document.getElementById("yield-table");
  // per group: the judged attempts by verdict, then its DUTs' first-pass and final yield (GET /api/yield's rule)
  const pct = (v) => (given(v) ? fmt(v, 1) + " %" : "–");
  yt.replaceChildren(el("tr", {}, ...[["yield by"], ["group"], ["judged", "judged attempts"], ["pass"], ["marginal"], ["fail"], ["error"],
    ["DUTs", "DUTs with a judged attempt in the group"], ["first pass", "DUTs whose first judged attempt passed"],
    ["final", "DUTs whose latest valid (non-error) attempt passed"]].map(([t, title]) => el("th", { title }, t))));
  for (const by of ["batch", "day", "product", "limits", "station"]) {
    for (const y of r.yield[by] || []) {
      yt.append(el("tr", { "data-by": by }, el("td", {}, by), el("td", {}, y.key), el("td", {}, y.judged), el("td", {}, y.passed),
        el("td", {}, y.marginal), el("td", {}, y.failed), el("td", {}, y.errors), el("td", { class: "duts" }, y.duts),
        el("td", { class: "first-pass", title: `${y.first_pass} of ${y.duts} DUTs` }, pct(y.first_pass_pct)),
        el("td", { class: "final", title: `${y.final_pass} of ${y.duts} DUTs` }, pct(y.final_pct))));
    }
  }
}

// ---- failure Pareto: bars + cumulative line --------------------------------------------------------
function paretoChart(title, rows) {
  const W = 460, H = 270, box = { L: 40, R: 40, T: 22, B: 98 }, MAX = 12;
  const svg = frame(title, W, H, box);
  const shown = rows.slice(0, MAX), top = Math.max(1, ...shown.map((r) => r.count)), hh = H - box.T - box.B;
  const bw = (W - box.L - box.R) / Math.max(1, shown.length);
  const cy = (pct) => box.T + (1 - pct / 100) * hh;
  svg.append(svgEl("text", { x: box.L - 4, y: box.T + 8, class: "spc-tick", "text-anchor": "end" }, String(top)));
  svg.append(svgEl("text", { x: box.L - 4, y: H - box.B, class: "spc-tick", "text-anchor": "end" }, "0"));
  for (const pct of [0, 50, 100]) svg.append(svgEl("text", { x: W - box.R + 4, y: cy(pct) + 3, class: "spc-tick" }, `${pct} %`));
  shown.forEach((r, i) => {
    const x = box.L + i * bw;
    const bar = svgEl("rect", { x: x + 2, width: Math.max(1, bw - 4), y: box.T + (1 - r.count / top) * hh, height: (r.count / top) * hh,
      class: "pareto-bar", "data-what": r.what });
    bar.append(svgEl("title", {}, `${r.what}: ${r.count} (${r.pct.toFixed(1)} %)` + (r.example ? ` · e.g. ${r.example}` : "")));
    svg.append(bar);
    const lx = x + bw / 2, ly = H - box.B + 10;
    svg.append(svgEl("text", { x: lx, y: ly, class: "spc-tick", "text-anchor": "end", transform: `rotate(-35 ${lx} ${ly})` },
      r.what.length > 28 ? r.what.slice(0, 27) + "…" : r.what));
  });
  if (shown.length) {
    const pts = shown.map((r, i) => `${box.L + (i + 0.5) * bw},${cy(r.cum_pct)}`);
    svg.append(svgEl("polyline", { points: pts.join(" "), class: "pareto-cum" }));
    pts.forEach((p) => { const [x, y] = p.split(","); svg.append(svgEl("circle", { cx: x, cy: y, r: 2.5, class: "pareto-cum-dot" })); });
  }
  if (rows.length > MAX) svg.append(svgEl("text", { x: W - box.R, y: 14, class: "spc-tick", "text-anchor": "end" }, `+${rows.length - MAX} more in the table`));
  return svg;
}

async function paretoShow() {
  const status = document.getElementById("pareto-status");
  const q = filterQuery().toString();
  REC_STATE.paretoCsv = "/api/records/pareto.csv" + (q ? "?" + q : "");
  document.getElementById("pareto-csv").setAttribute("data-src", REC_STATE.paretoCsv);
  const seq = ++REC_STATE.paretoSeq;
  try {
    const p = await api("/api/records/pareto" + (q ? "?" + q : ""));
    if (seq !== REC_STATE.paretoSeq) return;
    status.textContent = `${p.runs} judged runs: ${p.runs_failed} failed, ${p.runs_error} error.`;
    document.getElementById("pareto-charts").replaceChildren(
      paretoChart("Failing checks (fail + error)", p.checks), paretoChart("Why runs do not pass (one cause per run)", p.causes));
    const t = document.getElementById("pareto-table");
    t.replaceChildren(el("tr", {}, ...p.columns.map((c) => el("th", {}, c))));
    for (const r of [...p.checks, ...p.causes]) {
      t.append(el("tr", { "data-table": r.table, title: r.example || "" }, ...[r.table, r.rank, r.what, r.fail, r.error, r.count,
        r.pct.toFixed(1), r.cum_pct.toFixed(1)].map((v) => el("td", {}, String(v)))));
    }
  } catch (e) {
    if (seq !== REC_STATE.paretoSeq) return;
    status.textContent = e.message;
    for (const id of ["pareto-charts", "pareto-table"]) document.getElementById(id).replaceChildren();
    REC_STATE.paretoCsv = null;
  }
}

async function downloadCsv(src, name) {
  if (!src) return;
  const url = await blobUrl(src);
  const a = el("a", { href: url, download: name }); document.body.append(a); a.click(); a.remove();
}

function spcInit() {
  if (!document.getElementById("spc-group")) return;
  const refilter = () => Promise.all([spcShow({ group: null, keepParameter: true }), paretoShow()]);
  for (const id of ["f-from", "f-to", "f-product", "f-station", "f-work-order"]) document.getElementById(id).addEventListener("change", refilter);
  document.getElementById("f-clear").addEventListener("click", () => {
    for (const id of ["f-from", "f-to", "f-product", "f-station", "f-work-order"]) document.getElementById(id).value = "";
    refilter();
  });
  document.getElementById("spc-group").addEventListener("change", (e) => spcShow({ group: e.target.value, parameter: REC_STATE.parameter, keepParameter: true }));
  document.getElementById("spc-parameter").addEventListener("change", (e) => spcShow({ parameter: e.target.value }));
  document.getElementById("spc-csv").addEventListener("click", (e) => { e.preventDefault(); downloadCsv(REC_STATE.spcCsv, `spc-${REC_STATE.parameter || "none"}.csv`); });
  document.getElementById("pareto-csv").addEventListener("click", (e) => { e.preventDefault(); downloadCsv(REC_STATE.paretoCsv, "failure-pareto.csv"); });
}

window.loadSpc = () => Promise.all([spcShow(), paretoShow()]);
document.addEventListener("DOMContentLoaded", spcInit);

// ---- replays (station replay) ----------------------------------------------------------------------
async function loadReplays() {
  const table = document.getElementById("replay-table");
  const status = document.getElementById("replay-status");
  table.replaceChildren();
  try {
    const rows = await api("/api/replays?limit=20");
    status.textContent = rows.length ? "" : t("records.no_replay");
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
    if (!d) { box.append(el("p", { class: "muted" }, t("records.replay_unfinished"))); return; }
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
