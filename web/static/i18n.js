// The page's words in the operator's language (issue 41): message catalogs in /static/i18n/<lang>.json
// (flat {"key": "text with {name} placeholders"}), loaded once; t(key, params) looks a key up. A
// key the catalog lacks shows as the key itself and is logged, never silently as English: a missing
// translation must be seen, on the page and in tests/test_i18n_catalogs.py. The language is a kiosk's
// setting (localStorage "station.lang"), from the browser's language when none is stored; a switch
// reloads the page (every view is built again in the new words; the batch, the token and the
// operator's name survive a reload). Numbers and dates through Intl in that language.
// Loaded before the other scripts; app.js boots once I18N.ready resolves.
"use strict";

const I18N = (() => {
  // the languages offered, each named in its own words (the switch shows these, in every language)
  const LANGS = { en: "English", de: "Deutsch", zh: "中文" };
  const HTML_LANG = { en: "en", de: "de", zh: "zh-Hans" };  // <html lang>: zh-Hans picks a Simplified Chinese font
  const STORE = "station.lang";
  let catalog = {};
  const missing = new Set();

  function fromBrowser() {
    const wanted = [...(navigator.languages || []), navigator.language || ""];
    for (const tag of wanted) {
      const primary = String(tag || "").toLowerCase().split("-")[0];
      if (primary in LANGS) return primary;
    }
    return "en";
  }

  function chosen() {
    const stored = localStorage.getItem(STORE);
    return stored && stored in LANGS ? stored : fromBrowser();
  }

  const lang = chosen();

  function has(key) { return Object.prototype.hasOwnProperty.call(catalog, key); }

  function t(key, params) {
    if (!has(key)) {
      if (!missing.has(key)) { missing.add(key); console.warn(`i18n: no "${key}" in the ${lang} catalog`); }
      return key;
    }
    const text = catalog[key];
    if (!params) return text;
    return text.replace(/\{(\w+)\}/g, (m, name) => (params[name] === undefined || params[name] === null ? m : String(params[name])));
  }

  // The words in the static HTML: data-i18n (text), data-i18n-placeholder, -title, -aria-label.
  function applyStatic(root = document) {
    for (const e of root.querySelectorAll("[data-i18n]")) e.textContent = t(e.dataset.i18n);
    for (const [attr, data] of [["placeholder", "i18nPlaceholder"], ["title", "i18nTitle"], ["aria-label", "i18nAriaLabel"], ["alt", "i18nAlt"]]) {
      for (const e of root.querySelectorAll(`[data-${attr === "aria-label" ? "i18n-aria-label" : "i18n-" + attr}]`)) {
        e.setAttribute(attr, t(e.dataset[data]));
      }
    }
  }

  function setLang(next) {
    if (!(next in LANGS) || next === lang) return;
    localStorage.setItem(STORE, next);
    location.reload();
  }

  // The switch in the header: the languages in their own names.
  function renderSwitch() {
    const sel = document.getElementById("lang");
    if (!sel) return;
    sel.replaceChildren(...Object.entries(LANGS).map(([code, name]) => {
      const o = document.createElement("option");
      o.value = code; o.textContent = name; o.lang = HTML_LANG[code];
      if (code === lang) o.selected = true;
      return o;
    }));
    sel.addEventListener("change", () => setLang(sel.value));
  }

  // Numbers: a fixed count of decimals in the locale (German "23,5"), no grouping (serial-like
  // counts and coefficients read as one figure); English keeps toFixed, what the page always showed.
  const numberFormats = new Map();
  function num(v, digits) {
    const n = Number(v);
    if (lang === "en") return n.toFixed(digits);
    if (!numberFormats.has(digits)) {
      numberFormats.set(digits, new Intl.NumberFormat(HTML_LANG[lang], { minimumFractionDigits: digits, maximumFractionDigits: digits, useGrouping: false }));
    }
    return numberFormats.get(digits).format(n);
  }

  const dateFormat = new Intl.DateTimeFormat(HTML_LANG[lang], { dateStyle: "short", timeStyle: "medium" });
  function dateTime(iso) {
    const d = new Date(iso);
    return Number.isNaN(d.getTime()) ? String(iso) : dateFormat.format(d);
  }

  const ready = fetch(`/static/i18n/${lang}.json`, { cache: "no-cache" })
    .then((r) => { if (!r.ok) throw new Error(`${r.status} ${r.statusText}`); return r.json(); })
    .then((c) => { catalog = c; })
    .catch((e) => { console.error(`i18n: the ${lang} catalog did not load: ${e.message}`); })
    .then(() => new Promise((resolve) => {
      const go = () => {
        document.documentElement.lang = HTML_LANG[lang];
        applyStatic();
        renderSwitch();
        resolve(lang);
      };
      if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", go); else go();
    }));

  return { LANGS, lang, t, has, num, dateTime, applyStatic, setLang, ready, missing };
})();

const t = I18N.t;

// A reason the station wrote (English, kept so in the records) said in the operator's language:
// the sentence for its code (station/records/causes.py reason_code) and the station's own words,
// smaller, as the detail (numbers, serials, the operator's note). Unknown code: the words as they
// are, marked untranslated. English: the words alone (the sentence would say them twice).
// `short`: the words shortened for the kiosk (cards.js shortReason). Returns DOM nodes.
const SAYS_NO_MORE = new Set(["all_limits_met"]);

function reasonNodes(code, text, short) {
  const words = short === undefined ? String(text || "") : short;
  if (!words) return [];
  const detail = (extra) => {
    const e = document.createElement("span");
    e.className = "reason-detail" + (extra || "");
    e.lang = "en";  // the station's words, in English by design
    e.textContent = words;
    return e;
  };
  const key = code ? "reason." + code : null;
  if (I18N.lang === "en") return [words];
  if (key && I18N.has(key)) {
    const s = document.createElement("span");
    s.className = "reason-text";
    s.dataset.code = code;
    s.textContent = t(key);
    if (SAYS_NO_MORE.has(code)) return [s];  // "all limits met": the words add nothing to the sentence
    return [s, " ", detail("")];
  }
  const mark = document.createElement("span");
  mark.className = "untranslated";
  mark.title = t("reason.untranslated");
  mark.textContent = "EN";
  return [mark, " ", detail(" raw")];
}
