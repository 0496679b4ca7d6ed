"""The operator page in German and Simplified Chinese (issue 41), in Debian's headless Chromium at the
800x480 kiosk.

For each language: the start form, the operator's "turn the plate" prompt of a batch run without the
motorized fixture (a live simulated station), and the end view of ended batches (real database
rows, tests/end_view_support.py: verdicts and fault reasons in the station's own English words).
Each view is screenshotted (a pytest tmp dir, and /tmp/i18n_shots/ for the reviewer) and its visible
text (body.innerText) must hold no English catalog value (web/static/i18n/en.json): a string the page
forgot to translate fails here. Left out of that text on purpose, and checked for it: the station's
own words shown as the detail of a translated reason (elements with lang="en", class reason-detail:
numbers, serials, the operator's note, stored in English by design) and the data the site and the
boards name (serials, slot and profile names from the config).

Also: the language comes from the browser's language when none is stored (Playwright's locale), the
switch in the header changes it and the kiosk remembers it (localStorage), `<html lang>` follows;
reasons are said by their code (a refused MES route check included) with the English words beside
them; a reason no rule names is shown as it is, marked untranslated; numbers in the locale (German
decimal comma); Chinese glyphs have a font (fonts-noto-cjk, scripts/test.sh).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from fastapi import HTTPException

import end_view_support
from end_view_support import Slot, mixed_slots, write_ended_batch
from web_support import CHROMIUM, TOKENS, IdleStation, LiveStation, auth, serve_in_thread, wait_for

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]

I18N_DIR = Path(__file__).resolve().parents[1] / "web" / "static" / "i18n"
SHOTS = Path("/tmp/i18n_shots")
LOCALES = {"de": "de-DE", "zh": "zh-CN"}
HTML_LANG = {"de": "de", "zh": "zh-Hans"}
# Words the same in every language: the coefficients' and methods' symbols, formats, the MES (a
# system's name). A catalog fragment made only of these (and of words of 3 letters or fewer) is not
# looked for. Keep it this small.
SAME_IN_EVERY_LANGUAGE = {"TDB", "TDSF", "SFEM", "RMSE", "CRC", "CSV", "PDF", "MES", "SPC", "OK"}
TOKEN = TOKENS["operator"]


def english_fragments() -> list[str]:
    """The English catalog's values as the page could show them: split at their {placeholders},
    trimmed; the fragments of at least 4 characters with a word outside SAME_IN_EVERY_LANGUAGE."""
    en = json.loads((I18N_DIR / "en.json").read_text(encoding="utf-8"))
    out: set[str] = set()
    for value in en.values():
        for frag in re.split(r"\{\w+\}", value):
            frag = frag.strip(" \t·:;,.()→±/-\"'")
            words = [w for w in re.findall(r"[A-Za-z]+", frag) if w not in SAME_IN_EVERY_LANGUAGE]
            if len(frag) >= 4 and any(len(w) > 3 for w in words):
                out.add(frag)
    return sorted(out, key=len, reverse=True)


ENGLISH = english_fragments()

# The visible text without the station's own English words (lang="en") and the site's (class
# site-words: a profile the site's config describes, in the site's words), and the station's English
# words with what stands before them (a translated sentence, or the "untranslated" mark).
VISIBLE_TEXT_JS = """() => {
  const kept = [...document.querySelectorAll('body [lang="en"]:not(#lang option)')];  // the switch names English in English
  const details = kept.map((e) => ({cls: e.className, text: e.textContent,
    before: (e.previousElementSibling || {}).className || '', beforeText: (e.previousElementSibling || {}).textContent || ''}));
  const was = kept.map((e) => e.style.display);
  kept.forEach((e) => { e.style.display = 'none'; });
  const text = document.body.innerText;
  kept.forEach((e, i) => { e.style.display = was[i]; });
  // a select lists its options in innerText whatever their display: the site's words come out by text
  const site = [...document.querySelectorAll('body .site-words')].map((e) => e.textContent);
  return {text: site.reduce((t, s) => t.replace(s, ''), text), details, lang: document.documentElement.lang, stored: localStorage.getItem('station.lang'),
          switchValue: document.querySelector('#lang').value, title: document.title};
}"""


def english_left(text: str) -> list[str]:
    """The English catalog fragments found in `text` as words (not inside a longer word)."""
    return [f for f in ENGLISH if re.search(r"(?<![A-Za-z])" + re.escape(f) + r"(?![A-Za-z])", text)]


def check_view(page, lang: str, view: str, tmp_path: Path) -> dict:
    """Screenshot the view (tmp dir and /tmp/i18n_shots) and fail on English left in its text."""
    page.evaluate("() => window.scrollTo(0, 0)")
    time.sleep(0.4)
    SHOTS.mkdir(parents=True, exist_ok=True)
    name = f"{view}-{lang}-800x480.png"
    page.screenshot(path=str(tmp_path / name))
    shutil.copyfile(tmp_path / name, SHOTS / name)
    page.screenshot(path=str(SHOTS / f"{view}-{lang}-800x480-full.png"), full_page=True)
    m = page.evaluate(VISIBLE_TEXT_JS)
    assert m["lang"] == HTML_LANG[lang], (view, m["lang"])
    left = english_left(m["text"])
    assert not left, f"{lang} {view}: English left on the page: {left}\n--- page text ---\n{m['text']}"
    # the English kept on purpose is only ever the detail of a reason: after its translated
    # sentence, or after the mark that says no translation exists
    for d in m["details"]:
        assert "reason-detail" in d["cls"], (lang, view, d)
        assert d["before"] in ("reason-text", "untranslated") or "prompt-why" in d["cls"], (lang, view, d)
    return m


def new_page(browser, lang: str, batch: int | None = None):
    """A kiosk whose browser speaks `lang` (navigator.language), signed in, at 800x480 (showing
    `batch`, an ended one, when given)."""
    page = browser.new_page(viewport={"width": 800, "height": 480}, locale=LOCALES[lang])
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    warnings: list[str] = []
    page.on("console", lambda msg: warnings.append(msg.text) if "i18n:" in msg.text else None)
    page.set_default_timeout(30_000)
    page.add_init_script(f"localStorage.setItem('station.token', {TOKEN!r});"
                         + (f"localStorage.setItem('station.batch', '{batch}');" if batch else ""))
    return page, errors, warnings


@pytest.fixture(scope="module")
def browser():
    pytest.importorskip("playwright.sync_api")
    from playwright import sync_api

    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                               args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        try:
            yield b
        finally:
            b.close()


def test_chinese_glyphs_have_a_font():
    """Without a CJK font the Chinese page is boxes: scripts/test.sh installs fonts-noto-cjk."""
    if shutil.which("fc-list") is None:
        pytest.fail("fontconfig missing: install fonts-noto-cjk (scripts/test.sh)")
    out = subprocess.run(["fc-list", ":lang=zh"], capture_output=True, text=True, check=False).stdout
    assert out.strip(), "no font for Chinese: apt-get install fonts-noto-cjk (scripts/test.sh does)"


@pytest.mark.parametrize("lang", ["de", "zh"])
def test_start_form_and_prompt_in_the_operators_language(tmp_path, browser, lang):
    with LiveStation(tmp_path, n_serial=3, n_can=0, speed=250.0, fixture=False, operator_hands=True) as live:
        page, errors, warnings = new_page(browser, lang)
        try:
            page.goto(live.url + "/")
            page.wait_for_selector("#slot-picks input[value='s3']")
            page.select_option("#profile", "fast-thermal")
            page.wait_for_function("() => document.querySelector('#profile-desc').textContent !== ''")
            m = check_view(page, lang, "start-form", tmp_path)
            # the language from the browser's (nothing stored), the switch shows it
            assert m["stored"] is None and m["switchValue"] == lang, m
            assert m["title"] == json.loads((I18N_DIR / f"{lang}.json").read_text(encoding="utf-8"))["page.title"]
            start_word = json.loads((I18N_DIR / f"{lang}.json").read_text(encoding="utf-8"))["start.start"]
            assert page.inner_text("#start") == start_word  # "Charge starten", "开始批次"

            # Start without a name: the message in the language; then a batch from the page
            page.click("#start")
            assert "Operator" not in page.inner_text("#message") and page.inner_text("#message")
            page.fill("#operator", "Ana")
            page.click("#start")
            page.wait_for_selector("#prompt-banner:not(.hidden)")
            page.wait_for_function("() => document.querySelector('#prompt-words').textContent !== ''")
            batch_id = int(page.inner_text("#batch-id"))
            m = check_view(page, lang, "prompt", tmp_path)
            cat = json.loads((I18N_DIR / f"{lang}.json").read_text(encoding="utf-8"))
            assert page.inner_text("#prompt-text") == cat["prompt.turn_plate"].format(position="P"), page.inner_text("#prompt-text")
            assert page.inner_text("#prompt-confirm") == cat["prompt.done"]
            assert page.inner_text("#prompt-words") == "P: " + " · ".join(cat["orient.axis_up"].format(axis=a) for a in "xyz")
            httpx.post(f"{live.url}/api/batches/{batch_id}/abort", headers=auth("operator"), timeout=10)
            wait_for(lambda: httpx.get(f"{live.url}/api/batches/{batch_id}", headers=auth("operator"),
                                       timeout=10).json()["state"] != "running", 30, what="the abort")
            assert errors == [], errors
            assert warnings == [], warnings  # no key missing from the catalog
        finally:
            page.close()


class StoredOnly(IdleStation):
    """A daemon that holds no batch: the page gets each ended batch from the database."""

    def batch_status(self, batch_id):
        raise HTTPException(status_code=404, detail=f"batch {batch_id} not found")


ROUTE_REFUSED = ("MES route check: the MES refused {serial} at 'thermal-cal': part on quality hold (NCR 4411); "
                 "not tested")


def test_end_view_in_german_and_chinese_reasons_by_code(tmp_path, browser, monkeypatch):
    from db import Database
    from web.app import create_app
    from web.auth import TokenStore
    from web.db_repo import DbRepository

    db = Database(f"sqlite:///{tmp_path / 'i18n.db'}", station="line-3")
    db.upgrade()
    # two faults beside the usual: a refused MES route check (its code has a sentence in every
    # catalog) and words no rule names (a board's own message: shown as they are, marked)
    monkeypatch.setitem(end_view_support.OUTCOMES, "route refused", (None, "faulted", ROUTE_REFUSED.format(serial="SIM0013")))
    monkeypatch.setitem(end_view_support.OUTCOMES, "unnamed", (None, "faulted", "board firmware says: E42 sensor self-test"))
    slots = mixed_slots() + [Slot("s13", "route refused"), Slot("s14", "unnamed")]
    mixed = write_ended_batch(db, slots)
    app = create_app(StoredOnly(db), repo=DbRepository(db), outbox=False, tokens=TokenStore([(TOKEN, "operator", "kiosk")]))
    url, stop = serve_in_thread(app)
    try:
        for lang in ("de", "zh"):
            page, errors, warnings = new_page(browser, lang, mixed["batch"])
            try:
                page.goto(url + "/")
                page.wait_for_function(f"() => document.querySelectorAll('#trays .tray-slot').length === {len(slots)}"
                                       " && document.querySelector('#batch-outcome').textContent !== ''")
                time.sleep(0.9)  # the bar's transition
                m = check_view(page, lang, "end-view", tmp_path)
                cat = json.loads((I18N_DIR / f"{lang}.json").read_text(encoding="utf-8"))
                n_pass = sum(e["verdict"] == "pass" for e in mixed["slots"].values())
                assert page.text_content("#batch-outcome") == cat["outcome.some"].format(**{"pass": n_pass, "n": len(slots)})
                why = page.evaluate("""() => Object.fromEntries([...document.querySelectorAll('#trays .tray-slot')].map((s) => {
                    const w = s.querySelector('.tray-why'); if (!w) return [s.dataset.slot, null];
                    const r = w.querySelector('.reason-text'), d = w.querySelector('.reason-detail');
                    return [s.dataset.slot, {code: r ? r.dataset.code : null, sentence: r ? r.textContent : null,
                      detail: d ? d.textContent : null, marked: !!w.querySelector('.untranslated')}]; }))""")
                assert why["s03"]["code"] == "label_mismatch" and why["s03"]["sentence"] == cat["reason.label_mismatch"]
                assert why["s03"]["detail"] == "label SIM9999 ≠ board SIM0003"  # the numbers, as the station wrote them
                assert why["s08"]["code"] == "link_lost" and why["s08"]["sentence"] == cat["reason.link_lost"]
                assert why["s13"]["code"] == "route_refused_mes" and why["s13"]["sentence"] == cat["reason.route_refused_mes"]
                assert "part on quality hold" in why["s13"]["detail"]  # the MES's own words, kept
                assert why["s06"]["code"] == "limit_exceeded" and "-612" in why["s06"]["detail"]
                assert why["s14"]["code"] is None and why["s14"]["marked"], why["s14"]
                assert why["s14"]["detail"] == "board firmware says: E42 sensor self-test"
                # the station's tray names in the language, the attribute keeps the station's
                trays = page.evaluate("() => [...document.querySelectorAll('#trays .tray-row')].map((r) => "
                                      "[r.dataset.tray, r.querySelector('.tray-name').textContent])")
                assert ["reject", cat["tray.reject"]] in trays and ["grade A", cat["tray.grade"].format(grade="A")] in trays
                # numbers in the locale: German decimal comma in the result tables
                tdb = page.inner_text('.slot-card[data-slot="s01"] td.tdb')
                assert tdb == {"de": "0,200", "zh": "0.200"}[lang], tdb
                assert errors == [], errors
                assert warnings == [], warnings
            finally:
                page.close()

        # the switch: German chosen on a Chinese-speaking kiosk, remembered across a reload
        page, errors, _ = new_page(browser, "zh")
        try:
            page.goto(url + "/")
            page.wait_for_function("() => document.documentElement.lang === 'zh-Hans'")
            with page.expect_navigation():
                page.select_option("#lang", "de")
            page.wait_for_function("() => document.documentElement.lang === 'de'")
            assert page.evaluate("() => localStorage.getItem('station.lang')") == "de"
            page.reload()
            page.wait_for_function("() => document.documentElement.lang === 'de'")
            assert page.inner_text("#tab-history") == "Verlauf"
            assert errors == [], errors
        finally:
            page.close()
    finally:
        stop()
        db.dispose()
