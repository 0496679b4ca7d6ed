"""Fault matrix (issue "A PASS you can trust", design 8): every fault x every profile over the whole
daemon (simulated boards on real ptys / an slcan pty, Modbus relay, fixture and chamber on
127.0.0.1, SQLite on disk, the real Station), each fault applied at the step where it hurts.

The promise checked in every cell: no DUT with a fault or a missing required measurement is `pass`
in the batch status, the database, the MES feed or the webhook, and its verdict's reason names the
fault; the healthy DUTs of the same (finished) batch are judged per their data (pass / marginal /
fail), so a cell cannot pass because everything is error; a pass anywhere is backed by the run's
evidence (program and verify: CRC written == read back, compensation on, verified E per axis).

Faults: board link lost (fast-thermal: during P hot; verified: on the first $CALW and, separately,
during the verification heat; sfem-24: in the 45 C block), write refused / CRC mismatch /
lost reply (persistent: refuse_writes(99), every write flipped, a damaged read-back CRC, every reply
dropped; plus single transient faults that the 3 tries must absorb: those DUTs must be programmed
on the retry (CRC match, compensation on) and judged per their data, never error),
power cycle between write and read-back (the board restarts right after acking $CALW: NVM kept,
RAM lost), operator abort in each step (sfem-24: its first step, the 45 C block and its last step),
daemon SIGKILL then --resume, the Modbus relay stops answering, and the database's disk full.
Cells that do not apply are n/a (write faults need program and verify).

The matrix is printed (`pytest -s`) and written to artifacts/fault_matrix.txt; the list of broken
promises under it names slot, place and reason. One batch per profile and fault moment, faults that
do not interact on different slots of one batch, batches of a profile run PARALLEL at a time
(longest first).
"""

from __future__ import annotations

import asyncio
import dataclasses
import sys

import pytest

from drivers.sim.mes_standin import MesStandIn
from drivers.sim.operator import HumanTiming, Person
from drivers.sim.station_sim import SimStation
from tests.db_helpers import HOLD_LOCK
from tests.ownership_support import check_during_batch
from tests.fault_matrix_support import (
    LIMITS, MATRIX, PLAN_SLACK_S, PROFILES, ROWS, VERIFIED, Ctx, Expect, KillCtx, Plan, board_hook, coil,
    collect_and_check, daemon, fill, run_all, wait_for,
)

FAST = 250.0  # fast-thermal(-verified): x250, like tests/test_program_verify_e2e.py
SFEM_SPEED = 3000.0  # sfem-24 is ~12 h of sample time: x3000 (tests/test_daemon_e2e.py runs it at x4000)
PARALLEL = 4  # batches of one profile at a time: they mostly wait on simulated hardware
# sfem-24 is CPU-bound at x3000 (12 h of samples per plan): on a loaded 2-core machine a plan takes
# minutes of wall time, so two run at once (with more, starved board readers and a starved Modbus
# server read as silent boards and a failed fixture) and the
# limits that only guard against a hang are generous; a fast machine finishes as fast as before
SFEM_PARALLEL = 2
SFEM_PLAN_TIMEOUT_S = 420.0
SFEM_STEP_TIMEOUT_S = 300.0

LINK = ("link",)
ABORT = ("abort",)
RELAY = ("relay",)
DISK = ("not stored", "database", "disk", "space")
KILL = ("restart", "resum", "interrupt", "killed", "programming record")
LABEL = ("label serial",)
CANNOT = ("could not turn the plate",)
NO_FIXTURE = {"fixture": False}  # the operator turns the plate: the station prompts
NEVER = ("never arrived",)
PEOPLE = ["person: Done before turning the plate", "person: wrong turn, then corrected", "person: plate never arrives"]


def _labels(**by_slot):
    """Label serials per slot: a string is scanned as is; 0 scans the board's own serial (a match)."""
    def labels(sim: SimStation) -> dict[str, str]:
        return {slot: (v if isinstance(v, str) else _own_serial(sim, slot)) for slot, v in by_slot.items()}
    return labels


def _own_serial(sim: SimStation, slot: str) -> str:
    """The serial the simulated board in `slot` reports (s01.. serial boards first, then c01.. CAN)."""
    kind, k = slot[0], int(slot[1:]) - 1
    index = k if kind == "s" else sim.n_serial + k
    return sim.world.identity(index).serial


# issue 42: the board's own calibrator as a second opinion (profile option board_selfcal, firmware boards)
SELFCAL_ROWS = ["board calibrator disagrees (board_selfcal)", "board calibrator: $SCRR answers E"]
ROWS[:] = [r for r in ROWS if r not in SELFCAL_ROWS]
ROWS[-1:-1] = SELFCAL_ROWS  # before the healthy DUTs' row


@pytest.fixture(scope="module", autouse=True)
def matrix_report():
    yield
    print("\n" + MATRIX.write())


def _report(profile: str) -> None:
    text = MATRIX.write()
    print("\n" + text)
    probs = MATRIX.problems(profile)
    assert not probs, f"{len(probs)} broken promise(s) for {profile}:\n" + "\n".join(probs)


# ------------------------------------------------------------------------------- shared injections
def _abort_in(step: int, min_samples: int = 10, timeout_s: float = 120.0):
    async def inject(ctx: Ctx) -> None:
        async with ctx.at_step(step, min_samples, timeout_s):
            ctx.st.abort(ctx.bid, f"fault matrix: abort in step {step}")
    return inject


def _abort_in_program():
    async def inject(ctx: Ctx) -> None:
        async with ctx.at_program_step():
            ctx.st.abort(ctx.bid, "fault matrix: abort in the program step")
    return inject


def _abort_in_heat():
    async def inject(ctx: Ctx) -> None:
        async with ctx.at_heat_lamp_on():
            ctx.st.abort(ctx.bid, "fault matrix: abort during the verification heat")
    return inject


def _cannot_at_first_prompt():
    """No fixture: at the first "turn the plate" prompt the operator answers that it cannot be done,
    with words (every DUT on the plate ends as error, the batch fails, the lamp stays off)."""
    async def inject(ctx: Ctx) -> None:
        await ctx.wait(lambda: ctx.st.prompt(ctx.bid) is not None, "the first turn-the-plate prompt")
        prompt = ctx.st.prompt(ctx.bid)
        ctx.st.answer_prompt(ctx.bid, prompt["id"], "cannot", by="fault matrix",
                             note="plate jammed against the lamp bracket")
    return inject


def _person(timing):
    """No fixture: the plate is turned by the simulated person (drivers/sim/operator.py) with this
    behaviour, from the first prompt to the end of the batch."""
    async def inject(ctx: Ctx) -> None:
        person = Person(ctx.sim.world, lambda b, pid: ctx.st.answer_prompt(b, pid, "done", by="fault matrix person"),
                        timing=timing, seed=ctx.plan.seed)
        await person.run(ctx.st.bus)
    return inject


def _done_but_never_turned():
    """No fixture: every prompt is answered Done at once and the plate is never turned: the first
    step that needs another position than where the plate sits never gets its plate."""
    async def inject(ctx: Ctx) -> None:
        answered: set[int] = set()
        while True:
            p = ctx.st.prompt(ctx.bid)
            if p is not None and p["id"] not in answered:
                answered.add(p["id"])
                try:
                    ctx.st.answer_prompt(ctx.bid, p["id"], "done", by="fault matrix")
                except ValueError:
                    pass
            await asyncio.sleep(0.02)
    return inject


def _people_plans(profile: str, speed: float, seed: int, n_serial: int = 2, n_can: int = 1,
                  timeout_s: float = 150.0) -> list[Plan]:
    """The human rows: Done pressed before the turn and a wrong turn (corrected when the station
    names it) never fault a healthy DUT; a plate that never arrives ends every DUT as error, with
    that reason; a fixture that reports "reached" early never mislabels samples."""
    slots = _slots(n_serial, n_can)
    done_first = HumanTiming.fixed(react_s=5.0, turn_s=4.0, confirm_s=1.0, done_first=True)
    wrong = HumanTiming.fixed(react_s=5.0, turn_s=4.0, confirm_s=1.0, wrong_turn=True)

    def early(sim: SimStation) -> None:
        sim.modbus.move_time_s = 60.0
        sim.modbus.reports_early_s = 50.0  # "reached, not moving" 50 s before the plate gets there

    return [
        Plan(f"{profile}-done-first", profile, speed, n_serial, n_can, seed, hands=_person(done_first), kw=NO_FIXTURE,
             timeout_s=timeout_s, expects=_all(slots, PEOPLE[0], kind="unharmed")),
        Plan(f"{profile}-wrong-turn", profile, speed, n_serial, n_can, seed + 1, hands=_person(wrong), kw=NO_FIXTURE,
             timeout_s=timeout_s, expects=_all(slots, PEOPLE[1], kind="unharmed")),
        Plan(f"{profile}-never", profile, speed, 1, 1, seed + 2, hands=_done_but_never_turned(), kw=NO_FIXTURE,
             timeout_s=timeout_s, expects=_all(_slots(1, 1), PEOPLE[2], keywords=NEVER)),
        Plan(f"{profile}-early", profile, speed, n_serial, n_can, seed + 3, arm=early, timeout_s=timeout_s,
             expects=_all(slots, "fixture reports reached early", kind="unharmed")),
    ]


# ------------------------------------------------------------------------------- one board, one record
SWAPPED = ("swapped", "answers")
IDENTITY_ROWS = ["duplicate serial", "empty serial", "overlong serial", "board swapped mid-run (same port)",
                 "board reset mid-run (streams again)", "clock jump back", "clock jump forward",
                 "stuck temperature sensor", "--check during a batch"]
STORE_ROWS = ["database locked mid-batch (12 s)"]
ROUTE_ROWS = ["MES refuses the part", "MES does not answer (refuse)", "MES does not answer (proceed, flag)"]
ROUTE = ("mes route check",)
_MES: list[MesStandIn] = []


def _mes_url(up: bool) -> str:
    """The route check URL of the matrix's MES stand-in (one for the module, started on first use),
    or of one that is down (stopped: its port refuses connections)."""
    if not up:
        down = MesStandIn()
        down.stop()
        return down.url
    if not _MES:
        _MES.append(MesStandIn().start())
    return _MES[0].url


def _holds(**by_slot: str):
    """arm: the MES stand-in holds the serial of the board in each slot, with the reason given."""
    def arm(sim: SimStation) -> None:
        for slot, why in by_slot.items():
            _MES[0].hold(_own_serial(sim, slot), why)
    return arm


def _route_plans(profile: str, speed: float, seed: int) -> list[Plan]:
    """The MES's route check (design 5.4): a held part is stopped before the lamp heats; an MES that
    does not answer stops every part (policy refuse) or lets them be tested, flagged (proceed_and_flag)."""
    def route(up: bool, policy: str) -> dict:
        return {"route_check": {"url": _mes_url(up), "when_unanswered": policy, "timeout_s": 2.0}}

    return [
        Plan("ft-route", profile, speed, 3, 1, seed, arm=_holds(s02="on quality hold: NCR-77"), kw=route(True, "refuse"),
             inject=_refused_before_heat({"s02"}), expects={
            "s02": Expect("MES refuses the part", "faulted", ROUTE + ("quality hold",)),
            "s01": Expect("MES refuses the part", "healthy"), "s03": Expect("MES refuses the part", "healthy"),
            "c01": Expect("MES refuses the part", "healthy"),
        }),
        Plan("ft-route-down", profile, speed, 1, 1, seed + 1, kw=route(False, "refuse"),
             expects=_all(_slots(1, 1), "MES does not answer (refuse)", keywords=("did not answer",))),
        Plan("ft-route-flag", profile, speed, 2, 1, seed + 2, kw=route(False, "proceed_and_flag"),
             expects=_all(_slots(2, 1), "MES does not answer (proceed, flag)", kind="unharmed")),
    ]


def _serials(**by_board):
    """arm: the simulated boards (by index) answer ID with these serials (a cloned image, an
    unprovisioned EEPROM, a garbage field)."""
    def arm(sim: SimStation) -> None:
        for i, serial in by_board.items():
            b = sim.board(int(i[1:]))
            b.identity = dataclasses.replace(b.identity, serial=serial)
    return arm


def _refused_before_heat(slots):
    """The refused slots were stopped before the lamp first switched on (and stay stopped)."""
    async def inject(ctx: Ctx) -> None:
        await ctx.wait(lambda: ctx.sim.world.lamp_on, "the lamp switches on for P hot")
        live = [d.slot for d in ctx.st.batches[ctx.bid].duts if d.slot in slots and d.live]
        assert not live, f"{live} still live when the lamp switched on"
    return inject


def _stream_faults():
    """P hot: s02 resets and streams again by itself, s03's clock jumps 600 s back, s05's temperature
    sensor sticks; N hot: another board answers behind s01's open port, s04's clock jumps 600 s on."""
    async def inject(ctx: Ctx) -> None:
        async with ctx.at_step(1, 10):
            ctx.sim.board(1).reset_streaming()
            ctx.sim.board(2).jump_clock(-600.0)
            ctx.sim.world.stick_temp_sensor(4)
        async with ctx.at_step(2, 10):
            _swap(ctx.sim, 0)
            ctx.sim.board(3).jump_clock(600.0)
    return inject


def _swap(sim: SimStation, i: int) -> None:
    b = sim.board(i)
    b.swap_to(dataclasses.replace(b.identity, serial=f"SWAPPED-{i + 1:02d}"), offset_counts=(800, -800, 400))


def _identity_plans(profile: str, speed: float, seed: int) -> list[Plan]:
    serials = _serials(b0="SIM-CLONE-1", b1="SIM-CLONE-1", b2="", b3="X" * 300)
    return [
        Plan("ft-identity", profile, speed, 5, 1, seed, arm=serials, inject=_refused_before_heat({"s01", "s02", "s03", "s04"}),
             expects={
            "s01": Expect("duplicate serial", "refused", ("s01 and s02 both report sim-clone-1",)),
            "s02": Expect("duplicate serial", "refused", ("s01 and s02 both report sim-clone-1",)),
            "s03": Expect("empty serial", "refused", ("empty serial",)),
            "s04": Expect("overlong serial", "refused", ("300-character serial",)),
            "s05": Expect("duplicate serial", "healthy"), "c01": Expect("duplicate serial", "healthy"),
        }),
        Plan("ft-stream", profile, speed, 6, 1, seed + 1, inject=_stream_faults(), expects={
            "s01": Expect("board swapped mid-run (same port)", "faulted", SWAPPED),
            "s02": Expect("board reset mid-run (streams again)", "faulted", ("restarted", "reset")),
            "s03": Expect("clock jump back", "faulted", ("clock jumped", "back")),
            "s04": Expect("clock jump forward", "faulted", ("clock jumped",)),
            "s05": Expect("stuck temperature sensor", "faulted", ("temperature sensor",)),
            "s06": Expect("board reset mid-run (streams again)", "healthy"),
            "c01": Expect("board reset mid-run (streams again)", "healthy"),
        }),
    ]


def _relay_off_at(moment):
    """moment(ctx) -> a Ctx.held_at context (the plant held there while the relay goes silent)."""
    async def inject(ctx: Ctx) -> None:
        async with moment(ctx):
            ctx.sim.modbus.relay_offline = True
    return inject


def _disk_full_at(moment):
    async def inject(ctx: Ctx) -> None:
        async with moment(ctx):
            await ctx.st.flush_db()
            ctx.filler = await asyncio.to_thread(fill, ctx.mount)
            # The plant goes on slowly until the writer has met the full disk: at x3000 the rest of
            # an sfem-24 batch is 2 s of wall time, which a writer reusing its WAL's free pages can
            # outlast, and the batch would end before the fault is in.
            ctx.sim.set_speed(max(1.0, ctx.plan.speed / 30.0))
        try:
            await ctx.wait(lambda: ctx.st.storage_status().startswith("error"), "the writer reports the full disk", 60)
        finally:
            ctx.sim.set_speed(ctx.plan.speed)
    return inject


def _db_locked_at(moment, hold_s):
    """Another process holds the station database's write lock for hold_s (a backup tool, an
    engineer's sqlite3 shell): the writer journals what it cannot commit, the batch goes on and is
    judged on its data, and once the lock is gone the journal is forwarded before the checks."""
    async def inject(ctx: Ctx) -> None:
        path = str(ctx.st.db.url).removeprefix("sqlite:///")
        async with moment(ctx):
            locker = await asyncio.create_subprocess_exec(sys.executable, "-c", HOLD_LOCK, path, str(hold_s),
                                                          stdout=asyncio.subprocess.PIPE)
            assert (await locker.stdout.readline()).split()[0] == b"LOCKED"
        await locker.wait()
        await ctx.wait(lambda: ctx.st.storage_status() == "ok", "the journal is forwarded after the lock", 60)
    return inject


def _all(slots, row, kind="faulted", keywords=()):
    return {s: Expect(row, kind, keywords) for s in slots}


def _slots(n_serial, n_can):
    return [f"s{i + 1:02d}" for i in range(n_serial)] + [f"c{j + 1:02d}" for j in range(n_can)]


def _na(profile: str, rows: list[str], why: str = "n/a") -> None:
    for r in rows:
        MATRIX.na(r, profile, why)


# ------------------------------------------------------------------------------- fast-thermal-verified
def _verified_plans() -> list[Plan]:
    P = VERIFIED
    plans = []

    # --- the write path: persistent faults (3 tries used up) and transient ones (retried: programmed)
    def arm_write(sim: SimStation) -> None:
        sim.board(0).cal.refuse_writes(99)
        sim.board(1).cal.flip_next_write(99, field_index=2, bit=11)  # every write: stored CRC != written
        sim.board(2).cal.corrupt_readback_crc(99)  # stored right, every read-back reports a damaged CRC
        sim.board(3).cal.drop_replies(99)  # every calibration reply lost
        sim.board(4).cal.flip_next_write(1, field_index=1, bit=17)  # one flip: retried
        sim.board(5).cal.drop_replies(1)  # CAN: one lost commit reply: retried

    plans.append(Plan("ftv-write", P, FAST, 5, 1, 21, arm=arm_write, expects={
        "s01": Expect("write refused", "faulted", ("refused",)),
        "s02": Expect("CRC mismatch on readback", "faulted", ("crc",)),
        "s03": Expect("CRC mismatch on readback", "faulted", ("crc",)),
        "s04": Expect("lost reply", "faulted", ("no_reply", "no reply", "timeout", "timed out")),
        "s05": Expect("transient write fault (retried)", "retried"),
        "c01": Expect("transient write fault (retried)", "retried"),
    }))

    # --- link lost on the first $CALW, power cycle between write and read-back, link lost in the heat
    def arm_link(sim: SimStation) -> None:
        b0 = sim.board(0)

        def lose_link(cmd, args):
            if cmd == "CALW":
                b0.disconnect()  # the port closes as the first $CALW arrives: no reply, ever
                return False
            return True

        board_hook(b0, before=lose_link)
        cycled = []

        def power_cycle(cmd, args):
            if cmd == "CALW" and not cycled:  # right after the write is acked, before the read-back
                cycled.append(1)
                sim.power_cycle(1)

        board_hook(sim.board(1), after=power_cycle)

    async def lose_in_heat(ctx: Ctx) -> None:
        first: list[int] = []

        def s03_streams() -> bool:  # 10 compensated samples of s03 in the heat
            n = ctx.st.samples_taken(ctx.bid).get("s03", 0)
            first[:] = first or [n]
            return n >= first[0] + 10

        async with ctx.at_heat_lamp_on(then=s03_streams):
            ctx.sim.board(2).disconnect()

    # c01's label names another part: stopped at connect, before any data (error, never judged)
    plans.append(Plan("ftv-link", P, FAST, 3, 1, 22, arm=arm_link, inject=lose_in_heat, labels=_labels(c01="WRONG-1"),
                      expects={
        "s01": Expect("link lost", "faulted", LINK),
        "s02": Expect("power cycle write->readback", "judged"),
        "s03": Expect("link lost, verify heat", "faulted", LINK),
        "c01": Expect("label serial mismatch", "faulted", LABEL),
    }))

    plans.append(Plan("ftv-cannot", P, FAST, 1, 1, 23, inject=_cannot_at_first_prompt(), kw=NO_FIXTURE,
                      expects=_all(_slots(1, 1), "operator cannot turn the plate", keywords=CANNOT)))
    rows = ["abort, 1st step", "abort, 2nd step", "abort, 3rd step", "abort, 4th step"]
    for k, row in enumerate(rows):
        plans.append(Plan(f"ftv-abort{k}", P, FAST, 1, 1, 30 + k, inject=_abort_in(k),
                          expects=_all(_slots(1, 1), row, keywords=ABORT)))
    plans.append(Plan("ftv-abort-prog", P, FAST, 1, 1, 34, inject=_abort_in_program(),
                      expects=_all(_slots(1, 1), "abort, program step", keywords=ABORT)))
    plans.append(Plan("ftv-abort-heat", P, FAST, 2, 1, 35, inject=_abort_in_heat(),
                      expects=_all(_slots(2, 1), "abort, verify heat", keywords=ABORT)))
    # the relay dies as the boards are programmed: the heat needs it
    plans.append(Plan("ftv-relay", P, FAST, 2, 1, 36, inject=_relay_off_at(lambda c: c.at_program_step()),
                      expects=_all(_slots(2, 1), "relay failure", keywords=RELAY)))
    # the relay dies while the verification heat runs (lamp on): the heat may still complete in
    # compressed time, but a station that cannot confirm its lamp off has not finished the batch
    plans.append(Plan("ftv-relay-heat", P, FAST, 1, 1, 39, inject=_relay_off_at(lambda c: c.at_heat_lamp_on()),
                      expects=_all(_slots(1, 1), "relay failure, verify heat", keywords=RELAY)))
    plans.append(Plan("ftv-disk", P, FAST, 2, 1, 37, disk_mb=16, inject=_disk_full_at(lambda c: c.at_heat_lamp_on()),
                      expects=_all(_slots(2, 1), "full disk", keywords=DISK)))

    async def kill_in_heat(k: KillCtx) -> None:
        await k.wait_completed(4)  # the program step is done: the boards are programmed
        await wait_for(lambda: k.sim.world.lamp_on, 60, "verification heat lamp on")
        t0 = k.sim.world.time_s
        await wait_for(lambda: k.sim.world.time_s > t0 + 30.0, 60, "30 s of the verification heat")

    plans.append(Plan("ftv-kill", P, FAST, 2, 1, 38, kill=kill_in_heat, timeout_s=200,
                      expects=_all(_slots(2, 1), "SIGKILL + --resume", keywords=KILL)))
    _na(P, ["abort, 45 C block", "abort, last step"], "n/a (sfem-24 rows)")
    plans += _people_plans(P, FAST, 90)

    async def swap_before_programming(ctx: Ctx) -> None:
        async with ctx.at_step(3, 10):  # N ambient, the last step before the program step
            _swap(ctx.sim, 0)

    # the coefficients are never written to another board: the identity is read again before programming
    plans.append(Plan("ftv-swap", P, FAST, 2, 1, 120, inject=swap_before_programming, expects={
        "s01": Expect("board swapped mid-run (same port)", "faulted", SWAPPED),
        "s02": Expect("board swapped mid-run (same port)", "healthy"),
        "c01": Expect("board swapped mid-run (same port)", "healthy"),
    }))
    _na(P, [r for r in IDENTITY_ROWS if r != "board swapped mid-run (same port)"],
        "n/a (connect and link path: the same for every profile, run in fast-thermal)")
    _na(P, ROUTE_ROWS, "n/a (asked at connect, before any step: the same for every profile, run in fast-thermal)")
    _na(P, STORE_ROWS, "n/a (the writer's path: the same for every profile, run in fast-thermal)")
    return plans


# ------------------------------------------------------------------------------- fast-thermal
def _fast_thermal_plans() -> list[Plan]:
    P = "fast-thermal"
    plans = []

    async def lose_in_p_hot(ctx: Ctx) -> None:
        async with ctx.at_step(1, 20):
            ctx.sim.board(0).disconnect()

    # s02's label names another part (stopped at connect); s03's label is its own (runs on)
    plans.append(Plan("ft-link", P, FAST, 3, 1, 41, inject=lose_in_p_hot, labels=_labels(s02="WRONG-2", s03=0),
                      expects={
        "s01": Expect("link lost", "faulted", LINK), "s02": Expect("label serial mismatch", "faulted", LABEL),
        "s03": Expect("link lost", "healthy"), "c01": Expect("link lost", "healthy"),
    }))
    plans.append(Plan("ft-cannot", P, FAST, 1, 1, 42, inject=_cannot_at_first_prompt(), kw=NO_FIXTURE,
                      expects=_all(_slots(1, 1), "operator cannot turn the plate", keywords=CANNOT)))
    for k, row in enumerate(["abort, 1st step", "abort, 2nd step", "abort, 3rd step", "abort, 4th step"]):
        plans.append(Plan(f"ft-abort{k}", P, FAST, 1, 1, 50 + k, inject=_abort_in(k),
                          expects=_all(_slots(1, 1), row, keywords=ABORT)))
    plans.append(Plan("ft-relay", P, FAST, 2, 1, 44, inject=_relay_off_at(lambda c: c.at_step(1, 10)),
                      expects=_all(_slots(2, 1), "relay failure", keywords=RELAY)))
    plans.append(Plan("ft-disk", P, FAST, 2, 1, 45, disk_mb=16, inject=_disk_full_at(lambda c: c.at_step(1, 10)),
                      expects=_all(_slots(2, 1), "full disk", keywords=DISK)))

    async def kill_in_n_hot(k: KillCtx) -> None:
        await k.wait_completed(1)  # P ambient and P hot stored
        await wait_for(lambda: k.sim.world.position == 1 and k.sim.world.lamp_on, 60, "N hot (plate turned)")
        t0 = k.sim.world.time_s
        await wait_for(lambda: k.sim.world.time_s > t0 + 60.0, 60, "60 s of N hot")

    # a resumed run that completes every step may pass (design 8): its pass must be backed
    plans.append(Plan("ft-kill", P, FAST, 2, 1, 46, kill=kill_in_n_hot, timeout_s=200,
                      expects=_all(_slots(2, 1), "SIGKILL + --resume", kind="recovered")))
    _na(P, ["link lost, verify heat", "write refused", "CRC mismatch on readback", "lost reply",
            "transient write fault (retried)", "power cycle write->readback", "abort, program step",
            "abort, verify heat", "relay failure, verify heat"], "n/a (no program/verify)")
    _na(P, ["abort, 45 C block", "abort, last step"], "n/a (sfem-24 rows)")
    plans += _people_plans(P, FAST, 80)
    plans += _identity_plans(P, FAST, 110)
    plans += _route_plans(P, FAST, 120)
    # a second station's `serve --check` on the same config mid-batch is refused and touches nothing
    plans.append(Plan("ft-check", P, FAST, 2, 1, 47, inject=check_during_batch,
                      expects=_all(_slots(2, 1), "--check during a batch", kind="unharmed")))
    # another process holds the database's lock for 12 s mid-batch: the station journals and goes on
    plans.append(Plan("ft-db-locked", P, FAST, 2, 1, 48, inject=_db_locked_at(lambda c: c.at_step(1, 10), 12.0),
                      expects=_all(_slots(2, 1), "database locked mid-batch (12 s)", kind="unharmed")))
    return plans


# ------------------------------------------------------------------------------- sfem-24
def _sfem_plans() -> list[Plan]:
    P = "sfem-24"
    plans = []
    mid = 24 + 6  # a static step of the 45 C block

    async def lose_at_45(ctx: Ctx) -> None:
        async with ctx.at_step(mid, timeout_s=SFEM_STEP_TIMEOUT_S):
            ctx.sim.board(0).disconnect()

    plans.append(Plan("sfem-link", P, SFEM_SPEED, 2, 1, 61, inject=lose_at_45, timeout_s=SFEM_PLAN_TIMEOUT_S, expects={
        "s01": Expect("link lost", "faulted", LINK), "s02": Expect("link lost", "healthy"),
        "c01": Expect("link lost", "healthy"),
    }))
    plans.append(Plan("sfem-cannot", P, SFEM_SPEED, 1, 1, 60, inject=_cannot_at_first_prompt(), kw=NO_FIXTURE,
                      timeout_s=SFEM_PLAN_TIMEOUT_S, expects=_all(_slots(1, 1), "operator cannot turn the plate", keywords=CANNOT)))
    for name, step, row in (("first", 0, "abort, 1st step"), ("45c", mid, "abort, 45 C block"), ("last", 71, "abort, last step")):
        plans.append(Plan(f"sfem-abort-{name}", P, SFEM_SPEED, 1, 1, 62 + step, inject=_abort_in(step, 0, SFEM_STEP_TIMEOUT_S),
                          timeout_s=SFEM_PLAN_TIMEOUT_S,
                          expects=_all(_slots(1, 1), row, keywords=ABORT)))
    # sfem-24 never switches the lamp on, but a relay that does not answer cannot be trusted to
    # hold it off (design 3.3): the batch fails at the third failed read, every DUT names it
    plans.append(Plan("sfem-relay", P, SFEM_SPEED, 1, 1, 66, inject=_relay_off_at(lambda c: c.at_step(mid, 0, SFEM_STEP_TIMEOUT_S)),
                      timeout_s=SFEM_PLAN_TIMEOUT_S, expects=_all(_slots(1, 1), "relay failure", keywords=RELAY)))
    plans.append(Plan("sfem-disk", P, SFEM_SPEED, 1, 1, 67, disk_mb=64, timeout_s=SFEM_PLAN_TIMEOUT_S,
                      inject=_disk_full_at(lambda c: c.at_step(mid, timeout_s=SFEM_STEP_TIMEOUT_S)),
                      expects=_all(_slots(1, 1), "full disk", keywords=DISK)))

    async def kill_at_45(k: KillCtx) -> None:
        await k.wait_completed(mid, timeout_s=SFEM_PLAN_TIMEOUT_S)

    plans.append(Plan("sfem-kill", P, SFEM_SPEED, 1, 1, 68, kill=kill_at_45, timeout_s=SFEM_PLAN_TIMEOUT_S,
                      expects=_all(_slots(1, 1), "SIGKILL + --resume", kind="recovered")))
    _na(P, ["link lost, verify heat", "write refused", "CRC mismatch on readback", "lost reply",
            "transient write fault (retried)", "power cycle write->readback", "abort, program step",
            "abort, verify heat", "relay failure, verify heat"], "n/a (no program/verify)")
    _na(P, ["abort, 2nd step", "abort, 3rd step", "abort, 4th step"], "n/a (see 45 C / last)")
    _na(P, ["label serial mismatch"], "n/a (checked at connect, before any step: one code path for all profiles)")
    _na(P, IDENTITY_ROWS, "n/a (connect and link path: the same for every profile, run in fast-thermal)")
    _na(P, ROUTE_ROWS, "n/a (asked at connect, before any step: the same for every profile, run in fast-thermal)")
    _na(P, STORE_ROWS, "n/a (the writer's path: the same for every profile, run in fast-thermal)")
    # x1000, not x3000: a person's seconds (and a wrong turn's correction within a static step's 600 s
    # timeout) must not vanish into one 150 s tick of the compressed plant
    plans += _people_plans(P, 1000.0, 94, n_serial=1, timeout_s=SFEM_PLAN_TIMEOUT_S)
    return plans


# ------------------------------------------------------------------------------- board_selfcal (issue 42)
def _selfcal_plan() -> Plan:
    """fast-thermal with the option board_selfcal (a site profile under the built-in's name), on
    firmware boards (caps scal) beside a Python board (no calibrator): s01's calibrator is skewed
    through the bridge (its TDB 0.25 mg/C off: the check fails), s02's is restarted ($SCAL,1) as N
    ambient begins so that at the end it has no result ($SCRR answers E: error, never pass)."""
    from station.profiles import BUILTIN_PROFILES

    steps = [{k: v for k, v in st.to_json().items() if k in ("name", "position", "lamp", "chamber_setpoint_c", "require",
                                                             "dwell_s", "settle_s", "timeout_s")}
             for st in BUILTIN_PROFILES["fast-thermal"].steps]
    profiles = {"fast-thermal": {"description": "fast-thermal, the boards' own calibrators compared",
                                 "analysis": "thermal", "steps": steps, "board_selfcal": True}}

    def arm(sim: SimStation) -> None:
        sim.board(0).selfcal_skew(0.25)

    async def restart_s02(ctx: Ctx) -> None:
        async with ctx.at_step(3, 10):  # N ambient: the board's calibrator loses every segment so far
            drv = ctx.st.bank.driver_of("s02")
            assert drv is not None and drv.supports_selfcal
            await drv.set_selfcal(True)

    return Plan("ft-selfcal", "fast-thermal", FAST, 4, 0, 140, arm=arm, inject=restart_s02,
                kw={"profiles": profiles}, timeout_s=150.0, expects={
        "s01": Expect(SELFCAL_ROWS[0], "faulted", ("calibrator disagrees",)),
        "s02": Expect(SELFCAL_ROWS[1], "faulted", ("scrr",)),
        "s03": Expect(SELFCAL_ROWS[0], "healthy"),  # firmware, agrees
        "s04": Expect(SELFCAL_ROWS[0], "healthy"),  # Python board: no calibrator, not applicable
    })


async def _run_firmware_plan(plan: Plan, tmp, firmware: dict[int, str]) -> None:
    """fault_matrix_support's plan run, with these slots' boards running the C firmware (host)."""
    tmp.mkdir(parents=True, exist_ok=True)
    async with SimStation(n_serial=plan.n_serial, n_can=plan.n_can, seed=plan.seed, speed=plan.speed,
                          firmware=firmware) as sim:
        if plan.arm is not None:
            plan.arm(sim)
        async with daemon(sim, tmp, plan.speed, limits=LIMITS, **plan.kw) as st:
            bid = st.start_batch(plan.profile, None, "fault-matrix")
            ctx = Ctx(sim, st, bid, plan)
            sim.pace = ctx.lead_pace
            extra: list[str] = []
            inj = asyncio.create_task(plan.inject(ctx)) if plan.inject is not None else None
            status = await st.wait_batch(bid, timeout_s=plan.timeout_s)
            if inj is not None:
                if not inj.done():
                    inj.cancel()
                    extra.append(f"the fault was never injected: the batch ended first ({status['state']})")
                try:
                    await inj
                except asyncio.CancelledError:
                    pass
                except Exception as exc:  # noqa: BLE001
                    extra.append(f"injection failed: {type(exc).__name__}: {exc}")
            if await coil(sim):
                extra.append("lamp coil still on after the batch")
            await collect_and_check(plan, st, st.db, bid, st.batch_status(bid), extra)


# ------------------------------------------------------------------------------- the tests
@pytest.mark.timeout(420)
async def test_fault_matrix_fast_thermal_verified(tmp_path):
    await run_all(_verified_plans(), tmp_path, PARALLEL)
    _report(VERIFIED)


@pytest.mark.timeout(300)
async def test_fault_matrix_fast_thermal(tmp_path):
    await run_all(_fast_thermal_plans(), tmp_path, PARALLEL)
    _report("fast-thermal")


@pytest.mark.timeout(300)
async def test_fault_matrix_board_selfcal(tmp_path):
    from drivers.sim.firmware_build import missing_tools

    if missing_tools("host"):
        pytest.skip(f"firmware tools missing: {missing_tools('host')}")
    for prof in (VERIFIED, "sfem-24"):
        _na(prof, SELFCAL_ROWS, "n/a (run in fast-thermal)")
    plan = _selfcal_plan()
    await asyncio.wait_for(_run_firmware_plan(plan, tmp_path / plan.name, {0: "host", 1: "host", 2: "host"}),
                           plan.timeout_s + PLAN_SLACK_S)
    _report("fast-thermal")


@pytest.mark.timeout(1500)
async def test_fault_matrix_sfem_24(tmp_path):
    await run_all(_sfem_plans(), tmp_path, SFEM_PARALLEL)
    _report("sfem-24")


assert set(PROFILES) == {"fast-thermal", VERIFIED, "sfem-24"}
