"""Issue 35: each run stores what measured it (the station software's version, the board firmware's as
its identity reply reports it, and what turned the plate: the fixture or a person), the run's API
shows it and the certificate states it: a run without a fixture never reads "the fixture holds".

A real fast-thermal batch on simulated boards (serial boards report firmware "sim-1.0"; the CAN
identity frames carry none), once with the motorized fixture and once without (a simulated person
answers each prompt and turns the plate), then the stored columns, GET /api/runs/{id} and the
certificate's text.
"""

from __future__ import annotations

import asyncio

import pytest
from fastapi.testclient import TestClient

from db import repository as repo
from drivers.sim.operator import Person
from drivers.sim.station_sim import SimStation
from station.records.certificate import certificate_for
from station.records.certificate_layout import layout
from station.version import software_version
from web.app import create_app
from web.auth import TokenStore
from test_daemon_e2e import daemon

SPEED = 1000.0
TOKEN = "op-token-measured-0123"


def _text(cert) -> str:
    """The certificate's words in reading order, one space between words (rows wrap anywhere)."""
    return " ".join(" ".join(" ".join(r.cells) for page in layout(cert) for r in page).split())


async def _batch(tmp_path, fixture: bool):
    async with SimStation(n_serial=1, n_can=1, seed=21, speed=SPEED) as sim:
        async with daemon(sim, tmp_path, SPEED, fixture=fixture, limits={"lamp_max_on_s": 9000.0}) as st:
            hands = None
            if not fixture:  # a person at the plate answers every prompt and turns it
                person = Person(sim.world, lambda b, pid: st.answer_prompt(b, pid, "done", by="simulated person"),
                                seed=3)
                hands = asyncio.create_task(person.run(st.bus))
            try:
                bid = st.start_batch("fast-thermal", None, "pytest")
                status = await st.wait_batch(bid, timeout_s=400)
                await st.flush_db()
            finally:
                if hands is not None:
                    hands.cancel()
            assert status["state"] == "finished", status["error"]
            runs = repo.batch_detail(st.db, bid)["runs"]
            certs = {r["slot"]: certificate_for(st.db, r["serial"]) for r in runs}
            app = create_app(st, tokens=TokenStore([(TOKEN, "operator", "op")]), outbox=False)
            with TestClient(app) as c:
                api = [c.get(f"/api/runs/{r['id']}", headers={"Authorization": f"Bearer {TOKEN}"}) for r in runs]
    return runs, certs, api


@pytest.mark.timeout(600)
@pytest.mark.parametrize("fixture", [True, False], ids=["fixture", "no-fixture"])
async def test_a_run_stores_and_states_what_measured_it(tmp_path, fixture):
    runs, certs, api = await _batch(tmp_path, fixture)
    holder = "fixture" if fixture else "operator"
    version = software_version()
    assert version  # the package is installed (scripts/setup.sh): a run never stores a guess
    firmware = {"s01": "sim-1.0", "c01": None}
    for r, answer in zip(runs, api):
        assert (r["software_version"], r["firmware_version"], r["holder"]) == (version, firmware[r["slot"]], holder)
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert (body["software_version"], body["firmware_version"], body["holder"]) == (
            version, firmware[r["slot"]], holder)
    for slot, cert in certs.items():
        text = _text(cert)
        assert f"thermal-cal-station {version} measured this run" in text, text
        assert "not stored with this run" not in text  # neither the version nor the holder is missing
        assert f"firmware {firmware[slot] or 'not reported'}" in text
        if fixture:
            assert "Plate turned by the station's motorized fixture" in text
            assert "The station's motorized fixture turned the plate to each position" in text
            assert "by hand" not in text
        else:
            assert "Plate turned by a person, by hand (no fixture)" in text
            assert "A person turned the plate to each position by hand" in text
            assert "fixture turned" not in text and "fixture holds" not in text


def test_a_run_from_before_the_columns_says_so_and_guesses_nothing():
    from station.records.certificate import build_certificate

    run = {"id": 4, "batch_id": 1, "serial": "OLD1", "identity": {"sensor": "LIS3DSH", "fw": "2.1"}}
    cert = build_certificate(run, {"station": "s1", "operator": "op", "profile": "fast-thermal", "schema_version": "0008"},
                             [], software_version="9.9")
    text = _text(cert)
    assert "thermal-cal-station 9.9 issued this certificate" in text and "the version that measured is not stored with this run" in text
    assert "Plate turned by not stored with this run" in text
    assert "What turned the plate (a fixture or a person) is not stored with this run" in text
    assert "firmware 2.1" in text  # the identity stored with the run still names it
