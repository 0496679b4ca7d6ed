"""Why runs do not pass, by name (station/records/causes.py), and first-pass and final yield per
group (station/records/spc_yield.py), issue 34.

The classifier is tested on the reasons the daemon writes: made by the daemon's own functions where
they are pure (contracts.trace.label_mismatch, station/daemon/plate_watch.py, the verdict's
final_verdict), else in the exact shape of its f-strings (the file each comes from is named). Then
over HTTP on a database of ended batches: the Pareto's causes, and the Records yield rows of each
batch equal to what GET /api/yield says for that batch.
"""

from __future__ import annotations

from types import SimpleNamespace

import httpx
import pytest

from contracts.positions import POSITION_NAMES
from contracts.trace import label_mismatch
from station.decisions.limits import default_products
from station.decisions.verdicts import RunRecord, final_verdict
from station.profiles import Step
from station.records import causes, pareto, spc_yield
from station.science.placement import direction_id

from end_view_support import OUTCOMES, Slot, mixed_slots, thermal, write_ended_batch

POS = {name: i for i, name in enumerate(POSITION_NAMES)}


def _facing(pos: str):
    """A DutRun as plate_watch reads it: settled at `pos`, never arrived at the step's position."""
    placement = SimpleNamespace(settled_direction=lambda: direction_id(POS[pos]), facing_now=lambda: direction_id(POS[pos]))
    return SimpleNamespace(slot="s03", placement=placement, arrived_t=None, faced_at_step_start=direction_id(POS[pos]))


def _daemon_reasons() -> list[tuple[str, str]]:
    """(reason as the daemon writes it, the cause it must be counted as)."""
    from station.daemon import plate_watch

    step = Step(name="N hot", position=POS["N"], lamp=True)
    link = "serial /dev/ttyACM3"
    can = "can slcan:/dev/ttyACM9 node 2"
    return [
        # station/daemon/slots.py: the label check, a resumed slot with another board, connect/start
        (label_mismatch("SIM9999", "SIM0003"), "label mismatch"),
        (f"{link}: found serial SIM0004, the interrupted run was SIM0003 (board swapped?)", "board swapped (resume)"),
        (f"{link}: no identity reply from /dev/ttyACM3 within 2 s", "board did not answer"),
        (f"{can}: no identity reply from CAN node 2 on /dev/ttyACM9 within 2 s", "board did not answer"),
        (f"{link}: cannot open serial port /dev/ttyACM3: [Errno 2] No such file or directory", "board did not answer"),
        (f"{link}: start failed: board /dev/ttyACM3 did not acknowledge START (3 tries)", "board did not answer"),
        # station/daemon/intake.py: the pump and the stall watchdog
        (f"{link}: link lost: serial port /dev/ttyACM3 is not open", "link lost"),
        (f"{can}: link lost: CAN bus /dev/ttyACM9 is not open", "link lost"),
        (f"{link}: no samples for 10.1 s", "no samples"),
        (f"{link}: only garbage for 10.4 s (312 bad frames/bytes, no good frame)", "garbage on the link"),
        (f"{link}: board data could not be read: ValueError: bad frame", "board data unreadable"),
        (f"{link}: board data could not be processed: IndexError: index 3 is out of bounds", "board data unreadable"),
        # station/daemon/sequencer.py and plate_watch.py: the plate after Done, a timeout, "Cannot do it"
        (plate_watch.never_arrived_reason(step, _facing("P"), 412.0, False, "Done"), "plate never arrived"),
        ("plate never arrived at P: 40 s after Done the plate faces N", "plate never arrived"),
        ("the plate faces -x, not P: 40 s after the fixture reported it reached", "plate at wrong position"),
        ("s01, s02 face -x, not P (a wrong turn?)", "plate at wrong position"),
        (plate_watch.never_arrived_reason(step, _facing("P"), 412.0, True, "Done"), "DUT never faced the position"),
        ("step 'P hot' timed out after 900 s sample time without a segment", "step timed out"),
        ("step 'P hot' timed out after 900 s sample time without a segment: the plate left P and it faces N",
         "step timed out"),
        ("Ana (token line-3 kiosk) could not turn the plate to N: plate jammed against the lamp bracket",
         "cannot do it (operator)"),
        # a re-prompt's words inside the operator's answer: still the operator's "Cannot do it"
        ("Ana could not s03 still faces N 40 s after Done: turn the plate to P: the link lost its clip",
         "cannot do it (operator)"),
        # station/daemon/program_verify.py, verdicts.py (_program_verify_causes)
        ("program: refused: board refused CALW (3 tries)", "programming"),
        ("program: crc_mismatch: read back 0x1234ABCD, wrote 0x89AB0001", "programming"),
        ("program: link: serial port /dev/ttyACM3 is not open", "link lost"),
        ("program: no thermal result to write", "programming"),
        ("not programmed: no programming record in this run (resumed after its program step?)", "programming"),
        ("not verified: no heat: the plate warmed 1.2 C (need 15)", "verification"),
        # station/daemon/run_end.py: the analysis, the storage, the batch's own end
        ("analysis: offline: orientation 0 holds data more than 0.8 g apart", "analysis"),
        ("analysis: 4 segment(s) logged (orientation 0: 1, orientation 1: 1, orientation 2: 2)", "analysis"),
        ("results not stored: database is locked (3 writes failed)", "results not stored"),
        ("batch aborted: aborted by Ana (token line-3 kiosk) at 2026-11-23 14:02:05 UTC", "aborted"),
        ("batch failed: safety trip: lamp on for 7201 s (limit 7200 s)", "safety trip"),
        ("batch failed: lamp relay failed: Modbus write coil (unit 1) at 127.0.0.1:502 failed: timeout "
         "(check its power, Modbus address (unit 1) and cable/network)", "lamp relay"),
        ("batch failed: fixture did not reach position P within 60 s", "fixture"),
        ("batch failed: thermal chamber failed: timeout (check its power, Modbus address (unit 4) and cable/network)",
         "thermal chamber"),
        ("batch failed: no DUT left: every slot is faulted", "no DUT left"),
        ("station restarted", "interrupted"),  # db.mark_interrupted at daemon start
        # one board, one record (issue 36): slots.board_changed, drivers StreamBreak, the station's
        # clock bound (sequencer), the temperature watch
        ("s01 answers SWAPPED-01 at the end of its run, SIM0001 at its start: a board swapped mid-run? "
         "(serial 'SIM0001' -> 'SWAPPED-01')", "board swapped mid-run"),
        ("program: not written: s01 answers SWAPPED-01 before programming, SIM0001 at its start: a board "
         "swapped mid-run? (serial 'SIM0001' -> 'SWAPPED-01')", "board swapped mid-run"),
        ("serial /dev/pts/4: the board's identity could not be read again at the end of its run: no identity "
         "reply from /dev/pts/4 within 2 s", "board swapped mid-run"),
        ("/dev/pts/18: the board restarted while streaming (seq 2010 -> 0, clock 668.2 s -> 0.1 s): a reset "
         "(power, brown-out, watchdog)? after 668.2 s board time; one run is one board's one timeline: its run "
         "ends here", "board reset mid-run"),
        ("/dev/pts/19: its clock jumped 600.0 s back while its seq ran on (seq 1929 -> 1930): a clock fault?",
         "board clock jumped"),
        ("step 'P hot' timed out without a +20 C rise: the station's clock ran 9000 s since Done, this board's "
         "own clock 2100 s (a board clock that slowed or stopped?)", "board clock slow"),
        ("temperature sensor stuck at 28 C: the plate's other DUTs rose 6.0 C (median) in the 188 s since the "
         "lamp went on", "temperature sensor"),
        ("temperature sensor implausible: 24 C -> 91 C in 0.3 s", "temperature sensor"),
        ("run interrupted: incomplete", "interrupted"),  # verdicts.decide without a fault reason
        # issue 42: a restart the board reports itself (its `boots` moved between two identity
        # replies: station/daemon/run_end.py "<slot>: " + identity_check.board_restart)
        ("s01: " + _restart_words(None), "board reset mid-run"),
        ("s02: " + _restart_words(0x08001A2C), "board reset mid-run"),
        # issue 42: the cubic SFEM written as the board's version-2 record (station/daemon/sfem_program.py
        # f"program: {exc.kind}: {exc}" after drivers/serial_board_commands.py's CalibrationError, retried
        # by sfem_program._tries): its write and read-back failures are "programming"
        ("program: crc_mismatch: failed after 3 attempts: /dev/pts/4 stored the cubic SFEM with CRC 1234ABCD, "
         "station computed 89AB0001", "programming"),
        ("program: crc_mismatch: failed after 3 attempts: board stored CRC 1234ABCD, station computed 89AB0001",
         "programming"),
        ("program: readback_mismatch: failed after 3 attempts: /dev/pts/4: the cubic SFEM read back has CRC "
         "1234ABCD, the board names 89AB0001", "programming"),
        ("program: readback_mismatch: failed after 3 attempts: read back CRC 1234ABCD differs from the written "
         "89AB0001 or its values do", "programming"),
        ("program: refused: failed after 3 attempts: SFTW,2 refused by /dev/pts/4: NVM write failed", "programming"),
        ("program: comp_not_set: compensation failed after 3 attempts: compensation still off after COMP 1",
         "programming"),
        ("program: nothing to write: no SFEM thermal model (one temperature step, or no SFEM result)", "programming"),
        ("not verified: no programming record for this run in this session: not verified", "verification"),
        ("not verified: only 12 compensated samples within the record's range 27.4..67.4 C after programming: "
         "not verified", "verification"),
    ]


def _restart_words(fault_pc: int | None) -> str:
    """station/daemon/identity_check.py board_restart's words for a watchdog or a fault reset."""
    from contracts.types import Identity
    from station.daemon.identity_check import board_restart

    before = Identity("SIM0001", boots=1, reset_cause="power")
    after = Identity("SIM0001", boots=2, reset_cause="fault" if fault_pc else "watchdog",
                     fault_pc=fault_pc, fault_cfsr=0x400 if fault_pc else None)
    words = board_restart(before, after)
    assert words is not None
    return words


@pytest.mark.parametrize("reason,cause", _daemon_reasons())
def test_each_daemon_reason_is_counted_by_its_cause(reason, cause):
    assert causes.cause_of(reason) == cause, reason
    assert cause in causes.CAUSES
    # the verdict's reason of a faulted run: the fault reason after its end (moment.end_of)
    assert causes.cause_of(f"faulted: {reason}") == cause, reason


def test_verdict_reasons_of_runs_that_did_not_finish():
    from station.decisions import moment

    seq = SimpleNamespace(ending="aborted", state="aborted", error="aborted by Ana (token kiosk) at 2026-11-23 14:02:05 UTC")
    d = SimpleNamespace(state="interrupted", fault_reason="")
    state, why = moment.end_of(seq, d)
    assert causes.cause_of(why) == "aborted", why
    seq = SimpleNamespace(ending="failed", state="failed", error="safety trip: lamp on for 7201 s (limit 7200 s)")
    assert causes.cause_of(moment.end_of(seq, d)[1]) == "safety trip"
    d = SimpleNamespace(state="faulted", fault_reason="serial /dev/ttyACM3: no samples for 10.1 s")
    assert causes.cause_of(moment.end_of(seq, d)[1]) == "no samples"
    assert causes.cause_of("interrupted: station restarted during the batch, DUT incomplete "
                           "(resumable: station serve --resume)") == "interrupted"
    assert causes.run_cause({"verdict": "error", "state": "faulted", "reasons": ["faulted"]})[0] == "faulted"


def test_words_no_rule_knows_stay_their_own_cause_without_link_and_numbers():
    assert causes.cause_of("serial /dev/ttyACM3: board reset itself 3 times") is None
    run = {"verdict": "error", "state": "faulted", "reasons": ["serial /dev/ttyACM3: board reset itself 3 times"]}
    assert causes.run_cause(run) == ("board reset itself N times", "serial /dev/ttyACM3: board reset itself 3 times")


def _run(result, state="done", why="", spec="LIS3DSH"):
    """A run as db.repository.judged_runs gives it, judged by the station's own verdict."""
    v = final_verdict(RunRecord("thermal", False, state, why, result, {"samples_lost": 0}, 2000),
                      default_products()[spec] if spec else None).to_json()
    return {"verdict": v["verdict"], "reasons": v["reasons"], "checks": v["checks"], "state": state, "fault_reason": why}


def test_run_cause_of_real_verdicts():
    # a fail by the measurement that failed it (its worst reason first), never by its words
    assert causes.run_cause(_run(thermal(tdsf=(-150.0, -120.0, -612.0)))) == ("limit: TDSF", "z TDSF -612 ppm/C, limit -500")
    assert causes.run_cause(_run(thermal(tdb=(1.62, 0.1, 0.2), e_fs=1.4)))[0] in ("limit: TDB", "limit: drift error E_FS")
    assert causes.run_cause(_run(thermal(e_fs=1.4)))[0] == "limit: drift error E_FS"
    # an error: a finished run without a required measurement, no limits for the part, a fault
    no_z = thermal()
    del no_z["axes"]["z"]
    assert causes.run_cause(_run(no_z)) == ("not measured", "z TDB not measured")
    assert causes.run_cause(_run(thermal(), spec=None))[0] == "no spec limits"
    mismatch = label_mismatch("SIM9999", "SIM0003")
    assert causes.run_cause(_run(None, "faulted", mismatch)) == ("label mismatch", mismatch)
    # the fault reason wins over a verdict reason that says less
    assert causes.run_cause({"verdict": "error", "state": "faulted", "reasons": ["run faulted: incomplete"],
                             "fault_reason": "serial /dev/ttyACM3: no samples for 10.1 s"})[0] == "no samples"


def _opinion(board_tdb_x: float, error: str | None = None) -> dict:
    """A board calibrator's opinion as station/science/selfcal_compare.py makes it (its JSON)."""
    from contracts.selfcal_opinion import OpinionRow, SelfCalOpinion

    if error is not None:
        return SelfCalOpinion(True, error=error).to_json()
    rows = tuple(OpinionRow(ax, fig, board, station, u, 0.003, 3.0)
                 for ax, b in zip("xyz", (board_tdb_x, -0.3, 0.4))
                 for fig, board, station, u in (("tdb_mg_per_c", b, (0.2, -0.3, 0.4)["xyz".index(ax)], 0.004),
                                                ("tdsf_ppm_per_c", -150.0, -150.0, 3.0)))
    return SelfCalOpinion(True, rows, n_segments_board=8, n_segments_station=8).to_json()


def _selfcal_run(opinion: dict, result: dict | None = None) -> dict:
    """A thermal run with the profile option board_selfcal, judged by the station's own verdict."""
    v = final_verdict(RunRecord("thermal", False, "done", "", result or thermal(), {"samples_lost": 0}, 2000,
                                board_selfcal=opinion), default_products()["LIS3DSH"]).to_json()
    return {"verdict": v["verdict"], "reasons": v["reasons"], "reason": v["reason"], "checks": v["checks"],
            "state": "done", "fault_reason": ""}


def test_board_calibrator_reasons_are_named():
    """Issue 42: the verdict's words of the board's own calibrator (the check board_selfcal_agrees),
    made by the station's own functions: a disagreement names its cause (a fail: the Pareto counts it
    by its check), a calibrator that could not be read names its own (an error); the code on the
    line follows its worst reason, so a limit failed first keeps its own."""
    from station.daemon.board_selfcal import BoardCalibrators
    from station.decisions.moment import board_opinion

    bad = _selfcal_run(_opinion(0.45))  # x TDB 0.25 mg/C off, u 0.005: 50 sigmas
    assert bad["verdict"] == "fail"
    assert bad["reasons"][0].startswith("board's own calibrator disagrees: x TDB board 0.45"), bad["reasons"]
    assert causes.cause_of(bad["reasons"][0]) == "board calibrator disagrees"
    assert causes.reason_code(bad["reason"]) == "board_calibrator_disagrees"
    assert causes.run_cause(bad)[0] == "limit: board calibrator agrees"
    good = _selfcal_run(_opinion(0.2))
    assert good["verdict"] == "pass" and causes.reason_code(good["reason"]) == "all_limits_met"
    both = _selfcal_run(_opinion(0.45), thermal(tdsf=(-150.0, -120.0, -612.0)))  # a limit first, then the opinion
    assert both["reasons"][0] == "z TDSF -612 ppm/C, limit -500" and len(both["reasons"]) == 2, both["reasons"]
    assert causes.reason_code(both["reason"]) == "limit_exceeded"
    unread = [
        _opinion(0.0, error="$SCRR failed: no reply to $SCRR from /dev/pts/4 within 1 s (3 tries)"),
        BoardCalibrators(True).opinion_of("s01"),  # never read at the end of the thermal steps
        board_opinion(SimpleNamespace(profile=SimpleNamespace(board_selfcal=True)), SimpleNamespace(slot="s01")),
    ]
    for op in unread:
        run = _selfcal_run(dict(op))
        assert run["verdict"] == "error", run
        assert run["reasons"][0].startswith("board's own calibrator: no comparison: "), run["reasons"]
        assert causes.run_cause(run) == ("board calibrator not read", run["reasons"][0])
        assert causes.reason_code(run["reason"]) == "board_calibrator_not_read"
    # a board without a calibrator: not applicable, a mark that is never among the reasons
    na = _selfcal_run({"shape": "board-selfcal/1", "applicable": False, "note": "caps: none; 'scal' needed"})
    assert na["verdict"] == "pass" and na["reasons"] == []


def test_sfem_verified_on_the_board_names_its_cause():
    """Issue 42: the cubic SFEM's verification on the board failed on an axis: the verdict's line
    (the contract's verify_failed_axes, then the told residual of the axis) names the SFEM's
    verification; the Pareto counts the fail by its check; a passing one says nothing."""
    fit = {"temp_c": 26.0, "bias": [0.012, -0.03, 0.0], "bias_sigma": [1e-4] * 3, "scale": [1.002, 0.997, 1.001],
           "scale_sigma": [1e-4] * 3}
    result = {"shape": "sfem-record/1", "t_ref_c": 25.0, "steps": [fit]}  # contracts/sfem_result.py
    prog = {"programmed": True, "comp": True, "attempts": 1, "crc": "70EFA827", "readback_crc": "70EFA827"}

    def axis(rms: float) -> dict:
        return {"passed": rms <= 2.97, "residual_rms_mg": rms, "residual_max_mg": 1.5 * rms, "limit_rms_mg": 2.97,
                "limit_max_mg": 3.94, "sigma_mg": 0.97}

    def judged(rms_y: float) -> dict:
        ver = {"kind": "sfem-cubic", "passed": rms_y <= 2.97, "flags": [], "temp_range_c": [27.9, 66.8],
               "axes": {"x": axis(0.4), "y": axis(rms_y), "z": axis(0.5)}}
        v = final_verdict(RunRecord("sfem", True, "done", "", result, {"samples_lost": 0}, 2000, prog, ver),
                          default_products()["LIS3DSH"]).to_json()
        return {"verdict": v["verdict"], "reasons": v["reasons"], "reason": v["reason"], "checks": v["checks"],
                "state": "done", "fault_reason": ""}

    bad = judged(4.1)
    assert bad["verdict"] == "fail", bad
    told = [r for r in bad["reasons"] if "SFEM on the board" in r]
    assert told and told[0].startswith("y SFEM on the board: residual rms 4.1 mg over 27.9..66.8 C over its limit")
    assert causes.cause_of(told[0]) == "SFEM verification failed"
    assert causes.reason_code(bad["reason"]) == "sfem_verification_failed", bad["reason"]
    assert causes.run_cause(bad)[0] == "limit: axes failing verification"
    good = judged(0.6)
    assert good["verdict"] == "pass" and causes.reason_code(good["reason"]) == "all_limits_met", good["reasons"]
    # an axis within its limit is never named a failure
    within = "x SFEM on the board: residual rms 0.4 mg over 27.9..66.8 C within its limit 2.97 mg"
    assert causes.cause_of(within) is None


def test_pareto_counts_causes_by_name_never_faulted():
    kinds = ["label", "label", "link lost", "no samples", "plate never arrived", "cannot", "analysis", "fail TDB",
             "fail TDB", "fail TDSF", "marginal", "pass A"]
    runs = []
    for i, k in enumerate(kinds):
        result, state, why = OUTCOMES[k]
        why = label_mismatch("X1", "SIM1") if k == "label" else why
        runs.append(dict(_run(result, state, f"faulted: {why}" if why else ""), fault_reason=why, run_id=i))
    p = pareto.pareto(runs)
    assert (p.runs, p.runs_failed, p.runs_error) == (12, 3, 7)
    got = {r.what: (r.fail, r.error) for r in p.causes}
    assert got == {"label mismatch": (0, 2), "limit: TDB": (2, 0), "link lost": (0, 1), "no samples": (0, 1),
                   "plate never arrived": (0, 1), "cannot do it (operator)": (0, 1), "analysis": (0, 1),
                   "limit: TDSF": (1, 0)}
    assert [r.what for r in p.causes][:2] == ["label mismatch", "limit: TDB"]  # most frequent first, ties by name
    assert "faulted" not in got and sum(r.count for r in p.causes) == 10  # the marginal and the pass: no cause


def test_first_pass_and_final_yield_per_group_follow_the_api_rule():
    def r(run_id, serial, verdict, batch, attempt=1):
        return {"run_id": run_id, "serial": serial, "verdict": verdict, "batch_id": batch, "attempt": attempt}

    runs = [r(1, "A", "pass", 1), r(2, "B", "fail", 1), r(3, "C", "error", 1), r(4, "D", "error", 1, attempt=0),
            r(5, "E", "marginal", 1),
            r(6, "B", "pass", 2, 2), r(7, "C", "error", 2, 2), r(8, "E", "pass", 2, 2), r(9, "D", "pass", 2)]
    rows = {y.key: y for y in spc_yield.yields(runs, "batch")}
    one, two = rows["1"], rows["2"]
    # batch 1: D's label mismatch is no attempt; A passed first time; B and E pass later (final)
    assert (one.judged, one.duts, one.first_pass, one.final_pass) == (4, 4, 1, 3)
    assert (one.first_pass_pct, one.final_pct, one.yield_pct) == (25.0, 75.0, 25.0)
    # batch 2 (the retest): its DUTs' first attempts were in batch 1 (B, C, E), D's first is here
    assert (two.judged, two.duts, two.first_pass, two.final_pass) == (4, 4, 1, 3)
    first, final = spc_yield.dut_outcomes([x for x in runs if x["attempt"] != 0])
    assert first == {"A": True, "B": False, "C": False, "E": False, "D": True}
    assert final == {"A": True, "B": True, "C": False, "E": True, "D": True}  # C: errors only, no final result


@pytest.fixture
def records_app(tmp_path):
    from db import Database
    from web.app import create_app
    from web.auth import TokenStore
    from web.db_repo import DbRepository
    from web_support import IdleStation, serve_in_thread

    db = Database(f"sqlite:///{tmp_path / 'causes.db'}", station="line-3")
    db.upgrade()
    first = write_ended_batch(db, mixed_slots())
    # the retest of its exceptions (the label scanned right this time): some pass now, some not
    again = {"s03": "pass A", "s05": "pass A", "s06": "fail TDSF", "s08": "pass B", "s10": "marginal", "s12": "pass A"}
    second = write_ended_batch(db, [Slot(k, v) for k, v in again.items()])
    app = create_app(IdleStation(db), repo=DbRepository(db), outbox=False,
                     tokens=TokenStore([("mes-token-causes-0001", "mes", "mes"), ("op-token-causes-0001", "operator", "op")]))
    url, stop = serve_in_thread(app)
    yield url, db, first, second
    stop()
    db.dispose()


def test_records_api_names_causes_and_gives_first_pass_and_final_yield_like_api_yield(records_app):
    url, db, first, second = records_app
    h = {"Authorization": "Bearer op-token-causes-0001"}
    mes = {"Authorization": "Bearer mes-token-causes-0001"}
    par = httpx.get(f"{url}/api/records/pareto", headers=h, timeout=30).json()
    got = {c["what"]: (c["fail"], c["error"]) for c in par["causes"]}
    assert got == {"limit: TDSF": (2, 0), "limit: TDB": (1, 0), "label mismatch": (0, 1), "link lost": (0, 1)}, got
    assert par["causes"][0]["what"] == "limit: TDSF" and "faulted" not in got
    label = next(c for c in par["causes"] if c["what"] == "label mismatch")
    assert label["example"] == label_mismatch("SIM9999", "SIM0003")  # the run's fault reason, as the daemon wrote it
    assert first["slots"]["s03"]["reason"] == "faulted: " + label["example"]  # its verdict's reason
    spc = httpx.get(f"{url}/api/records/spc", headers=h, timeout=30).json()
    by_batch = {y["key"]: y for y in spc["yield"]["batch"]}
    for b in (first["batch"], second["batch"]):
        api = httpx.get(f"{url}/api/yield", params={"batch_id": b}, headers=mes, timeout=30).json()
        row = by_batch[str(b)]
        assert (row["duts"], row["first_pass"], row["final_pass"]) == (api["duts"], api["first_pass"], api["final_pass"])
        assert row["first_pass_pct"] == pytest.approx(100 * api["first_pass_yield"])
        assert row["final_pct"] == pytest.approx(100 * api["final_yield"])
    # the first batch: 11 DUTs (the mismatched label tested no part), 6 passed at once, 9 in the end
    assert (by_batch[str(first["batch"])]["duts"], by_batch[str(first["batch"])]["first_pass"],
            by_batch[str(first["batch"])]["final_pass"]) == (11, 6, 9)
    # the retest: its 6 DUTs; s03's board passed on its first real attempt
    assert (by_batch[str(second["batch"])]["first_pass"], by_batch[str(second["batch"])]["final_pass"]) == (1, 4)
