"""The Records view's SPC, Pareto and filters in headless Chromium (issue 24), at 1280x800 and
800x480, on a line's month (tests/records_support.py spc_line_lots: two products, two limits
versions of one, three work orders, two stations). What the page shows is checked against what
was written (run ids, values, limits), not against the page's own API answer; the CSVs it
downloads against the tables it shows. Screenshots: artifacts/records-spc-1280.png,
records-spc-filtered-1280.png, records-spc-800.png, records-pareto-800.png."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import pytest

from db import Database
from records_support import spc_line_lots, write_spc_line
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import CHROMIUM, IdleStation, chromium_page, serve_in_thread

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"
ADMIN = "admin-token-records-spc-01"
LABELS = {0: "ACC-100 rev A · LIS3DSH v1", 1: "ACC-100 rev A · LIS3DSH v2", 2: "ACC-200 rev B · ADXL355 v1",
          3: "unspecified product · LIS3DSH v1"}

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    path = tmp_path_factory.mktemp("spc-page") / "r.db"
    db = Database(f"sqlite:///{path}", station="line-2")
    db.upgrade()
    db9 = Database(f"sqlite:///{path}", station="line-9")
    written = write_spc_line(db, db9)
    app = create_app(IdleStation(db), repo=DbRepository(db), outbox=False, tokens=TokenStore([(ADMIN, "admin", "lead")]))
    url, stop = serve_in_thread(app)
    yield url, written
    stop()
    db.dispose()
    db9.dispose()


def _open_records(page, url):
    page.goto(url + "/")
    page.fill("#token", ADMIN)
    page.click("#save-token")
    page.wait_for_selector("#whoami >> text=lead")  # signed in (the header's own wording is app.js's)
    page.click("#tab-records")
    page.wait_for_selector("#spc-charts svg.wide g.spc-pt")
    page.wait_for_selector("#pareto-table tr[data-table]")


def _show_group(page, label):
    key = page.evaluate("(l) => [...document.querySelectorAll('#spc-group option')].find((o) => o.textContent"
                        ".startsWith(l + ' (')).value", label)
    page.select_option("#spc-group", key)
    page.wait_for_selector(f"[data-fig=group] >> text='{label}'")


def _table(page, sel):
    return page.evaluate("(s) => [...document.querySelectorAll(s + ' tr')].map((tr) => [...tr.children]"
                         ".map((c) => c.textContent))", sel)


def _download(page, link, tmp):
    with page.expect_download() as dl:
        page.click(link)
    dl.value.save_as(str(tmp))
    return list(csv.reader(io.StringIO(tmp.read_text())))


def _same_rows(shown, rows):
    """The CSV's cells are the table's: text equal, numbers equal as numbers (the page writes JS's
    shortest form, the CSV Python's repr: both give back the same float)."""
    assert len(shown) == len(rows) and shown[0] == rows[0], (shown[:1], rows[:1])
    for a, b in zip(shown[1:], rows[1:]):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            try:
                assert float(x) == float(y), (a, b)
            except ValueError:
                assert x == y, (a, b)


def _wait_until(page, js, timeout_s=15.0):
    """Poll `js` (an expression) with page.evaluate: the page's CSP (script-src 'self', no eval)
    refuses playwright's wait_for_function."""
    t0 = time.monotonic()
    while not page.evaluate(js):
        assert time.monotonic() - t0 < timeout_s, f"timed out waiting for {js}"
        time.sleep(0.05)


def _no_sideways_scroll(page):
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth"), \
        page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")


def _ids(written, lot):
    return [str(w["run"]) for w in written if w["lot"] == lot and w["tdb"] is not None]


def test_spc_groups_own_limits_rules_cpk_pareto_filters_and_csv_at_1280x800(line, tmp_path):
    url, written = line
    with chromium_page(1280, 800) as (page, errors):
        _open_records(page, url)
        _no_sideways_scroll(page)
        # the newest group first: ACC-200 (28 parts, Cpk about 0.7): highlighted red, in words
        assert page.text_content("[data-fig=group]") == LABELS[2]
        cpk = page.locator("[data-fig=cpk]")
        assert "cpk-low" in cpk.get_attribute("class") and "red" in cpk.get_attribute("class")
        assert cpk.text_content().endswith("below 1.33") and "95 % CI" in cpk.text_content()
        # four groups, never mixed: each one's points are exactly its own runs
        opts = page.evaluate("[...document.querySelectorAll('#spc-group option')].map((o) => o.textContent)")
        assert sorted(o.rsplit(" (", 1)[0] for o in opts) == sorted(LABELS.values())
        for lot, label in LABELS.items():
            _show_group(page, label)
            assert page.evaluate("[...document.querySelectorAll('#spc-points tr[data-run]')].map((r) => r.dataset.run)") \
                == _ids(written, lot), label
            assert page.locator("#spc-charts svg.wide g.spc-pt").count() == len(_ids(written, lot))
        # v2 (TDB ±1.0): its two 1.1 are out of ITS spec (ringed); n=12: no Cpk, and the page says why
        _show_group(page, LABELS[1])
        assert page.locator("svg.wide g.spc-pt.oos").count() == 2
        assert page.text_content("[data-fig=cpk]") == "Cpk n=12 < 25: not computed"
        assert page.locator("svg.wide text.spc-label.spec >> text=USL 1.00").count() == 1
        # v1 (TDB ±1.5): 1.2, 1.2 (over v2's USL) are in spec by their own limits; only the 1.6 is ringed
        _show_group(page, LABELS[0])
        a = spc_line_lots()[0].tdb_x
        assert sum(v > 1.0 for v in a) == 3 and page.locator("svg.wide g.spc-pt.oos").count() == 1
        oos_run = page.get_attribute("svg.wide g.spc-pt.oos", "data-run")
        assert oos_run == str(next(w["run"] for w in written if w["lot"] == 0 and w["tdb"] and w["tdb"][0] == 1.6))
        # a named run rule on a point: the shift to 0.6 gives rule 2 (9 in a row on one side)
        ruled = page.locator("svg.wide g.spc-pt.rule").filter(has=page.locator("title", has_text="9 in a row on one side"))
        assert ruled.count() >= 1
        first = ruled.first
        run = first.get_attribute("data-run")
        assert "2" in first.get_attribute("data-rules").split(",") and "2" in first.locator("text").text_content()
        first.click()  # a tap shows serial, run and date
        serial = next(w["serial"] for w in written if str(w["run"]) == run)
        info = page.text_content("#spc-point")
        assert serial in info and f"run {run}" in info and "2026-11-18" in info and "9 in a row" in info
        assert page.text_content("svg.wide .x-date >> nth=0") == "2026-11-18"  # dates under the x axis
        page.click("#spc-points-box summary")
        page.screenshot(path=str(ARTIFACTS / "records-spc-1280.png"), full_page=True)
        # the CSV is the points table shown
        _same_rows(_table(page, "#spc-points"), _download(page, "#spc-csv", tmp_path / "spc.csv"))
        # the Pareto: bars, the cumulative line, and its CSV equal to its table
        checks = page.locator("#pareto-table tr[data-table=checks]").count()
        assert page.locator("#pareto-charts svg >> nth=0").locator("rect.pareto-bar").count() == checks == 2
        assert page.locator("#pareto-charts polyline.pareto-cum").count() == 2
        pareto_rows = _table(page, "#pareto-table")
        assert pareto_rows[1][:6] == ["checks", "1", "TDB x", "3", "0", "3"]  # the 1.6 of A and the two 1.1 of B
        # one cause per failed or error run, by name: the three TDB fails, A's two faults, its unmeasured run
        assert [(r[2], r[3], r[4]) for r in pareto_rows if r[0] == "causes"] == [
            ("limit: TDB", "3", "0"), ("link lost", "0", "1"), ("no samples", "0", "1"), ("not measured", "0", "1")]
        assert page.locator("#pareto-charts svg >> nth=1").locator("rect.pareto-bar").count() == 4
        _same_rows(pareto_rows, _download(page, "#pareto-csv", tmp_path / "pareto.csv"))
        # filters change what is shown: work order WO-2 is group v2 only, and the Pareto counts its 12 runs
        page.select_option("#f-work-order", "WO-2")
        page.wait_for_selector(f"[data-fig=group] >> text='{LABELS[1]}'")
        page.wait_for_selector("#pareto-status >> text=12 judged runs")
        assert page.locator("#spc-group option").count() == 1
        assert _table(page, "#pareto-table")[1:] == [["checks", "1", "TDB x", "2", "0", "2", "100.0", "100.0"],
                                                     ["causes", "1", "limit: TDB", "2", "0", "2", "100.0", "100.0"]]
        _same_rows(_table(page, "#pareto-table"), _download(page, "#pareto-csv", tmp_path / "pareto2.csv"))
        page.click("#f-clear")
        page.wait_for_selector("#pareto-status >> text=79 judged runs")
        page.fill("#f-from", "2026-11-20")
        page.fill("#f-to", "2026-11-20")
        _wait_until(page, "document.querySelectorAll('#spc-group option').length === 2")
        got = page.evaluate("[...document.querySelectorAll('#spc-group option')].map((o) => o.textContent.split(' (')[0])")
        assert got == [LABELS[2], LABELS[3]]
        page.select_option("#f-station", "line-9")
        _wait_until(page, "document.querySelectorAll('#spc-group option').length === 1")
        page.wait_for_selector(f"[data-fig=group] >> text='{LABELS[3]}'")
        _same_rows(_table(page, "#spc-points"), _download(page, "#spc-csv", tmp_path / "spc2.csv"))
        assert page.evaluate("[...document.querySelectorAll('#spc-points tr[data-run]')].map((r) => r.dataset.run)") \
            == _ids(written, 3)
        assert page.text_content("[data-fig=cpk]") == "Cpk n=6 < 25: not computed"
        page.screenshot(path=str(ARTIFACTS / "records-spc-filtered-1280.png"), full_page=False)
        # an impossible range: the server's 422 message on the page, and no stale chart left under it
        page.fill("#f-from", "2026-11-21")
        page.wait_for_selector("#spc-status >> text=from 2026-11-21 is after to 2026-11-20")
        assert page.locator("#spc-charts svg").count() == 0 and page.locator("#pareto-table tr").count() == 0
        assert page.text_content("#pareto-status") == "from 2026-11-21 is after to 2026-11-20"
        _no_sideways_scroll(page)
        assert errors == []


def test_records_view_fits_800x480(line, tmp_path):
    url, written = line
    with chromium_page(800, 480) as (page, errors):
        _open_records(page, url)
        _show_group(page, LABELS[0])
        _no_sideways_scroll(page)
        for sel in ("#rec-filters", "#spc-charts svg.wide", "#spc-summary", "#pareto-charts", "#spc-group"):
            box = page.locator(sel).first.bounding_box()
            assert box and box["x"] >= 0 and box["x"] + box["width"] <= 800, (sel, box)
        assert page.locator("svg.wide g.spc-pt.rule").count() >= 1
        page.locator("#spc-panel").scroll_into_view_if_needed()
        page.screenshot(path=str(ARTIFACTS / "records-spc-800.png"), full_page=False)
        page.locator("#pareto-panel").scroll_into_view_if_needed()
        page.screenshot(path=str(ARTIFACTS / "records-pareto-800.png"), full_page=False)
        page.click("#spc-points-box summary")  # the wide points table scrolls in its own box, not the page
        _no_sideways_scroll(page)
        _same_rows(_table(page, "#spc-points"), _download(page, "#spc-csv", tmp_path / "spc.csv"))
        assert errors == []
