"""Issue 42's new station outputs are declared in the OpenAPI document, on the wire of real batches.

tests/test_openapi_truth.py holds the document to the whole truth on the station's usual batches;
issue 42 adds outputs only boards running the C reference firmware produce (drivers/sim/
firmware_boards.py, host target: one Linux process per board on a pty): the boards' own calibrators
as a second opinion (profile option `board_selfcal`: `slots[].result.board_selfcal`, the checks
`board_selfcal_agrees` and its per-axis figures in `verdict_detail`) and the SFEM written to the
board as its version-2 record (`slots[].program`: `sfem_cubic`, `approximation`, `not_applicable`;
`slots[].verification` of kind `sfem-cubic`). Two short batches, as tests/test_firmware_station.py
runs them but smaller (2 firmware boards and 1 Python board model each), with the web app on the
same event loop: every GET /api/batches/{id} (live, while it runs and after its end, full and
compact, its slots), /api/slots, /api/runs/{id}, /api/runs/{id}/segments, /api/duts/{serial} and
/api/duts/{serial}/runs answer is validated against a strict copy of the live document
(tests/openapi_truth_support.py: undeclared fields forbidden), and the response models pass every
value the daemon sent unchanged. The answers must carry the new outputs, and the document without
each new field must be reported (else the validation would prove nothing); the named causes of
station/records/causes.py must name the real reason the verdict wrote (the disagreeing calibrator,
its code on the wire). The board identity's new fields (reset cause, boots, caps, ...) are not on
the wire: a run stores the identity's first seven fields (station/daemon/slots.py IDENTITY_FIELDS),
which the validated /api/runs answers show.
"""

from __future__ import annotations

import asyncio
import copy
import json

import httpx
import pytest

from openapi_truth_support import DOC_URI, Checker
from test_firmware_station import _need_host_firmware, _short_sfem, _steps_of
from test_openapi_truth import _passes_through

from drivers.sim.physics import draw_population
from drivers.sim.station_sim import SimStation
from station.records.causes import cause_of, reason_code
from tests.test_daemon_e2e import daemon

TOKEN = {"Authorization": "Bearer demo-admin-token"}  # cli/commands/demo.py DEMO_TOKENS
ROUTES = ("/api/batches/{batch_id}", "/api/batches/{batch_id}/slots", "/api/slots", "/api/runs/{run_id}",
          "/api/runs/{run_id}/segments", "/api/duts/{serial}", "/api/duts/{serial}/runs", "/api/profiles")


class Wire:
    """The web app on the daemon's own loop (httpx's ASGI transport): every answer kept as
    (route template, body) to validate, and the daemon's own statuses before any model."""

    def __init__(self, st) -> None:
        from web.app import create_app

        self.st = st
        self.app = create_app(st, outbox=False)
        self.client = httpx.AsyncClient(transport=httpx.ASGITransport(app=self.app), base_url="http://station",
                                        headers=TOKEN, timeout=60)
        self.answers: list[tuple[str, str, object]] = []
        self.raw: list[dict] = []

    async def get(self, template: str, params: dict | None = None, **path) -> object:
        url = template.format(**path)
        r = await self.client.get(url, params=params)
        assert r.status_code == 200, (url, r.status_code, r.text[:300])
        body = r.json()
        self.answers.append((template, url, body))
        return body

    async def poll(self, bid: int) -> dict:
        from web.views import batch_view

        st = await self.get("/api/batches/{batch_id}", batch_id=bid)
        self.raw.append(batch_view(self.st.batch_status(bid), bid))
        await self.get("/api/batches/{batch_id}", batch_id=bid, params={"view": "compact"})
        await self.get("/api/batches/{batch_id}/slots", batch_id=bid)
        await self.get("/api/slots")
        assert isinstance(st, dict)
        return st

    async def run(self, bid: int, timeout_s: float) -> dict:
        """Poll the batch while it runs (every route the operator page polls), then once ended."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while (st := await self.poll(bid))["state"] not in ("finished", "aborted", "failed", "interrupted"):
            assert loop.time() < end, f"batch {bid} did not end: {st['state']}"
            await asyncio.sleep(1.0)
        await self.st.wait_batch(bid, timeout_s=30)
        await self.st.flush_db()
        return await self.poll(bid)

    async def stored(self, status: dict) -> dict[str, dict]:
        """Every run of the ended batch from the database: the run, its segments, its DUT, its DUT's runs."""
        runs = {}
        for s in status["slots"]:
            runs[s["slot"]] = await self.get("/api/runs/{run_id}", run_id=s["run_id"])
            await self.get("/api/runs/{run_id}/segments", run_id=s["run_id"])
            await self.get("/api/duts/{serial}", serial=s["serial"])
            await self.get("/api/duts/{serial}/runs", serial=s["serial"])
        await self.get("/api/profiles")
        return runs

    async def problems(self, new_fields: list[tuple[str, str]], parts: list[tuple[str, object]]) -> list[str]:
        """What the strict document does not declare, and what the models changed of the daemon's
        statuses. `parts` (component, value): values of the answers validated against the one
        schema they must match (inside a union the checker may name the wrong branch).
        `new_fields` (component, property): issue 42's fields these answers carry; the document
        without each of them must be reported (the check sees them, it is not vacuous)."""
        from web.schemas import BatchStatus
        from web.views import clean

        doc = (await self.client.get("/openapi.json")).json()
        assert {t for t, _u, _b in self.answers} == set(ROUTES)

        def found(d: dict) -> list[str]:
            checker = Checker(d)
            out = {p for t, _u, b in self.answers for p in checker.problems("GET", t, b)}
            out |= {p for name, v in parts for p in checker.validate(f"{DOC_URI}#/components/schemas/{name}", v, name)}
            return sorted(out)

        out = found(doc)
        for component, prop in new_fields:
            thin = copy.deepcopy(doc)
            del thin["components"]["schemas"][component]["properties"][prop]
            assert any(f"'{prop}' was unexpected" in p for p in found(thin)), (component, prop)
        for raw in self.raw:
            sent = json.loads(json.dumps(clean(raw)))
            out += sorted(set(_passes_through(sent, BatchStatus.model_validate(raw).model_dump(mode="json"), "status")))
        return out

    async def aclose(self) -> None:
        await self.client.aclose()


def _check(run: dict, measurement: str, axis: str | None = None) -> dict | None:
    checks = (run.get("verdict_detail") or {}).get("checks") or []
    return next((c for c in checks if c["measurement"] == measurement and c["axis"] == axis), None)


@pytest.mark.timeout(120)
async def test_board_selfcal_outputs_are_declared(tmp_path):
    _need_host_firmware()
    speed = 250.0
    profiles = {"fast-thermal-selfcal": {"description": "fast-thermal, the boards' own calibrators compared",
                                         "analysis": "thermal", "steps": _steps_of("fast-thermal"),
                                         "board_selfcal": True}}
    async with SimStation(n_serial=3, n_can=0, seed=42, speed=speed, truths=draw_population(3, 42),
                          firmware={0: "host", 1: "host"}) as sim:
        sim.board(1).selfcal_skew(0.25)  # s02's calibrator 0.25 mg/C off on TDB: the check fails
        async with daemon(sim, tmp_path, speed, limits={"lamp_max_on_s": 9000.0}, profiles=profiles) as st:
            wire = Wire(st)
            try:
                bid = st.start_batch("fast-thermal-selfcal", None, "pytest")
                status = await wire.run(bid, timeout_s=100)
                assert status["state"] == "finished", status["error"]
                runs = await wire.stored(status)
                problems = await wire.problems(
                    [("ThermalCalibration", "board_selfcal"), ("SelfCalRow", "board_from_segments"),
                     ("SelfCalNoise", "terms")],
                    [("ThermalCalibration", s["result"]) for s in status["slots"]])
            finally:
                await wire.aclose()
    slots = {s["slot"]: s for s in status["slots"]}
    # the new outputs are on the wire (else the validation proved nothing)
    for name in ("s01", "s02"):
        op = slots[name]["result"]["board_selfcal"]
        assert op["applicable"] and len(op["rows"]) == 6 and op["n_segments_board"] > 0, op
        assert _check(runs[name], "board_selfcal_agrees") is not None
        assert _check(runs[name], "board_selfcal_tdb_mg_per_c", "x") is not None
    assert "board_selfcal" not in (slots["s03"]["result"] or {})  # no calibrator: no comparison to show
    assert _check(runs["s03"], "board_selfcal_agrees")["outcome"] == "pass"  # not applicable, never a fail
    # the disagreeing calibrator: its reason, as the verdict wrote it, has its named cause and code
    bad = _check(runs["s02"], "board_selfcal_agrees")
    assert bad["outcome"] == "fail", bad
    assert cause_of(bad["reason"]) == "board calibrator disagrees", bad["reason"]
    assert slots["s02"]["decision"]["reason"].startswith("board's own calibrator disagrees"), slots["s02"]["decision"]
    assert slots["s02"]["reason_code"] == "board_calibrator_disagrees", slots["s02"]
    assert runs["s02"]["reason_code"] == reason_code(runs["s02"]["reason"]) == "board_calibrator_disagrees"
    print(f"\n{len(wire.answers)} answers validated; s02: {bad['reason'][:120]}")
    assert problems == [], "\n".join(problems[:40])


@pytest.mark.timeout(120)
async def test_sfem_program_and_verify_outputs_are_declared(tmp_path):
    _need_host_firmware()
    speed = 2000.0
    profiles = {"sfem-short-verified": {
        "description": "SFEM, 10 positions at 3 chamber temperatures, then the cubic SFEM on the board",
        "analysis": "sfem", "steps": _short_sfem((25.0, 45.0, 65.0)),
        "program_verify": {"settle_s": 60.0, "timeout_s": 9000.0, "sfem_verify_dwell_s": 2400.0}}}
    async with SimStation(n_serial=3, n_can=0, seed=43, speed=speed, truths=draw_population(3, 43),
                          firmware={0: "host", 1: "host"}) as sim:
        async with daemon(sim, tmp_path, speed, limits={"lamp_max_on_s": 9000.0}, profiles=profiles) as st:
            wire = Wire(st)
            try:
                bid = st.start_batch("sfem-short-verified", None, "pytest")
                status = await wire.run(bid, timeout_s=100)
                assert status["state"] == "finished", status["error"]
                runs = await wire.stored(status)
                problems = await wire.problems(
                    [("LiveProgram", "sfem_cubic"), ("LiveProgram", "approximation"), ("LiveProgram", "not_applicable"),
                     ("SfemVerification", "residual_blocks"), ("SfemAxisVerification", "terms_mg"),
                     ("SfemCalibration", "rmse_heldout_mg"), ("SfemCalibration", "residuals")],
                    [("SfemCalibration", s["result"]) for s in status["slots"]]
                    + [("SfemVerification", s["verification"]) for s in status["slots"] if s["verification"]])
            finally:
                await wire.aclose()
    slots = {s["slot"]: s for s in status["slots"]}
    for name in ("s01", "s02"):  # programmed with the cubic SFEM, verified on the cool-down
        p, v = slots[name]["program"], slots[name]["verification"]
        assert p["programmed"] and isinstance(p["sfem_cubic"], dict) and p["approximation"], p
        assert v["kind"] == "sfem-cubic" and set(v["axes"]) == {"x", "y", "z"}, v
        assert _check(runs[name], "sfem_verified_residual_rms_mg", "x") is not None, runs[name]["verdict_detail"]
    p = slots["s03"]["program"]  # the Python board model: no version-2 record, not programmed
    assert p["not_applicable"] is True and isinstance(p["sfem_cubic"], str), p
    print(f"\n{len(wire.answers)} answers validated")
    assert problems == [], "\n".join(problems[:40])
