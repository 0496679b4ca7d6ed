"""Issue 42's station features on boards that run the C reference firmware (firmware/, host target:
one Linux process per board on a pty, drivers/sim/firmware_boards.py), in the station's own batches.

1. The board's own calibrator as a second opinion (profile option board_selfcal, check
   `board_selfcal_agrees`). A fast-thermal batch at x250: s01-s03 run the firmware (caps `scal`),
   s04 is the Python board model (no calibrator). Truth: the station's own TDB/TDSF (offline fit)
   and, beside it, the station's streaming calibrator re-run on the same placed samples (the very
   algorithm the board runs, martinez2022 3.3): the board's figures are printed beside both. s01 and
   s02 must agree (check pass); s03's calibrator is skewed through the bridge
   (`$X,selfcal_skew,0.25`: its TDB 0.25 mg/C off) and must fail the check naming a TDB figure;
   s04's check is not applicable and its verdict is what the data give.
2. SFEM program and verify (a short SFEM site profile: 10 positions at chamber 25/45/65 C, then
   program and the verification cool-down back to 25 C), x2000; s01, s02 firmware (caps sfem3), s03
   the Python board model (version-1 record only). The station's thermal SFEM as the version-2 record:
   written ($SFTW/$SFTC), read back ($SFTR: CRC and values equal, decoded independently by
   contracts/sfem_cubic.py), applied ($COMP,1) and verified against the station's prediction while
   the plate cools; the residual per axis over temperature is printed; s01 then loses power and a
   fresh link reads back the same record from its flash (identity rec_ver=2); the Python board is
   not programmed and says so, and its verdict has no program-and-verify requirement.
`python -m pytest tests/test_firmware_station.py -s` prints the figures.
"""

from __future__ import annotations

import os
import shutil

import pytest

from contracts.sfem_cubic import SfemCubicRecord
from contracts.types import AXES
from drivers.sim.firmware_build import missing_tools
from drivers.sim.physics import draw_population
from drivers.serial_board import SerialBoard
from drivers.sim.station_sim import SimStation
from station.profiles import BUILTIN_PROFILES
from tests.test_daemon_e2e import coil, daemon

SPEED = 250.0
# The boards' target: the host process by default (fast); FW_STATION_TARGET=qemu runs the same batches
# on the emulated Cortex-M4 (firmware/targets/qemu), the image a real board runs.
TARGET = os.environ.get("FW_STATION_TARGET", "host")
SKEW_MG_PER_C = 0.25


def _need_host_firmware() -> None:
    missing = missing_tools(TARGET)
    if missing:
        if os.environ.get("STATION_REQUIRE_FIRMWARE") == "1":
            pytest.fail(f"firmware tools missing: {missing} (scripts/test.sh installs them)")
        pytest.skip(f"firmware tools missing: {missing}")
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")


def _steps_of(name: str) -> list[dict]:
    return [{k: v for k, v in s.to_json().items() if k in ("name", "position", "lamp", "chamber_setpoint_c", "require",
                                                            "dwell_s", "settle_s", "timeout_s")}
            for s in BUILTIN_PROFILES[name].steps]


def _check(slot: dict, measurement: str, axis: str | None = None) -> dict | None:
    checks = (slot.get("verdict_detail") or {}).get("checks") or []
    return next((c for c in checks if c["measurement"] == measurement and c["axis"] == axis), None)


@pytest.mark.timeout(150)
async def test_board_calibrator_second_opinion(tmp_path):
    _need_host_firmware()
    from db.repository import run_detail

    profiles = {"fast-thermal-selfcal": {"description": "fast-thermal, the boards' own calibrators compared",
                                         "analysis": "thermal", "steps": _steps_of("fast-thermal"),
                                         "board_selfcal": True}}
    async with SimStation(n_serial=4, n_can=0, seed=42, speed=SPEED, truths=draw_population(4, 42),
                          firmware={0: TARGET, 1: TARGET, 2: TARGET}) as sim:
        sim.board(2).selfcal_skew(SKEW_MG_PER_C)
        async with daemon(sim, tmp_path, SPEED, limits={"lamp_max_on_s": 9000.0}, profiles=profiles) as st:
            bid = st.start_batch("fast-thermal-selfcal", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=120)
            assert status["state"] == "finished", status["error"]
            assert await coil(sim) is False
            await st.flush_db()
            slots = {s["slot"]: s for s in status["slots"]}
            runs = {name: run_detail(st.db, s["run_id"]) for name, s in slots.items()}
    for name in ("s01", "s02", "s03", "s04"):
        s, run = slots[name], runs[name]
        assert s["state"] == "done", (name, s["fault_reason"])
        agree = _check(run, "board_selfcal_agrees")
        assert agree is not None, (name, run.get("verdict_detail"))
        print(f"\n{name} ({'firmware' if name != 's04' else 'Python model'}): {s['decision']['verdict']}: "
              f"{agree['outcome']}: {agree['reason']}")
        opinion = (s["result"] or {}).get("board_selfcal") or {}
        streaming = (s["result"] or {}).get("streaming") or {}
        for r in opinion.get("rows") or []:
            st_stream = (streaming.get("axes") or {}).get(r["axis"], {}).get(r["figure"])
            print(f"  {r['axis']} {r['figure']:<15} board {r['board']:+10.4f}  station {r['station']:+10.4f}  "
                  f"(station streaming {st_stream:+10.4f})  diff {r['difference']:+.4f}  u_board {r['u_board']:.4f} "
                  f"u_station {r['u_station']:.4f}  -> {r['difference'] / r['u_combined']:+.1f} u "
                  f"{'agrees' if r['agrees'] else 'DISAGREES'}")
    # s01, s02: the board's own calibrator agrees with the station's figures; its figures are the
    # station's streaming calibrator's on the same samples to within what placement changes
    for name in ("s01", "s02"):
        agree = _check(runs[name], "board_selfcal_agrees")
        assert agree["outcome"] == "pass" and agree["value"] == 1.0, (name, agree)
        rows = slots[name]["result"]["board_selfcal"]["rows"]
        assert len(rows) == 6 and all(r["agrees"] for r in rows), rows
        assert slots[name]["decision"]["verdict"] in ("pass", "marginal"), slots[name]["decision"]
        for a in AXES:
            tdb = _check(runs[name], "board_selfcal_tdb_mg_per_c", a)
            assert tdb is not None and tdb["low"] < tdb["value"] < tdb["high"], tdb
    # s03: skewed by 0.25 mg/C on TDB: the check fails, naming the TDB figures with both values
    agree = _check(runs["s03"], "board_selfcal_agrees")
    assert agree["outcome"] == "fail" and agree["value"] == 0.0, agree
    assert slots["s03"]["decision"]["verdict"] == "fail", slots["s03"]["decision"]
    assert "TDB board" in slots["s03"]["decision"]["reason"], slots["s03"]["decision"]["reason"]
    rows = slots["s03"]["result"]["board_selfcal"]["rows"]
    bad = {(r["axis"], r["figure"]) for r in rows if not r["agrees"]}
    assert bad and {f for _, f in bad} == {"tdb_mg_per_c"}, bad
    for r in rows:
        if r["figure"] == "tdb_mg_per_c":
            # independent truth: the skew the bridge injected, on top of the station's own figure
            assert r["difference"] == pytest.approx(SKEW_MG_PER_C, abs=6 * r["u_combined"]), r
    # s04: the Python board has no calibrator: not applicable, never a fail
    agree = _check(runs["s04"], "board_selfcal_agrees")
    assert agree["outcome"] == "pass" and "not applicable" in agree["reason"], agree
    assert slots["s04"]["decision"]["verdict"] in ("pass", "marginal"), slots["s04"]["decision"]


SFEM_POSITIONS = ("sfem-z0", "sfem-z90", "sfem-z180", "sfem-z270", "sfem-x0", "sfem-x90", "sfem-x180", "sfem-x270",
                  "sfem-y90", "sfem-y270")


def _short_sfem(temps_c: tuple[float, ...]) -> list[dict]:
    steps = []
    for t in temps_c:
        for k, name in enumerate(SFEM_POSITIONS):
            steps.append({"name": f"{name} @ {t:g} C", "position": name, "chamber_setpoint_c": t, "require": "static",
                          "settle_s": 1500.0 if k == 0 else 10.0, "dwell_s": 64.0,
                          "timeout_s": 6000.0 if k == 0 else 600.0})
    return steps


@pytest.mark.timeout(150)
async def test_sfem_cubic_programmed_read_back_and_verified(tmp_path):
    _need_host_firmware()
    from db.repository import run_detail

    speed = 2000.0
    profiles = {"sfem-short-verified": {
        "description": "SFEM, 10 positions at 3 chamber temperatures, then the cubic SFEM on the board",
        "analysis": "sfem", "steps": _short_sfem((25.0, 45.0, 65.0)),
        "program_verify": {"settle_s": 60.0, "timeout_s": 9000.0, "sfem_verify_dwell_s": 2400.0}}}
    async with SimStation(n_serial=3, n_can=0, seed=43, speed=speed, truths=draw_population(3, 43),
                          firmware={0: TARGET, 1: TARGET}) as sim:
        async with daemon(sim, tmp_path, speed, limits={"lamp_max_on_s": 9000.0}, profiles=profiles) as st:
            bid = st.start_batch("sfem-short-verified", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=130)
            assert status["state"] == "finished", status["error"]
            await st.flush_db()
            slots = {s["slot"]: s for s in status["slots"]}
            runs = {name: run_detail(st.db, s["run_id"]) for name, s in slots.items()}
        # after the batch: s01 loses power and boots from its flash (CRC checked at boot); a fresh
        # link reads back the record it holds, version 2, compensation still on
        board = sim.board(0)
        sim.power_cycle(0)
        await board.wait_ready()
        drv = SerialBoard(board.path)
        await drv.open()
        try:
            ident = await drv.identify()
            stored = await drv.read_sfem_cubic()
            comp = (await drv.read_thermal()).comp
        finally:
            await drv.close()
    for name in ("s01", "s02"):
        s = slots[name]
        assert s["state"] == "done", (name, s["fault_reason"])
        p, v = s["program"], s["verification"]
        assert p["programmed"] and p["comp"] and p["crc"] == p["readback_crc"] and p["readback_identical"], p
        rec = SfemCubicRecord(**{k: p["sfem_cubic"][k] for k in ("t_ref_c", "t_lo_c", "t_hi_c")},
                              coef=tuple(map(tuple, p["sfem_cubic"]["coef"])))
        assert p["crc"] == f"{rec.crc32():08X}"  # the station's own CRC of what it wrote (contracts/sfem_cubic.py)
        if name == "s01":  # what the board holds after a power cycle is what the station wrote
            assert stored == rec and stored.crc32() == rec.crc32() and comp, (stored, rec)
            assert ident.record is not None and ident.record.rec_ver == 2 and ident.record.rec_state == "ok", ident
        print(f"\n{name}: cubic SFEM {rec.t_lo_c:.1f}..{rec.t_hi_c:.1f} C written, read back CRC {p['readback_crc']}, "
              f"approximation {p['approximation']['max_output_error_mg'] * 1e3:.3f} ug; verified "
              f"{'PASS' if v['passed'] else 'FAIL'} over {v['temp_range_c'][0]:.1f}..{v['temp_range_c'][1]:.1f} C "
              f"({v['n_blocks']} blocks of {v['block_s']:.1f} s): {s['decision']['verdict']}")
        for a in AXES:
            ax = v["axes"][a]
            print(f"  {a}: residual rms {ax['residual_rms_mg']:.3f} mg, max {ax['residual_max_mg']:.3f} mg "
                  f"(limits {ax['limit_rms_mg']:.3f} / {ax['limit_max_mg']:.3f}; sigma {ax['sigma_mg']:.3f}: "
                  + ", ".join(f"{k} {x:.3f}" for k, x in ax["terms_mg"].items()) + ")")
        blocks = v["residual_blocks"]
        step = max(1, len(blocks["temp_c"]) // 8)
        print("  residual vs temperature (mg): " + "; ".join(
            f"{blocks['temp_c'][i]:.1f} C: " + " ".join(f"{blocks[a][i]:+.2f}" for a in AXES)
            for i in range(0, len(blocks["temp_c"]), step)))
        assert v["passed"] and not v["flags"], v["flags"]
        assert v["temp_range_c"][1] - v["temp_range_c"][0] > 20.0, v["temp_range_c"]
        assert _check(runs[name], "verify_failed_axes")["outcome"] == "pass"
        assert s["decision"]["verdict"] in ("pass", "marginal"), s["decision"]
    s = slots["s03"]  # the Python board model: version 1 only
    assert s["state"] == "done" and not s["program"]["programmed"] and s["program"]["not_applicable"], s["program"]
    assert "not programmed" in s["program"]["sfem_cubic"] and s["verification"] is None
    assert _check(runs["s03"], "program_crc_match") is None  # no program-and-verify requirement for it
    print(f"\ns03: {s['program']['sfem_cubic']}; {s['decision']['verdict']}")
