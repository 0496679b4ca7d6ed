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
    ]


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
