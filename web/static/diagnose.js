// Model diagnostics panel (issue 6, design 7): for a stored run, rank the effects missing from the
// baseline thermal model; click an effect to add it and watch the error staircase fall.
// Uses app.js's globals (api, blobUrl, el, fmt, showPlot); loaded after it.
"use strict";

const DIAG = { runId: null, serial: "", add: [], busy: false, plots: [] };
const DIAG_PLOTS_SHOWN = ["staircase", "ranking", "residual_vs_temperature", "residual_vs_time",
  "measured_vs_model", "residual_vs_rate", "residual_vs_acceleration"];

function diagQuery() {
  return DIAG.add.map((e) => "add=" + encodeURIComponent(e)).join("&");
}

function diagUrl(suffix) {
  const q = diagQuery();
  return `/api/runs/${DIAG.runId}/diagnosis${suffix || ""}${q ? "?" + q : ""}`;
}

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

function diagStatus(text, isError) {
  const s = document.getElementById("diag-status");
  s.textContent = text || "";
  s.className = isError ? "error" : "muted";
}

async function diagRefresh() {
  DIAG.busy = true;
  const title = document.getElementById("diag-title");
  title.textContent = `Model diagnostics · ${DIAG.serial} run ${DIAG.runId}` +
    (DIAG.add.length ? ` · baseline + ${DIAG.add.join(" + ")}` : " · baseline");
  diagStatus("fitting the models (held-out validation of every candidate: this can take a minute)…");
  try {
    const doc = await api(diagUrl());
    diagRender(doc);
    diagStatus("");
    diagLoadPlots();
  } catch (e) {
    diagStatus(e.message, true);
  } finally {
    DIAG.busy = false;
  }
}

function diagRender(doc) {
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

  // ranking
  const rk = document.getElementById("diag-ranking");
  rk.replaceChildren(el("caption", {}, "Candidates, best held-out first"),
    el("tr", {}, el("th", {}, "effect"), el("th", {}, "held-out mg"), el("th", {}, "ΔBIC"),
      el("th", {}, "score p"), el("th", {}, "admitted"), el("th", {}, "flags")));
  for (const r of doc.ranking) {
    rk.append(el("tr", { class: r.admitted ? "admitted" : "" },
      el("td", {}, el("button", { type: "button", class: "link", onclick: () => diagToggle(r.effect) }, r.effect)),
      el("td", {}, fmt(r.heldout_rms_mg, 4)), el("td", {}, fmt(r.delta_bic, 1)),
      el("td", {}, r.score_p === null ? "–" : Number(r.score_p).toPrecision(2)),
      el("td", {}, r.admitted ? "yes" : "no"), el("td", {}, r.flags.join(" "))));
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
}

function diagValue(e) {
  if (e.value === null || e.value === undefined) return "–";
  return e.sigma === null || e.sigma === undefined ? `${Number(e.value).toPrecision(5)}`
    : `${Number(e.value).toPrecision(5)} ± ${Number(e.sigma).toPrecision(2)}`;
}

function diagLoadPlots() {
  const box = document.getElementById("diag-plots");
  box.replaceChildren();
  for (const name of DIAG_PLOTS_SHOWN.filter((p) => DIAG.plots.includes(p))) {
    const fig = el("figure", { class: "diag-plot" }, el("figcaption", {}, name.replaceAll("_", " ")));
    box.append(fig);
    blobUrl(diagUrl(`/${name}.png`)).then((url) => fig.prepend(
      el("img", { src: url, alt: name, width: "440", onclick: () => showPlot(url) }))).catch((e) => fig.append(el("span", { class: "error" }, e.message)));
  }
  const dl = document.getElementById("diag-model");
  dl.onclick = async () => {
    const url = await blobUrl(diagUrl("/model.json"));
    const a = el("a", { href: url, download: `${DIAG.serial}-run${DIAG.runId}.model.json` });
    document.body.append(a); a.click(); a.remove();
  };
}

window.diagnoseRun = diagnoseRun;

document.addEventListener("DOMContentLoaded", () => {
  const close = document.getElementById("diag-close");
  if (close) close.addEventListener("click", () => document.getElementById("diag-panel").classList.add("hidden"));
});
