"""The operator page's message catalogs (web/static/i18n/*.json, issue 41), without a browser.

Fails on an untranslated key before any kiosk shows it: every key the page's scripts and HTML use
exists in every catalog (a missing one shows as its key on the page); no catalog has keys the others
lack; the {placeholders} of a message are the same in every language (a German message that drops
{serial} would hide the serial); a German or Chinese message is not the English one left as it is
(unless it is made only of symbols every language shares); every cause station/records/causes.py
can name, and every code `reason_code` gives, has its sentence in every catalog (the page says a
stored English reason by its code); the MES route check's refusal among them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from station.records.causes import CAUSES, CODES, code_of, reason_code

STATIC = Path(__file__).resolve().parents[1] / "web" / "static"
I18N = STATIC / "i18n"
LANGS = ("en", "de", "zh")
# Symbols and names the same in every language: a message made only of these, numbers, punctuation
# and placeholders may be the English one (e.g. "SFEM{at}: RMSE {before} → {after} mg").
SAME_IN_EVERY_LANGUAGE = {"TDB", "TDSF", "SFEM", "RMSE", "CRC", "CSV", "PDF", "MES", "SPC", "OK", "mg", "ppm", "g", "v",
                          "x", "y", "z", "E"}
PLACEHOLDER = re.compile(r"\{(\w+)\}")


def catalog(lang: str) -> dict[str, str]:
    return json.loads((I18N / f"{lang}.json").read_text(encoding="utf-8"))


CATALOGS = {lang: catalog(lang) for lang in LANGS}


def keys_used() -> dict[str, set[str]]:
    """Every literal catalog key in the page: t("key", ...), data-i18n*="key" in the HTML, and the
    keys a script picks between (`t(cond ? "a.b" : "a.c")`): any string literal "ns.key" whose
    namespace is a catalog namespace. Keys built at run time ("verdict." + v) are checked by
    their own tests below."""
    namespaces = {k.split(".")[0] for k in CATALOGS["en"]}
    used: dict[str, set[str]] = {}
    for path in sorted(STATIC.glob("*.js")) + sorted(STATIC.glob("*.html")):
        text = path.read_text(encoding="utf-8")
        found = set(re.findall(r"""\bt\(\s*["'`]([A-Za-z0-9_.-]+)["'`]""", text))
        found |= set(re.findall(r'data-i18n(?:-[a-z-]+)?="([^"]+)"', text))
        for lit in re.findall(r'"([a-z_]+\.[A-Za-z0-9_.-]+)"', text):
            if lit.split(".")[0] in namespaces and not lit.endswith((".", "_", "-")) and not lit.endswith(".js"):
                found.add(lit)
        for key in found:
            if not key.endswith((".", "_", "-")):  # a prefix a key is built from at run time ("verdict." + v)
                used.setdefault(key, set()).add(path.name)
    return used


def test_the_scan_finds_the_page_keys():
    """The scan itself works: the must-have views' keys are found where they are used."""
    used = keys_used()
    assert "start.start" in used and "index.html" in used["start.start"]
    assert "prompt.done" in used and "prompt.say_why" in used
    assert "sorting.yield" in used and "outcome.some" in used
    assert len(used) > 150, len(used)


@pytest.mark.parametrize("lang", LANGS)
def test_every_key_the_page_uses_is_in_every_catalog(lang):
    missing = {k: sorted(files) for k, files in keys_used().items() if k not in CATALOGS[lang]}
    assert not missing, f"{lang}.json lacks keys the page uses: {missing}"


def test_no_catalog_has_keys_the_others_lack():
    every = set().union(*(set(c) for c in CATALOGS.values()))
    for lang, c in CATALOGS.items():
        assert not every - set(c), f"{lang}.json lacks {sorted(every - set(c))}"


def test_placeholders_match_across_languages():
    bad = []
    for key, text in CATALOGS["en"].items():
        want = sorted(PLACEHOLDER.findall(text))
        for lang in ("de", "zh"):
            got = sorted(PLACEHOLDER.findall(CATALOGS[lang][key]))
            if got != want:
                bad.append((lang, key, want, got))
    assert not bad, bad


def test_every_message_is_a_nonempty_string():
    for lang, c in CATALOGS.items():
        for key, text in c.items():
            assert isinstance(text, str) and text.strip(), (lang, key)


def _only_shared_symbols(text: str) -> bool:
    words = re.findall(r"[A-Za-z]+", PLACEHOLDER.sub("", text))
    return all(w in SAME_IN_EVERY_LANGUAGE for w in words)


@pytest.mark.parametrize("lang", ["de", "zh"])
def test_no_message_is_the_english_one_left_untranslated(lang):
    same = [k for k, text in CATALOGS["en"].items()
            if CATALOGS[lang][k] == text and not _only_shared_symbols(text) and k not in SAME_BY_DESIGN]
    assert not same, f"{lang}.json keeps English: {same}"


# The few messages whose words are the same in these languages by design: the MES role (a system's name).
SAME_BY_DESIGN = {"role.mes"}


def test_chinese_messages_are_chinese():
    """Every Chinese message with words in it has Han characters (not a German or English copy)."""
    han = re.compile(r"[\u4e00-\u9fff]")
    bad = [k for k, text in CATALOGS["zh"].items() if not han.search(text) and not _only_shared_symbols(text)
           and k not in SAME_BY_DESIGN]
    assert not bad, bad


def test_every_cause_has_a_code_with_a_sentence_in_every_catalog():
    codes = {code_of(c) for c in CAUSES}
    assert codes <= set(CODES)
    assert len(codes) == len(CAUSES), "two causes share a code"
    for lang, c in CATALOGS.items():
        missing = sorted(code for code in CODES if f"reason.{code}" not in c)
        assert not missing, f"{lang}.json lacks reason sentences: {missing}"
    for code in CODES:  # codes are slugs: stable, safe as keys and CSS/data attributes
        assert re.fullmatch(r"[a-z0-9]+(?:_[a-z0-9]+)*", code), code


def test_route_refused_by_the_mes_is_said_in_every_language():
    assert code_of("route refused (MES)") == "route_refused_mes"
    assert reason_code("MES route check: the MES refused SIM0013 at 'thermal-cal': on hold; not tested") == "route_refused_mes"
    for lang, c in CATALOGS.items():
        assert c["reason.route_refused_mes"].strip(), lang


@pytest.mark.parametrize("reason, code", [
    ("faulted: serial /dev/pts/7: link lost: serial port /dev/pts/7 closed", "link_lost"),
    ("label serial 'SIM9999' does not match the board's own serial 'SIM0003'", "label_mismatch"),
    ("z TDSF -612 ppm/C, limit -500", "limit_exceeded"),
    ("y TDSF -496 ±8 ppm/C crosses limit -500", "limit_crossed"),
    ("all limits met", "all_limits_met"),
    ("board firmware says: E42 sensor self-test", None),  # words no rule names: shown as they are
    ("", None),
])
def test_reason_code_of_the_stations_words(reason, code):
    assert reason_code(reason) == code


def test_the_page_knows_every_state_and_verdict_it_names():
    """Keys the scripts build at run time: verdicts, batch and slot states, trays and grades the
    station itself names (station/decisions/limits.py defaults, verdicts.py grades)."""
    from station.decisions.verdicts import VERDICTS

    need = [f"verdict.{v}" for v in VERDICTS] + [f"verdict_name.{v}" for v in VERDICTS]
    need += [f"batch_state.{s}" for s in ("created", "running", "paused", "finished", "aborted", "failed", "interrupted")]
    need += [f"slot_state.{s}" for s in ("identified", "disconnected", "busy", "idle", "connecting", "running", "done",
                                         "faulted", "interrupted")]
    need += [f"tray.{t}" for t in ("reject", "hold_review_retest", "retest", "reject_no_grade", "grade")]
    need += [f"grade.{g}" for g in ("retest", "reject", "hold", "none")]
    for lang, c in CATALOGS.items():
        assert not [k for k in need if k not in c], lang
