// Model diagnostics panel (design 7): for a stored run, rank the effects missing from the
// baseline thermal model; click an effect to add it and watch the error staircase fall.
// Uses app.js's globals (S for the token, el, fmt, showPlot); loaded after it.
//
// The server bounds diagnosis work (web/diag_plots.py): when too many diagnoses or plots run or
// wait it answers 429 with Retry-After. So the panel asks politely: the plots go through a queue
// (DIAG_PLOT_CONCURRENCY in flight, the server's own plot limit), every request that meets 429 (or
// 503 with Retry-After) waits the time the server asked for (capped) and tries again, at most
// DIAG_MAX_TRIES times, and every plot and the diagnosis itself say in words what they wait for.
// The server renders a report's plots as soon as it has computed the report (web/diag_plots.py), in
// the order of doc.plots, so by the time the ranking is on screen the first plots are ready.
//
// Words, never labels: the leftover statement first (is anything left that the model misses?), each
// flag in words (doc.ranking[].flags_text, else diagFlagWords), each candidate's `why`, and the
// orientations as the CLI names them ("position 0 (P)").
"use strict";

const DIAG = { runId: null, serial: "", add: [], busy: false, plots: [], leftover: null, gen: 0, urls: [], queue: [],
  workers: 0 };
const DIAG_PLOT_CONCURRENCY = 2;  // = the server's MAX_RUNNING_PLOTS: more in flight only earns 429s
const DIAG_MAX_TRIES = 12;        // per request; then it gives up with a message and a Retry button
const DIAG_MAX_WAIT_S = 15;       // cap on one Retry-After wait
// the admission gate (station/diagnostics/gate.py), for the reasons derived when a row has no "why"
const DIAG_GATE = { bic: -30, p: 1e-3, gain: 0.03 };

class DiagCancelled extends Error {}

function diagCheck(gen) {
  if (gen !== DIAG.gen) throw new DiagCancelled("superseded");
}

function diagQuery() {
  return DIAG.add.map((e) => "add=" + encodeURIComponent(e)).join("&");
}

function diagUrl(suffix) {
  const q = diagQuery();
  return `/api/runs/${DIAG.runId}/diagnosis${suffix || ""}${q ? "?" + q : ""}`;
}

// ---- requests: the page's bearer token, retried on 429 --------------------------------------------
function diagSleep(ms) {
  return new Promise((resolve) => setTimeout(resolve, ms));
}

// seconds the server asked us to wait (Retry-After: seconds or an HTTP date), capped; backoff if absent
function diagRetryAfter(resp, attempt) {
  const h = resp.headers.get("Retry-After");
  let s = NaN;
  if (h !== null) {
    s = Number(h);
    if (!Number.isFinite(s)) s = (Date.parse(h) - Date.now()) / 1000;
  }
  if (!Number.isFinite(s)) s = Math.min(2 ** (attempt - 1), DIAG_MAX_WAIT_S);
  return Math.min(Math.max(s, 1), DIAG_MAX_WAIT_S);
}

async function diagDetail(resp) {
  let detail = `${resp.status} ${resp.statusText}`;
  try { const j = await resp.json(); if (j.detail) detail = typeof j.detail === "string" ? j.detail : JSON.stringify(j.detail); } catch (_) { /* not json */ }
  return detail;
}

// GET `path` with the page's token; on 429 (or 503 with Retry-After) wait and retry.
// hooks.onTry(attempt) before each try; hooks.onWait(secondsLeft, attempt) every second of a wait.
async function diagRequest(path, gen, hooks = {}) {
  for (let attempt = 1; ; attempt++) {
    diagCheck(gen);
    if (hooks.onTry) hooks.onTry(attempt);
    const headers = {};
    if (S.token) headers["Authorization"] = "Bearer " + S.token;
    let resp;
    try {
      resp = await fetch(path, { headers });
    } catch (e) {
      throw new Error("the station did not answer (" + e.message + ")");
    }
    diagCheck(gen);
    if (resp.ok) return resp;
    const retryable = resp.status === 429 || (resp.status === 503 && resp.headers.has("Retry-After"));
    if (!retryable) {
      const err = new Error(await diagDetail(resp));
      err.status = resp.status;
      throw err;
    }
    const wait = diagRetryAfter(resp, attempt);
    try { await resp.body?.cancel(); } catch (_) { /* already closed */ }
    if (attempt >= DIAG_MAX_TRIES) {
      const err = new Error(`gave up after ${attempt} tries: the station stayed too busy to serve it (HTTP ${resp.status})`);
      err.status = resp.status;
      throw err;
    }
    // the wait, counted down in whole seconds; a little jitter so queued requests do not return in step
    const until = performance.now() + wait * 1000 + Math.random() * 250;
    for (;;) {
      const left = until - performance.now();
      if (left <= 0) break;
      if (hooks.onWait) hooks.onWait(Math.max(1, Math.round(left / 1000)), attempt);
      await diagSleep(Math.min(left, left % 1000 || 1000));  // to the next whole second left
      diagCheck(gen);
    }
  }
}

// ---- the panel -------------------------------------------------------------------------------------
async function diagnoseRun(runId, serial) {
  DIAG.runId = runId;
  DIAG.serial = serial || "";
  DIAG.add = [];
  const panel = document.getElementById("diag-panel");
  panel.classList.remove("hidden");
  panel.scrollIntoView({ behavior: "smooth", block: "start" });
  await diagRefresh();
}

function diagToggle(effect) {
  if (DIAG.busy) return;
  const i = DIAG.add.indexOf(effect);
  if (i >= 0) DIAG.add.splice(0, DIAG.add.length, ...DIAG.add.slice(0, i));  // remove it and what came after
  else DIAG.add.push(effect);
  diagRefresh();
}

// kind: "" (plain), "working" (a request under way), "error" (with an optional retry action)
function diagStatus(text, kind, retry) {
  const s = document.getElementById("diag-status");
  s.replaceChildren();
  if (text) s.append(text);
  if (retry) s.append(" ", el("button", { type: "button", class: "btn small diag-retry", onclick: retry }, "Retry"));
  s.className = kind === "error" ? "error" : kind === "working" ? "muted diag-working" : "muted";
  s.dataset.state = kind || (text ? "info" : "idle");
}

function diagStop() {
  DIAG.gen += 1;  // every request and wait of the previous generation stops at its next check
  DIAG.queue = [];
  DIAG.workers = 0;  // workers of the previous generation no longer count (nor decrement)
}

async function diagRefresh() {
  diagStop();
  const gen = DIAG.gen;
  DIAG.busy = true;
  const title = document.getElementById("diag-title");
  title.textContent = `Model diagnostics · ${DIAG.serial} run ${DIAG.runId}` +
    (DIAG.add.length ? ` · baseline + ${DIAG.add.join(" + ")}` : " · baseline");
  document.getElementById("diag-plots").replaceChildren();
  diagLeftover(null);  // the previous model's statement is not this one's
  const t0 = performance.now();
  let phase = "fitting the models (held-out validation of every candidate: this can take a minute)";
  const show = () => {
    if (gen === DIAG.gen) diagStatus(`${phase} · ${Math.floor((performance.now() - t0) / 1000)} s`, "working");
  };
  show();
  const ticker = setInterval(show, 1000);
  try {
    const resp = await diagRequest(diagUrl(), gen, {
      onTry: (attempt) => {
        phase = "fitting the models (held-out validation of every candidate: this can take a minute)" +
          (attempt > 1 ? ` · try ${attempt} of ${DIAG_MAX_TRIES}` : "");
        show();
      },
      onWait: (left, attempt) => {
        phase = `the station is busy with other diagnoses: waiting ${left} s before try ${attempt + 1} of ${DIAG_MAX_TRIES}`;
        show();
      },
    });
    const doc = await resp.json();
    diagCheck(gen);
    clearInterval(ticker);
    diagRender(doc);
    diagStatus("");
    diagLoadPlots(gen);
  } catch (e) {
    if (!(e instanceof DiagCancelled) && gen === DIAG.gen) diagStatus("Diagnosis failed: " + e.message, "error", () => diagRefresh());
  } finally {
    clearInterval(ticker);
    if (gen === DIAG.gen) DIAG.busy = false;
  }
}

// The leftover statement (station/diagnostics/leftover.py): said first, above everything else, when
// the report has one; with the plots that show what is missing.
function diagLeftover(doc) {
  const box = document.getElementById("diag-leftover");
  if (!box) return;
  box.replaceChildren();
  box.className = "diag-leftover";
  delete box.dataset.above;
  const lo = doc && doc.leftover;
  if (!lo || typeof lo.statement !== "string" || !lo.statement.trim()) return;
  box.dataset.above = lo.above_floor ? "yes" : "no";
  box.classList.add(lo.above_floor ? "above" : "at-floor");
  box.append(el("span", { class: "diag-leftover-statement" }, lo.statement));
  const views = (lo.carrying || []).filter((p) => (doc.plots || []).includes(p));
  if (lo.above_floor && views.length) {
    box.append(el("span", { class: "diag-leftover-look" }, "Look at: ",
      ...views.flatMap((p, i) => [i ? ", " : "", el("button", { type: "button", class: "link", "data-plot": p,
        onclick: () => document.querySelector(`#diag-plots figure[data-plot="${p}"]`)?.scrollIntoView({ behavior: "smooth", block: "center" }) },
      diagPlotTitle(p))])));
  }
}

// A flag of a ranking row in words (the server's flags_text says the same; this is for a row without it).
function diagFlagWords(f) {
  const i = f.indexOf(":");
  const head = i < 0 ? f : f.slice(0, i);
  const rest = i < 0 ? "" : f.slice(i + 1);
  if (f === "no_evidence") return "no evidence on its own against the baseline";
  if (head === "confusable_with") return `confusable with ${diagList(rest)} on this data`;
  if (head === "explained_by") return `explained by ${diagList(rest)}, admitted before it`;
  if (head === "stands_for_it") return `${diagList(rest)}, admitted, stands for it (confusable on this data: only one goes in)`;
  if (head === "masked") {
    const j = rest.indexOf(":");
    const kind = j < 0 ? rest : rest.slice(0, j);
    const who = j < 0 ? "" : rest.slice(j + 1);
    if (kind === "evidence_given") return `its evidence shows only once ${diagList(who)} is in the model`;
    if (kind === "admitted_with") return `admitted together with ${diagList(who)} (each hides the other on the held-out legs)`;
    return `masked: ${kind.replaceAll("_", " ")}${who ? " " + who : ""}`;
  }
  return head.replaceAll("_", " ") + (rest ? ": " + rest : "");
}

function diagFlagTexts(r) {
  const flags = r.flags || [];
  const t = r.flags_text;
  return Array.isArray(t) && t.length === flags.length ? t.map(String) : flags.map(diagFlagWords);
}

// An orientation label of the report as the CLI says it ("position 0 (P)"); the server names them
// (doc.orientations), this is for a label it did not name.
function diagOrientationName(doc, label) {
  for (const list of Object.values((doc && doc.orientations) || {})) {
    const o = list.find((x) => String(x.label) === String(label));
    if (o) return o.name;
  }
  const k = Number(label);
  const name = Number.isInteger(k) && typeof positionNameOf === "function" ? positionNameOf({ position: k }) : "";
  return Number.isInteger(k) ? `position ${k}${name ? ` (${name})` : ""}` : `orientation ${label}`;
}

function diagPlotTitle(name) {
  return String(name).replaceAll("_", " ").replace(/^residual vs rate$/, "residual vs dT/dt");
}

function diagRender(doc) {
  diagLeftover(doc);

  // the orientations of the run, named as the CLI names them
  const or = document.getElementById("diag-orientations");
  if (or) {
    const parts = Object.entries(doc.orientations || {}).map(([serial, list]) =>
      (Object.keys(doc.orientations).length > 1 ? serial + ": " : "") + list.map((o) => o.name || diagOrientationName(doc, o.label)).join(", "));
    or.textContent = parts.length ? "Orientations in this run: " + parts.join("; ") : "";
  }

  // effect buttons: every library effect; added ones highlighted, in staircase order
  const effects = document.getElementById("diag-effects");
  const rows = new Map(doc.ranking.map((r) => [r.effect, r]));
  const unident = new Map(doc.unidentifiable.map((u) => [u.effect, u]));
  effects.replaceChildren(el("span", { class: "label" }, "Add an effect: "));
  for (const lib of doc.library) {
    const name = lib.effect;
    const r = rows.get(name);
    const added = DIAG.add.includes(name);
    let cls = "btn small diag-effect";
    if (added) cls += " added";
    else if (r && r.admitted) cls += " admitted";
    else if (unident.has(name)) cls += " unidentifiable";
    const tip = [lib.note, "identified by: " + lib.needs].join("\n");
    effects.append(el("button", { type: "button", class: cls, title: tip, "data-effect": name,
      onclick: () => diagToggle(name) }, (added ? "✓ " : "+ ") + name));
  }

  // staircase
  const st = document.getElementById("diag-staircase");
  st.replaceChildren(el("caption", {}, `Error staircase (RMS of ${doc.rms_basis}, mg; residual = measured − model)`),
    el("tr", {}, el("th", {}, "model"), el("th", {}, "in-sample"), el("th", {}, "held-out")));
  for (const s of doc.staircase) {
    st.append(el("tr", {}, el("td", {}, s.model), el("td", {}, fmt(s.rms_mg, 4)), el("td", {}, fmt(s.heldout_rms_mg, 4))));
  }

  // ranking: every row says in words why it is (not) in the model
  const rk = document.getElementById("diag-ranking");
  rk.replaceChildren(el("caption", {}, "Candidates, best held-out first"),
    el("tr", {}, el("th", {}, "effect"), el("th", {}, "held-out mg"), el("th", {}, "ΔBIC"),
      el("th", {}, "score p"), el("th", { class: "diag-why" }, "admitted? why")));
  for (const r of doc.ranking) {
    const words = diagFlagTexts(r);
    rk.append(el("tr", { class: r.admitted ? "admitted" : "rejected", "data-effect": r.effect },
      el("td", { class: "diag-name" },
        el("button", { type: "button", class: "link", onclick: () => diagToggle(r.effect) }, r.effect),
        r.shape ? el("span", { class: "diag-shape" }, r.shape) : null),
      el("td", {}, fmt(r.heldout_rms_mg, 4)), el("td", {}, fmt(r.delta_bic, 1)),
      el("td", {}, diagP(r.score_p)),
      el("td", { class: "diag-why" },
        el("span", { class: "diag-reason" }, diagReason(r, doc)),
        words.length ? el("span", { class: "diag-flagwords" }, words.join(" · ")) : null)));
  }

  // flags: confusable pairs, unidentifiable candidates, with the test that would settle them
  const fl = document.getElementById("diag-flags");
  fl.replaceChildren();
  for (const c of doc.confusable) {
    fl.append(el("li", {}, `Confusable: ${c.effects.join(" and ")}: ${c.reason}. To separate: ${c.to_separate}.`));
  }
  for (const u of doc.unidentifiable) {
    fl.append(el("li", {}, `Not identifiable: ${u.effect}: ${u.reason}. Test that would identify it: ${u.test_to_identify}.`));
  }

  // noise you can see: is the residual at the sensor's own noise? (Allan deviation statement)
  const nz = document.getElementById("diag-noise");
  nz.replaceChildren(...Object.values(doc.noise || {}).map((v) => el("span", {}, "Noise: " + v.statement)));

  // fitted parameters of the added effects
  const pr = document.getElementById("diag-params");
  pr.replaceChildren();
  for (const [serial, p] of Object.entries(doc.model.parameters || {})) {
    for (const [eff, vals] of Object.entries(p.effects || {})) {
      for (const [pname, entry] of Object.entries(vals)) {
        const txt = ("value" in entry)
          ? diagValue(entry)
          : Object.entries(entry).map(([ax, e]) => `${ax} ${diagValue(e)}`).join("   ");
        pr.append(el("li", {}, `${serial} ${eff}.${pname}: ${txt}`));
      }
    }
  }
  DIAG.plots = doc.plots || [];
  DIAG.leftover = doc.leftover || null;
}

function diagValue(e) {
  if (e.value === null || e.value === undefined) return "–";
  return e.sigma === null || e.sigma === undefined ? `${Number(e.value).toPrecision(5)}`
    : `${Number(e.value).toPrecision(5)} ± ${Number(e.sigma).toPrecision(2)} (1σ)`;
}

function diagP(p) {
  if (p === null || p === undefined || Number.isNaN(Number(p))) return "–";
  return Number(p) === 0 ? "0" : Number(p).toPrecision(2);
}

const diagMg = (v) => Number(v).toPrecision(3);
const diagList = (s) => String(s).split(",").filter(Boolean).join(" and ");

// Which gates of the admission gate a comparison (a ranking row, or its given_admitted record) fails,
// in words. `before` is the held-out RMS of the model it is compared with (mg) when known.
function diagGateFailures(c, before) {
  const out = [];
  const bicOk = c.delta_bic !== null && c.delta_bic !== undefined && Number(c.delta_bic) < DIAG_GATE.bic;
  const pOk = c.score_p !== null && c.score_p !== undefined && Number(c.score_p) < DIAG_GATE.p;
  if (!bicOk && c.delta_bic !== null && c.delta_bic !== undefined) {
    out.push(`not enough evidence in sample (delta BIC ${fmt(c.delta_bic, 1)} >= ${DIAG_GATE.bic})`);
  }
  if (!pOk && c.score_p !== null && c.score_p !== undefined) {
    out.push(`likelihood-ratio p = ${diagP(c.score_p)} >= ${DIAG_GATE.p} under the correlated-noise model`);
  }
  const gain = c.heldout_gain_rel;
  if (gain !== null && gain !== undefined && Number(gain) < DIAG_GATE.gain) {
    const after = c.heldout_rms_mg;
    let from = before;
    if ((from === null || from === undefined) && after !== null && after !== undefined && Number(gain) < 1) {
      from = Number(after) / (1 - Number(gain));
    }
    const ab = from !== null && from !== undefined && after !== null && after !== undefined
      ? ` (held-out error ${diagMg(from)} -> ${diagMg(after)} mg)` : "";
    out.push(`${bicOk && pOk ? "fits in sample but " : ""}does not lower the held-out error by ` +
      `${Math.round(DIAG_GATE.gain * 100)} %${ab}`);
  }
  return out;
}

// Why a ranking row is (not) admitted, in words: the backend's row.why when it has one, else derived
// from the row's numbers (against the baseline), its flags and, for a row gated on top of the effects
// already admitted, the numbers of that comparison (row.given_admitted).
function diagReason(r, doc) {
  if (typeof r.why === "string" && r.why.trim()) return r.why;
  const flags = r.flags || [];
  const flagged = (prefix) => flags.filter((f) => f.startsWith(prefix)).map((f) => f.slice(prefix.length));
  if (r.admitted) {
    const parts = ["admitted"];
    for (const x of flagged("masked:admitted_with:")) parts.push(`together with ${diagList(x)} (each hides the other held out)`);
    for (const x of flagged("masked:evidence_given:")) parts.push(`its evidence shows once ${diagList(x)} is in the model`);
    for (const x of flagged("confusable_with:")) parts.push(`confusable with ${diagList(x)} on this data (see below)`);
    return parts.join(": ");
  }
  const parts = [];
  const standsFor = flagged("stands_for_it:");
  const explained = flagged("explained_by:");
  for (const x of standsFor) {
    parts.push(`${diagList(x)}, admitted, stands for it (the two are confusable on this data; only one goes in)`);
  }
  for (const x of explained) {
    const on = r.given_admitted ? diagGateFailures(r.given_admitted, null) : [];
    parts.push(`explained by ${diagList(x)}, already admitted` + (on.length ? `: on top of it ${on.join("; ")}` : ""));
  }
  if (!standsFor.length && !explained.length) {
    const alone = diagGateFailures(r, doc && doc.baseline ? doc.baseline.heldout_rms_mg : null);
    parts.push(...alone);
    if (!alone.length && r.given_admitted) {
      const on = diagGateFailures(r.given_admitted, null);
      if (on.length) parts.push(`on top of the admitted effects ${on.join("; ")}`);
    }
  }
  for (const x of flagged("confusable_with:")) parts.push(`confusable with ${diagList(x)} on this data (see below)`);
  for (const f of flags) {
    if (!/^(no_evidence|explained_by:|stands_for_it:|confusable_with:|masked:)/.test(f)) parts.push(diagFlagWords(f));
  }
  if (r.same_as) parts.push(`same term as ${(r.aliases || []).join(", ")} on this data`);
  if (!parts.length) parts.push("passes the gate alone but the forward staircase did not admit it");
  return "not admitted: " + parts.join("; ");
}

// ---- plots: a queue, DIAG_PLOT_CONCURRENCY in flight, each with its state in words ----------------
// In the server's order (doc.plots): the order it renders them in ahead of these requests.
function diagPlotNames() {
  return [...new Set(DIAG.plots.map((p) => String(p).replace(/^.*\//, "").replace(/\.png(\?.*)?$/, "")))];
}

function diagPlotState(item, state, text) {
  item.fig.dataset.state = state;
  item.state.textContent = text || "";
  item.state.className = "diag-plot-state" + (state === "failed" ? " error" : "");
}

function diagQueueLabels() {
  DIAG.queue.forEach((item, i) => diagPlotState(item, "queued", i ? `queued (${i} ahead)` : "queued (next)"));
}

function diagLoadPlots(gen) {
  for (const u of DIAG.urls) URL.revokeObjectURL(u);
  DIAG.urls = [];
  const box = document.getElementById("diag-plots");
  box.replaceChildren();
  DIAG.queue = [];
  const carrying = new Set((DIAG.leftover && DIAG.leftover.above_floor && DIAG.leftover.carrying) || []);
  for (const name of diagPlotNames()) {
    const fig = el("figure", { class: "diag-plot" + (carrying.has(name) ? " carrying" : ""), "data-plot": name },
      el("figcaption", {}, diagPlotTitle(name) + (carrying.has(name) ? " · shows what the model misses" : "")));
    const item = { name, fig, state: el("div", { class: "diag-plot-state", role: "status" }) };
    fig.append(item.state);
    box.append(fig);
    DIAG.queue.push(item);
  }
  diagQueueLabels();
  diagPump(gen);
  const dl = document.getElementById("diag-model");
  dl.onclick = async () => {
    const g = DIAG.gen;
    try {
      const resp = await diagRequest(diagUrl("/model.json"), g, {
        onWait: (left) => diagStatus(`the station is busy: the model download waits ${left} s`, "working") });
      const url = URL.createObjectURL(await resp.blob());
      diagStatus("");
      const a = el("a", { href: url, download: `${DIAG.serial}-run${DIAG.runId}.model.json` });
      document.body.append(a); a.click(); a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 60_000);
    } catch (e) {
      if (!(e instanceof DiagCancelled)) diagStatus("Model download failed: " + e.message, "error");
    }
  };
}

function diagPump(gen) {
  while (gen === DIAG.gen && DIAG.workers < DIAG_PLOT_CONCURRENCY && DIAG.queue.length) {
    DIAG.workers += 1;
    diagWorker(gen).finally(() => {
      if (gen !== DIAG.gen) return;
      DIAG.workers -= 1;
      diagPump(gen);
    });
  }
}

async function diagWorker(gen) {
  while (gen === DIAG.gen && DIAG.queue.length) {
    const item = DIAG.queue.shift();
    diagQueueLabels();
    await diagLoadPlot(item, gen);
  }
}

async function diagLoadPlot(item, gen) {
  const t0 = performance.now();
  const rendering = (attempt) => diagPlotState(item, "loading",
    "rendering…" + (attempt > 1 ? ` (try ${attempt} of ${DIAG_MAX_TRIES})` : ""));
  try {
    const resp = await diagRequest(diagUrl(`/${item.name}.png`), gen, {
      onTry: rendering,
      onWait: (left, attempt) => diagPlotState(item, "waiting",
        `station busy, retrying in ${left} s (try ${attempt + 1} of ${DIAG_MAX_TRIES})`),
    });
    const blob = await resp.blob();
    diagCheck(gen);
    const url = URL.createObjectURL(blob);
    DIAG.urls.push(url);
    const img = el("img", { src: url, alt: diagPlotTitle(item.name), width: "440", onclick: () => showPlot(url) });
    try {
      await img.decode();
    } catch (_) {
      throw new Error("the plot arrived but is not a readable image");
    }
    diagCheck(gen);
    item.fig.querySelector("img")?.remove();
    item.fig.prepend(img);
    diagPlotState(item, "loaded", "");
    item.fig.dataset.ms = String(Math.round(performance.now() - t0));
  } catch (e) {
    if (e instanceof DiagCancelled || gen !== DIAG.gen) return;
    diagPlotState(item, "failed", e.message);
    item.state.append(" ", el("button", { type: "button", class: "btn small diag-retry", onclick: () => {
      if (gen !== DIAG.gen) return;
      DIAG.queue.push(item);
      diagQueueLabels();
      diagPump(gen);
    } }, "Retry"));
  }
}

window.diagnoseRun = diagnoseRun;

document.addEventListener("DOMContentLoaded", () => {
  const close = document.getElementById("diag-close");
  if (close) close.addEventListener("click", () => {
    diagStop();
    DIAG.busy = false;
    document.getElementById("diag-panel").classList.add("hidden");
  });
});
