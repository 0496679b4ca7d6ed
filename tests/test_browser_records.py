"""The Records view in headless Chromium (issue 13): on a database holding several judged batches,
the SPC charts (SVG drawn by the page), Cpk, the yield table and the audit trail show, and the DUT
history offers the certificate PDF. Screenshots go to artifacts/."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from db import Database
from db import repository as repo
from records_support import write_batches
from web.app import create_app
from web.auth import TokenStore
from web.db_repo import DbRepository
from web_support import CHROMIUM, IdleStation, chromium_page, serve_in_thread

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"
ADMIN = "admin-token-records-01"

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (scripts/test.sh installs it)"),
]


def test_records_view_spc_yield_audit_and_certificate(tmp_path):
    pytest.importorskip("playwright.sync_api")
    ARTIFACTS.mkdir(exist_ok=True)
    db = Database(f"sqlite:///{tmp_path / 'r.db'}", station="line-5")
    db.upgrade()
    written = write_batches(db, n_batches=4, per_batch=6, seed=5)
    repo.audit_append(db, "anna", "batch.start", f"batch {written[0]['batch']}", {"profile": "fast-thermal"})
    repo.audit_append(db, "anna", "batch.abort", f"batch {written[-1]['batch']}", {"reason": "operator"})
    app = create_app(IdleStation(db), repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([(ADMIN, "admin", "lead")]))
    url, stop_server = serve_in_thread(app)
    try:
        expected = httpx.get(f"{url}/api/records/spc", params={"parameter": "tdb_mg_per_c:x"},
                             headers={"Authorization": f"Bearer {ADMIN}"}, timeout=30).json()
        with chromium_page(1400, 1500) as (page, errors):
            page.goto(url + "/")
            page.fill("#token", ADMIN)
            page.click("#save-token")
            page.wait_for_selector("#whoami >> text=lead (admin)")
            page.click("#tab-records")
            try:
                page.wait_for_selector("#spc-charts svg.spc-chart >> nth=3")
            except Exception:
                page.screenshot(path=str(ARTIFACTS / "records-spc-failed.png"), full_page=True)
                raise AssertionError(f"no charts: status {page.text_content('#spc-status')!r}, errors {errors}")
            assert page.locator("#spc-charts svg.spc-chart").count() == 4
            first = page.input_value("#spc-parameter")
            assert first == "tdb_mg_per_c:x"
            assert page.text_content("#spc-parameter option:checked") == "TDB x (mg/°C)"  # in words, with unit
            # 24 runs: below the minimum n, so no Cpk, and the page says so (issue 24; was a number)
            assert expected["capability"]["cpk"] is None and expected["capability"]["n"] == 24
            assert page.text_content("[data-fig=cpk]") == "Cpk n=24 < 25: not computed"
            n_points = page.locator("#spc-charts svg.spc-chart >> nth=0").locator("g.spc-pt").count()
            assert n_points == len(written) == 24
            beyond = page.evaluate("[...document.querySelectorAll('#spc-charts g.spc-pt')]"
                                   ".filter((g) => g.dataset.rules.split(',').includes('1')).length")
            assert beyond == len(expected["chart"]["out_of_control"])
            yield_rows = page.locator("#yield-table tr[data-by=batch]")
            assert yield_rows.count() == 4
            assert page.text_content("#yield-table tr[data-by=batch] >> nth=1").endswith("66.7 %")  # batch 2: 4 of 6 pass
            audit = page.locator("#audit-table tr[data-action]")
            assert audit.count() == 2 and "batch.abort" in audit.nth(0).text_content()
            assert "line-5" in audit.nth(0).text_content()
            page.screenshot(path=str(ARTIFACTS / "records-spc.png"), full_page=True)
            # another parameter
            page.select_option("#spc-parameter", "tdsf_ppm_per_c:z")
            page.wait_for_selector("#spc-charts .spc-title >> text=Individuals: TDSF z (ppm/°C)")
            # certificate from the DUT history
            page.click("#tab-history")
            page.fill("#search", written[0]["serial"])
            page.click("#search-go")
            page.wait_for_selector("button.certificate")
            with page.expect_download() as dl:
                page.click("button.certificate")
            pdf = tmp_path / "c.pdf"
            dl.value.save_as(str(pdf))
            assert pdf.read_bytes().startswith(b"%PDF")
            assert page.text_content(".cert-msg") == ""
            page.screenshot(path=str(ARTIFACTS / "records-history-certificate.png"))
            assert errors == []
    finally:
        stop_server()
        db.dispose()


def test_records_view_pareto_causes_by_name_and_first_pass_and_final_yield(tmp_path):
    """Issue 34: the Pareto's second chart and table count one cause per failed or error run by name
    (a label mismatch, a lost link, the limit that failed), never "faulted"; the yield table shows
    first-pass and final yield per group, equal to GET /api/yield for each batch."""
    pytest.importorskip("playwright.sync_api")
    from end_view_support import Slot, mixed_slots, write_ended_batch

    ARTIFACTS.mkdir(exist_ok=True)
    db = Database(f"sqlite:///{tmp_path / 'causes.db'}", station="line-3")
    db.upgrade()
    first = write_ended_batch(db, mixed_slots())
    again = {"s03": "pass A", "s05": "pass A", "s06": "fail TDSF", "s08": "pass B", "s10": "marginal", "s12": "pass A"}
    second = write_ended_batch(db, [Slot(k, v) for k, v in again.items()])  # the retest of its exceptions
    app = create_app(IdleStation(db), repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([(ADMIN, "admin", "lead")]))
    url, stop_server = serve_in_thread(app)
    try:
        api = {b: httpx.get(f"{url}/api/yield", params={"batch_id": b}, headers={"Authorization": f"Bearer {ADMIN}"},
                            timeout=30).json() for b in (first["batch"], second["batch"])}
        with chromium_page(1280, 800) as (page, errors):
            page.goto(url + "/")
            page.fill("#token", ADMIN)
            page.click("#save-token")
            page.wait_for_selector("#whoami >> text=lead (admin)")
            page.click("#tab-records")
            page.wait_for_selector("#pareto-table tr[data-table=causes]")
            page.wait_for_selector("#yield-table tr[data-by=batch]")
            causes = page.evaluate("() => [...document.querySelectorAll('#pareto-table tr[data-table=causes]')]"
                                   ".map((tr) => [...tr.children].map((td) => td.textContent))")
            assert [(c[2], c[3], c[4]) for c in causes] == [
                ("limit: TDSF", "2", "0"), ("label mismatch", "0", "1"), ("limit: TDB", "1", "0"), ("link lost", "0", "1")]
            bars = page.evaluate("() => [...document.querySelectorAll('#pareto-charts svg')[1].querySelectorAll('rect.pareto-bar')]"
                                 ".map((r) => r.dataset.what)")
            assert bars == ["limit: TDSF", "label mismatch", "limit: TDB", "link lost"]
            head = page.evaluate("() => [...document.querySelectorAll('#yield-table tr:first-child th')].map((t) => t.textContent)")
            assert head[-3:] == ["DUTs", "first pass", "final"], head
            rows = {r[1]: r for r in page.evaluate(
                "() => [...document.querySelectorAll('#yield-table tr[data-by=batch]')].map((tr) => [...tr.children]"
                ".map((td) => td.textContent))")}
            for b, y in api.items():
                row = rows[str(b)]
                assert row[-3:] == [str(y["duts"]), f"{100 * y['first_pass_yield']:.1f} %", f"{100 * y['final_yield']:.1f} %"], (row, y)
            assert rows[str(first["batch"])][-3:] == ["11", "54.5 %", "81.8 %"]  # 6 and 9 of its 11 DUTs
            page.locator("#pareto-panel").scroll_into_view_if_needed()
            page.locator("#pareto-panel").screenshot(path=str(ARTIFACTS / "records-pareto-causes-1280.png"))
            page.locator("#yield-table").screenshot(path=str(ARTIFACTS / "records-yield-first-pass-final-1280.png"))
            assert errors == []
    finally:
        stop_server()
        db.dispose()
