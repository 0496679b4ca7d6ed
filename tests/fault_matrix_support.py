"""Harness of the fault matrix (tests/test_fault_matrix.py, issue "A PASS you can trust").

One `Plan` = one batch of the whole daemon (tests.test_daemon_e2e.daemon: simulated boards on ptys
and an slcan pty, Modbus relay/fixture/chamber on 127.0.0.1, SQLite on disk, the real Station).
Faults are armed on the simulated boards before the batch (write path: drivers/sim/board_nvm.py)
or injected at a moment (`inject(ctx)`: `Ctx.held_at` holds the simulated plant from the tick the
moment is reached until the fault is in, so a loaded machine cannot run the batch past it; or the
board's own command handler), never on a sleep. After the batch every DUT's verdict is read from the four places a
verdict reaches the world:
  status   st.batch_status(bid): slots[i]["decision"] and the "sorting" list
  db       db.repository.batch_detail / run_detail (dut_run.verdict, reason)
  mes      db.repository.results_since (what GET /api/results serves): every record of the run
  webhook  what web.mes_outbox.MesOutbox POSTs to a receiver on 127.0.0.1 (MesReceiver of
           tests/test_web_webhook.py), every record of the run
and checked against the slot's `Expect`:
  faulted  never `pass` in any place (no record that ever said pass), the final verdict's reason
           names the fault (one of `keywords`)
  healthy  in a finished batch: pass/marginal/fail (judged per its data, not error), in every place
  unharmed the batch must finish and the DUT be judged as healthy (a person's mistake, a fixture
           that reports "reached" early: nothing that may fault a good part)
  any      a `pass` anywhere must be backed by the run's evidence (done, result present; program
           and verify: CRC written == read back, compensation on, verified E per axis; sfem: the
           three temperature steps)
Cells collect their problems instead of raising at once, so that the whole matrix is printed
(`pytest -s`) and written to artifacts/fault_matrix.txt even when cells fail.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import time
import traceback
import logging
from collections import Counter
from pathlib import Path
from typing import Any, Awaitable, Callable

from contracts.trace import Trace
from drivers.sim.station_sim import SimStation
from contracts.types import AXES
from tests.test_daemon_e2e import coil, daemon, wait_for  # noqa: F401 (coil: re-exported for the test)

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
PROFILES = ("fast-thermal", "fast-thermal-verified", "sfem-24")
VERIFIED = "fast-thermal-verified"
# A plan that hangs is a broken cell with its own line, not a pytest timeout that loses the matrix:
# every plan gets its batch timeout plus this much for the daemon's start, the end checks and close.
PLAN_SLACK_S = 90.0
MAX_LEAD_S = 200.0  # sample seconds the plant may run ahead of the daemon (Ctx.lead_pace); x3000 ticks are 150 s
MAX_LEAD_HOLD_S = 5.0  # wall seconds one lead hold may last (half the 10 s stall timeout): a daemon that stopped taking samples is not waited for
LIMITS = {"lamp_max_on_s": 9000.0}  # CI: wall x speed overstates the on-time (see test_program_verify_e2e)

ROWS = [
    "label serial mismatch",
    "operator cannot turn the plate",
    "link lost",
    "link lost, verify heat",
    "write refused",
    "CRC mismatch on readback",
    "lost reply",
    "transient write fault (retried)",
    "power cycle write->readback",
    "abort, 1st step",
    "abort, 2nd step",
    "abort, 3rd step",
    "abort, 4th step",
    "abort, program step",
    "abort, verify heat",
    "abort, 45 C block",
    "abort, last step",
    "SIGKILL + --resume",
    "relay failure",
    "relay failure, verify heat",
    "full disk",
    "person: Done before turning the plate",
    "person: wrong turn, then corrected",
    "person: plate never arrives",
    "fixture reports reached early",
    "duplicate serial",
    "empty serial",
    "overlong serial",
    "board swapped mid-run (same port)",
    "board reset mid-run (streams again)",
    "clock jump back",
    "clock jump forward",
    "stuck temperature sensor",
    "--check during a batch",
    "MES refuses the part",
    "MES does not answer (refuse)",
    "MES does not answer (proceed, flag)",
    "database locked mid-batch (12 s)",
    "healthy DUTs (finished batches)",
]


# ----------------------------------------------------------------------------------- the matrix
@dataclasses.dataclass
class Cell:
    counts: Counter = dataclasses.field(default_factory=Counter)  # final status verdicts of the faulted DUTs
    healthy: Counter = dataclasses.field(default_factory=Counter)  # of the batch's healthy DUTs
    problems: list[str] = dataclasses.field(default_factory=list)
    note: str = ""
    ran: bool = False


class Matrix:
    def __init__(self) -> None:
        self.cells: dict[tuple[str, str], Cell] = {}
        self.wall: dict[str, float] = {}
        self.details: list[str] = []  # one line per DUT: every place's verdicts and the reason

    def cell(self, row: str, profile: str) -> Cell:
        assert row in ROWS, row
        return self.cells.setdefault((row, profile), Cell())

    def na(self, row: str, profile: str, why: str = "n/a") -> None:
        c = self.cell(row, profile)
        c.note = why

    def problems(self, profile: str | None = None) -> list[str]:
        out = []
        for (row, prof), c in self.cells.items():
            if profile is None or prof == profile:
                out += [f"[{row} | {prof}] {p}" for p in c.problems]
        return out

    def render(self) -> str:
        def fmt(c: Cell | None) -> str:
            if c is None:
                return "not run"
            if not c.ran:
                return c.note or "n/a"
            parts = []
            if c.counts:
                parts.append(", ".join(f"{k} {n}" for k, n in sorted(c.counts.items())))
            if c.healthy:
                parts.append("healthy: " + ", ".join(f"{k} {n}" for k, n in sorted(c.healthy.items())))
            txt = "; ".join(parts) or "-"
            if c.problems:
                txt += f"  FAIL({len(c.problems)})"
            if c.note:
                txt += f" [{c.note}]"
            return txt

        w0 = max(len(r) for r in ROWS)
        cols = {p: max([len(p)] + [len(fmt(self.cells.get((r, p)))) for r in ROWS]) for p in PROFILES}
        lines = ["FAULT MATRIX (verdicts in the batch status; FAIL(n) = n broken promises, listed below)",
                 " | ".join([" " * w0] + [p.ljust(cols[p]) for p in PROFILES])]
        lines.append("-" * len(lines[-1]))
        for r in ROWS:
            lines.append(" | ".join([r.ljust(w0)] + [fmt(self.cells.get((r, p))).ljust(cols[p]) for p in PROFILES]))
        if self.wall:
            lines.append("wall: " + ", ".join(f"{k} {v:.0f} s" for k, v in self.wall.items()))
        probs = self.problems()
        lines.append(f"\nbroken promises: {len(probs)}")
        lines += ["  " + p for p in probs]
        return "\n".join(lines)

    def write(self) -> str:
        text = self.render()
        out = ROOT / "artifacts"
        out.mkdir(exist_ok=True)
        per_dut = "\n\nper DUT (batch slot [row/expectation] state | status | db | mes records | webhook records | reason):\n"
        (out / "fault_matrix.txt").write_text(text + per_dut + "\n".join(sorted(self.details)) + "\n")
        return text


MATRIX = Matrix()


# ----------------------------------------------------------------------------------- a batch
@dataclasses.dataclass
class Expect:
    row: str
    # faulted | healthy | retried (one transient write fault: programmed on a retry, judged per its data)
    # | recovered (SIGKILL + resume: judged per its data) | judged (a verdict; a pass must be backed)
    # | faulted-if-failed (faulted if the batch failed, else recovered)
    # | unharmed (what happened must harm no DUT: the batch finishes, every DUT pass/marginal/fail in
    #   every place, counted in the row's own cell: a person's mistake, a fixture reporting early)
    # | refused (its identity is refused before any run: error in the status with the reason, no run
    #   stored, no record in the database, the MES feed or the webhook)
    kind: str = "faulted"
    keywords: tuple[str, ...] = ()  # the final verdict's reason names the fault (any of these, lower case)


@dataclasses.dataclass
class Plan:
    name: str
    profile: str
    speed: float
    n_serial: int
    n_can: int
    seed: int
    expects: dict[str, Expect]  # by slot
    arm: Callable[[SimStation], None] | None = None  # before the daemon starts
    inject: Callable[["Ctx"], Awaitable[None]] | None = None  # a task beside the batch
    # the person at the plate (no fixture): runs beside the whole batch, cancelled when it ends
    hands: Callable[["Ctx"], Awaitable[None]] | None = None
    disk_mb: int | None = None  # database on a tmpfs of this size (full-disk cells)
    kill: Callable[["KillCtx"], Awaitable[None]] | None = None  # SIGKILL cell: waits, returns -> SIGKILL
    timeout_s: float = 150.0
    kw: dict = dataclasses.field(default_factory=dict)  # more sim_config arguments
    labels: Callable[[SimStation], dict[str, str]] | None = None  # label serials scanned at the start


@dataclasses.dataclass
class Ctx:
    sim: SimStation
    st: Any
    bid: int
    plan: Plan
    mount: Path | None = None
    filler: Path | None = None
    _lead_since: float | None = None

    def status(self) -> dict:
        return self.st.batch_status(self.bid)

    async def wait(self, pred: Callable[[], Any], what: str, timeout_s: float = 120.0) -> None:
        await wait_for(pred, timeout_s, f"{self.plan.name}: {what}")

    def _seq(self) -> Any:
        return self.st.batches[self.bid]

    def lead_pace(self) -> bool:
        """Default SimStation.pace of a plan: hold the plant while a streaming serial board has sent
        more than MAX_LEAD_S of sample time that the daemon has not yet taken. A live plant at x3000
        on a loaded machine otherwise outruns the daemon by more than a static step's timeout (762 s
        of sample time is 0.25 s of wall time): samples from before a fixture move use up the step's
        timeout before the first one facing the new position arrives, and a healthy DUT is faulted
        for it. The lead is what the board *sent* ahead of the daemon, never the plant's clock ahead
        of the daemon's newest sample: after the program step a board streams again from a plant
        that ran on while it was stopped, and holding the plant for a sample only the plant can
        make held every board silent until the hold gave up (a CI run faulted all three DUTs of a
        plan "no samples for 10.1 s"). A board the plan has cut off (closed, muted) or a DUT no
        longer live is not waited for."""
        seq = self._seq()
        if seq.done.is_set():
            return False
        wall = time.monotonic()
        if self._lead_since is not None and wall - self._lead_since > MAX_LEAD_HOLD_S:
            self._lead_since = None
            log.warning("%s: lead hold gave up after %.1f s at plant %.1f s; unread lead (s) per DUT: %s",
                        self.plan.name, MAX_LEAD_HOLD_S, self.sim.world.time_s,
                        {d.slot: self._unread_lead_s(d) for d in seq.duts})
            return False
        for d in seq.duts:
            if not d.live or not d.slot.startswith("s"):
                continue
            board = self.sim.board(int(d.slot[1:]) - 1)
            lead_s = self._unread_lead_s(d)
            if board.connected and board.streaming and not getattr(board, "muted", False) \
                    and lead_s is not None and lead_s > MAX_LEAD_S:
                self._lead_since = self._lead_since or wall
                return True
        self._lead_since = None
        return False

    def _unread_lead_s(self, d: Any) -> float | None:
        """Sample seconds a serial DUT's board has sent beyond the daemon's newest sample (None:
        not known yet)."""
        if d.last_t is None or not d.slot.startswith("s"):
            return None
        sent_s = getattr(self.sim.board(int(d.slot[1:]) - 1), "sent_until_s", None)
        return None if sent_s is None else round(sent_s - d.last_t, 1)

    @contextlib.asynccontextmanager
    async def held_at(self, moment: Callable[[], bool], what: str, timeout_s: float = 120.0):
        """Wait for `moment` and hold the simulated plant there (SimStation.pace) until the block
        ends: the fault goes in at the moment it is meant for, however loaded the machine. Polling
        the status alone lost that race on a busy CI machine (x3000: a static step lasts 0.2 s of
        wall time; the batch ran past it, or ended, before the poll came round). `moment` runs on
        every plant tick, so it reads the sequencer directly, never the built status dict."""
        hit = asyncio.Event()
        missed: list[BaseException] = []
        seq = self._seq()

        def pace() -> bool:
            if hit.is_set():
                return True
            if missed or seq.done.is_set():
                return False
            try:
                if moment():
                    hit.set()
                    return True
            except AssertionError as exc:  # the moment can no longer come
                missed.append(exc)
            return False

        self.sim.pace = pace
        try:
            loop = asyncio.get_running_loop()
            end = loop.time() + timeout_s
            while not hit.is_set():
                if missed:
                    raise missed[0]
                if seq.done.is_set():
                    st = self.status()
                    raise AssertionError(f"{self.plan.name}: batch ended ({st['state']}: {st['error']}) before {what}")
                if loop.time() > end:
                    raise AssertionError(f"{self.plan.name}: timed out waiting for {what}")
                await asyncio.sleep(0.02)
            yield
        finally:
            self.sim.pace = self.lead_pace

    def at_step(self, index: int, min_samples: int = 0, timeout_s: float = 120.0):
        """held_at: the batch is in step `index` and every live DUT took min_samples in it.
        min_samples=0 holds the plant as the daemon enters the step (before the fixture arrives):
        the one moment that exists at any speed (at x3000 one plant tick carries 150 s of samples,
        more than a whole sfem-24 step, so 'n samples into the step' can fall between two ticks)."""
        base: dict[str, int] = {}
        seq = self._seq()

        def moment() -> bool:
            if seq.step_index > index:
                raise AssertionError(f"{self.plan.name}: the batch ran past step {index} "
                                     f"(now {seq.step_index}) before {min_samples} samples were taken in it")
            if seq.step_index != index:
                return False
            if min_samples == 0:
                return True
            if seq.state != "logging":
                return False
            taken = self.st.samples_taken(self.bid)
            for slot, n in taken.items():
                base.setdefault(slot, n)
            return all(n - base[slot] >= min_samples for slot, n in taken.items())

        return self.held_at(moment, f"step {index} with {min_samples} samples", timeout_s)

    def at_heat_lamp_on(self, then: Callable[[], bool] | None = None):
        """held_at: the verification heat runs (step require 'heat', lamp coil on), and `then`."""
        seq = self._seq()

        def moment() -> bool:
            step = seq.step
            return (step is not None and step.require == "heat" and self.sim.world.lamp_on
                    and (then is None or then()))

        return self.held_at(moment, "verification heat with the lamp on")

    def at_program_step(self):
        seq = self._seq()
        return self.held_at(lambda: seq.step_index == seq.profile.program_step, "program step")


def board_hook(board: Any, before: Callable[[str, tuple], bool] | None = None,
               after: Callable[[str, tuple], None] | None = None) -> None:
    """Wrap a simulated serial board's calibration command handler: before(cmd, args) -> False
    swallows the command (no reply); after(cmd, args) runs once the reply is written."""
    orig = board._calibration

    def hooked(cmd: str, args: tuple) -> None:
        if before is not None and before(cmd, args) is False:
            return
        orig(cmd, args)
        if after is not None:
            after(cmd, args)

    board._calibration = hooked


@contextlib.contextmanager
def tmpfs(path: Path, size_mb: int):
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(path)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        yield None
        return
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(directory: Path) -> Path:
    from tests.test_faults import _fill

    return _fill(directory)


# ----------------------------------------------------------------------------------- reading verdicts
def _v(d: dict | None) -> tuple[str | None, str]:
    if not d:
        return None, ""
    return d.get("verdict"), str(d.get("reason") or "")


def status_verdicts(status: dict) -> dict[str, list[tuple[str | None, str, str]]]:
    """slot -> [(verdict, reason, where)] from slots[i]['decision'] and the sorting list."""
    out: dict[str, list] = {}
    for s in status["slots"]:
        v, r = _v(s.get("decision") or ({"verdict": s["verdict"]} if isinstance(s.get("verdict"), str) else None))
        out.setdefault(s["slot"], []).append((v, r, "status.slots.decision"))
    for e in status.get("sorting") or []:
        out.setdefault(e["slot"], []).append((e.get("verdict"), str(e.get("reason") or ""), "status.sorting"))
    return out


async def deliver_webhook(db: Any, timeout_s: float = 30.0) -> tuple[dict[int, list[dict]], str]:
    """Run the MES outbox worker (web/mes_outbox.py) against a receiver on 127.0.0.1 until every
    feed record is delivered. Returns (run_id -> payloads, problem text or '')."""
    from db.repository import results_since
    from tests.test_web_webhook import MesReceiver
    from web.db_repo import DbRepository
    from web.mes_outbox import MesOutbox, OutboxConfig

    feed = await asyncio.to_thread(results_since, db, 0, 1000)
    want = {(r["run_id"], r["id"]) for r in feed}
    with MesReceiver() as mes:
        cfg = OutboxConfig(url=mes.url, timeout_s=3.0, base_delay_s=0.1, max_delay_s=0.3, poll_s=0.1,
                           station_name="fault-matrix")
        box = MesOutbox(DbRepository(db), cfg)
        await box.start()
        problem = ""
        try:
            loop = asyncio.get_running_loop()
            end = loop.time() + timeout_s
            while True:
                with mes.lock:
                    got = {(p.get("run_id"), p.get("result_id")) for p in mes.records.values()}
                if want <= got:
                    break
                if loop.time() > end:
                    problem = f"webhook: {len(want - got)} of {len(want)} feed records not delivered in {timeout_s:g} s"
                    break
                await asyncio.sleep(0.05)
        finally:
            await box.stop()
        with mes.lock:
            records = list(mes.records.values())
    by_run: dict[int, list[dict]] = {}
    for p in sorted(records, key=lambda p: p.get("result_id") or 0):
        by_run.setdefault(p.get("run_id"), []).append(p)
    return by_run, problem


def pass_evidence_status(s: dict, profile: str) -> list[str]:
    """What is missing for a pass in the batch status slot (empty: the pass is backed)."""
    miss = []
    if s.get("state") != "done":
        miss.append(f"state {s.get('state')!r} ({s.get('fault_reason')})")
    res = s.get("result") or {}
    if profile == "sfem-24":
        # the SFEM record (contracts/sfem_result.py): one step per chamber temperature, self-heating above it
        temps = {sp for t in res.get("steps") or [] for sp in (25, 45, 65) if 0 <= (t.get("temp_c") or -99) - sp < 10}
        if not {25, 45, 65} <= temps:
            miss.append(f"SFEM temperature steps {sorted(temps)} (25/45/65 required)")
    else:
        axes = res.get("axes") or {}
        if not all(a in axes and axes[a].get("tdb_mg_per_c") is not None and axes[a].get("tdsf_ppm_per_c") is not None
                   for a in AXES):
            miss.append("thermal result (TDB/TDSF per axis)")
    if profile == VERIFIED:
        p = s.get("program") or {}
        if not p.get("programmed"):
            miss.append(f"programmed ({p.get('error_kind') or 'no program record'})")
        if not p.get("comp"):
            miss.append("compensation on")
        if not p.get("crc") or p.get("crc") != p.get("readback_crc"):
            miss.append(f"readback CRC {p.get('readback_crc')} == written {p.get('crc')}")
        v = s.get("verification") or {}
        e = v.get("e_after_mg") or {}
        if not all(e.get(a) is not None for a in AXES):
            miss.append("verified drift figures (E after, per axis)")
    return miss


def pass_evidence_db(run: dict | None, profile: str) -> list[str]:
    if run is None:
        return ["no run in the database"]
    miss = []
    if run.get("state") != "done":
        miss.append(f"db state {run.get('state')!r}")
    if profile == VERIFIED:
        pv = run.get("program_verify") or {}
        if not (pv.get("programmed") and pv.get("readback_identical") and pv.get("comp_on")):
            miss.append(f"db program_verify {({k: pv.get(k) for k in ('programmed', 'readback_identical', 'comp_on')})}")
        e = pv.get("e_after_mg") or {}
        if not all(e.get(a) is not None for a in AXES):
            miss.append("db verified E after per axis")
    elif profile == "sfem-24":
        if not run.get("sfem"):
            miss.append("db sfem result")
    elif not run.get("thermal"):
        miss.append("db thermal result")
    return miss


# ----------------------------------------------------------------------------------- judging a batch
async def collect_and_check(plan: Plan, st: Any, db: Any, bid: int, status: dict, extra_problems: list[str]) -> None:
    from db.repository import batch_detail, results_since, run_detail

    await st.flush_db()
    detail = await asyncio.to_thread(batch_detail, db, bid)
    db_runs = {r["slot"]: r for r in (detail or {}).get("runs", [])}
    feed = [r for r in await asyncio.to_thread(results_since, db, 0, 1000) if r.get("batch_id") == bid]
    mes_by_run: dict[int, list[dict]] = {}
    for r in feed:
        mes_by_run.setdefault(r["run_id"], []).append(r)
    try:
        hook_by_run, hook_problem = await deliver_webhook(db)
    except Exception as exc:  # noqa: BLE001 - a broken worker is a finding of its own, not a crash of the matrix
        hook_by_run, hook_problem = {}, f"webhook worker failed: {type(exc).__name__}: {exc}"
    sv = status_verdicts(status)
    finished = status["state"] == "finished"
    batch_probs = list(extra_problems)
    if hook_problem:
        batch_probs.append(hook_problem)

    by_slot = {s["slot"]: s for s in status["slots"]}
    healthy_counts: Counter = Counter()
    per_slot: list[tuple[str, Expect, str | None, list[str]]] = []
    for slot, exp in plan.expects.items():
        if exp.kind == "faulted-if-failed":  # a fault the profile may not need (the relay in sfem-24)
            exp = dataclasses.replace(exp, kind="recovered" if finished else "faulted")
        s = by_slot.get(slot)
        probs: list[str] = []
        if s is None:
            per_slot.append((slot, exp, None, [f"{slot}: not in the batch status"]))
            continue
        run_id = s.get("run_id")
        dbr = db_runs.get(slot)
        places: list[tuple[str, str | None, str]] = []  # (where, verdict, reason) - every record
        places += [(w, v, r) for v, r, w in sv.get(slot, [])]
        if dbr is not None:
            places.append(("db.dut_run", dbr.get("verdict"), str(dbr.get("reason") or "")))
        mes = mes_by_run.get(run_id, [])
        places += [(f"mes#{r['id']}", r.get("verdict"), str(r.get("reason") or "")) for r in mes]
        hook = hook_by_run.get(run_id, [])
        places += [(f"webhook#{p.get('result_id')}", p.get("verdict"), str(p.get("reason") or "")) for p in hook]
        final = {  # the latest record of each place
            "status": sv.get(slot, [(None, "", "")])[0][:2],
            "db": (dbr or {}).get("verdict"), "mes": mes[-1].get("verdict") if mes else None,
            "webhook": hook[-1].get("verdict") if hook else None,
        }
        st_verdict = final["status"][0]
        for where in ("db", "mes", "webhook"):
            if final[where] is None and exp.kind != "refused":
                probs.append(f"{slot}: no verdict in {where} (status says {st_verdict})")
        if st_verdict is None:
            probs.append(f"{slot}: no verdict in the batch status")
        finals = {final["status"][0], final["db"], final["mes"], final["webhook"]} - {None}
        if len(finals) > 1:
            probs.append(f"{slot}: the places disagree on the final verdict: status {st_verdict}, db {final['db']}, "
                         f"mes {final['mes']}, webhook {final['webhook']}")

        passes = [w for w, v, _ in places if v == "pass"]
        if passes:
            miss = pass_evidence_status(s, plan.profile)
            if dbr is not None and run_id is not None:
                full = await asyncio.to_thread(run_detail, db, run_id)
                miss += pass_evidence_db(full, plan.profile)
            if miss and exp.kind != "faulted":
                probs.append(f"{slot}: pass in {', '.join(passes)} without evidence: missing {'; '.join(miss)}")
        kw_text = " / ".join(sorted({r for _, v, r in places if r}))
        if exp.kind == "faulted":
            if passes:
                why = s.get("fault_reason") or ""
                probs.append(f"{slot}: FALSE PASS in {', '.join(passes)} (DUT {s.get('state')}: {why[:160]})")
            finals_reasons = [final["status"][1], (dbr or {}).get("reason") or "",
                              (mes[-1].get("reason") or "") if mes else "", (hook[-1].get("reason") or "") if hook else ""]
            for where, r in zip(("status", "db", "mes", "webhook"), finals_reasons):
                r = str(r or "")
                if exp.keywords and r and not any(k in r.lower() for k in exp.keywords):
                    probs.append(f"{slot}: {where} reason does not name the fault ({'/'.join(exp.keywords)}): {r[:200]!r}")
        elif exp.kind == "judged":  # e.g. a power cycle the write path survives: a verdict, backed if pass
            pass
        elif exp.kind == "refused":  # no run: nothing may carry the board's claimed serial as a record
            why = str(s.get("fault_reason") or "")
            if st_verdict != "error":
                probs.append(f"{slot} (refused): status verdict {st_verdict!r}, expected error")
            if run_id is not None or dbr is not None or mes or hook:
                probs.append(f"{slot} (refused): a run or record exists (run {run_id}, db {dbr is not None}, "
                             f"mes {len(mes)}, webhook {len(hook)}): no record under a serial it cannot own")
            if exp.keywords and not any(k in why.lower() for k in exp.keywords):
                probs.append(f"{slot}: status reason does not name the fault ({'/'.join(exp.keywords)}): {why[:200]!r}")
            claimed = s.get("serial")
            if claimed is not None:
                false = [r for r in feed if r.get("serial") == claimed and r.get("verdict") == "pass"]
                if false:
                    probs.append(f"{slot}: FALSE PASS under its claimed serial {claimed!r} in the MES feed: "
                                 f"{[(r.get('slot'), r.get('run_id')) for r in false]}")
        elif exp.kind in ("healthy", "retried", "recovered", "unharmed"):
            ok = ("pass", "marginal", "fail")
            if exp.kind == "unharmed" and not finished:
                probs.append(f"{slot} (unharmed): the batch {status['state']} ({status.get('error') or '-'}); "
                             f"DUT {s.get('state')}: {(s.get('fault_reason') or '')[:200]}")
            if exp.kind == "retried":  # a single transient write fault: the 3 tries absorb it
                p = s.get("program") or {}
                if not (p.get("programmed") and p.get("comp") and p.get("crc") and p.get("crc") == p.get("readback_crc")
                        and int(p.get("attempts") or 0) >= 2):
                    probs.append(f"{slot} (retried): the retry did not program the board: "
                                 f"{ {k: p.get(k) for k in ('programmed', 'comp', 'crc', 'readback_crc', 'attempts', 'error')} }")
            if finished or exp.kind in ("recovered", "unharmed"):
                for where, v in (("status", st_verdict), ("db", final["db"]), ("mes", final["mes"]),
                                 ("webhook", final["webhook"])):
                    if v not in ok:
                        probs.append(f"{slot} ({exp.kind}): {where} verdict {v!r}, expected {'/'.join(ok)} "
                                     f"(state {s.get('state')}: {(s.get('fault_reason') or kw_text)[:200]})")
            if exp.kind == "healthy":
                healthy_counts[st_verdict or "none"] += 1
        per_slot.append((slot, exp, st_verdict, probs))
        MATRIX.details.append(
            f"{plan.name} {slot} [{exp.row}/{exp.kind}] {s.get('state')} | status {st_verdict} | db {final['db']} | "
            f"mes {[r.get('verdict') for r in mes]} | webhook {[p.get('verdict') for p in hook]} | "
            f"{(final['status'][1] or (dbr or {}).get('reason') or '')[:160]}")

    rows_here = {exp.row for _, exp, _, _ in per_slot if exp.kind != "healthy"}
    for slot, exp, v, probs in per_slot:
        if exp.kind == "healthy":
            c = MATRIX.cell("healthy DUTs (finished batches)", plan.profile) if finished else None
            if c is not None:
                c.ran = True
                c.healthy[v or "none"] += 1
                c.problems += [f"({plan.name}) {p}" for p in probs]
            else:
                for row in rows_here:
                    MATRIX.cell(row, plan.profile).problems += [f"({plan.name}) {p}" for p in probs]
            continue
        c = MATRIX.cell(exp.row, plan.profile)
        c.ran = True
        c.counts[v or "none"] += 1
        c.problems += probs
    for row in rows_here:
        c = MATRIX.cell(row, plan.profile)
        c.healthy.update(healthy_counts)
        c.problems += batch_probs
    if not rows_here and batch_probs:
        MATRIX.cell("healthy DUTs (finished batches)", plan.profile).problems += batch_probs


# ----------------------------------------------------------------------------------- running plans
async def run_plan(plan: Plan, tmp: Path) -> None:
    tmp.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        if plan.kill is not None:
            await asyncio.wait_for(_run_kill_plan(plan, tmp), plan.timeout_s + 2 * PLAN_SLACK_S)
        elif plan.disk_mb is not None:
            with tmpfs(tmp / "disk", plan.disk_mb) as mount:
                if mount is None:
                    for exp in plan.expects.values():
                        MATRIX.cell(exp.row, plan.profile).note = "skipped: cannot mount a tmpfs (needs root)"
                    return
                await asyncio.wait_for(_run_plan(plan, mount, mount), plan.timeout_s + PLAN_SLACK_S)
        else:
            await asyncio.wait_for(_run_plan(plan, tmp, None), plan.timeout_s + PLAN_SLACK_S)
    except Exception as exc:  # noqa: BLE001 - the cell says what broke; the matrix goes on
        tb = traceback.format_exc(limit=6)
        for row in {e.row for e in plan.expects.values() if e.kind != "healthy"} or {"healthy DUTs (finished batches)"}:
            c = MATRIX.cell(row, plan.profile)
            c.ran = True
            what = (f"the plan did not end within its {plan.timeout_s:g} s + {PLAN_SLACK_S:g} s (hung)"
                    if isinstance(exc, TimeoutError) else f"{type(exc).__name__}: {exc}")
            c.problems.append(f"({plan.name}) harness: {what}\n{tb}")
    finally:
        MATRIX.wall[plan.name] = time.monotonic() - t0


async def _run_plan(plan: Plan, tmp: Path, mount: Path | None) -> None:
    async with SimStation(n_serial=plan.n_serial, n_can=plan.n_can, seed=plan.seed, speed=plan.speed) as sim:
        if plan.arm is not None:
            plan.arm(sim)
        async with daemon(sim, tmp, plan.speed, limits=LIMITS, **plan.kw) as st:
            trace = Trace(work_order="WO-FM", labels=plan.labels(sim)) if plan.labels is not None else None
            bid = st.start_batch(plan.profile, None, "fault-matrix", trace)
            ctx = Ctx(sim, st, bid, plan, mount=mount)
            sim.pace = ctx.lead_pace
            extra: list[str] = []
            inj = asyncio.create_task(plan.inject(ctx)) if plan.inject is not None else None
            hands = asyncio.create_task(plan.hands(ctx)) if plan.hands is not None else None
            try:
                status = await st.wait_batch(bid, timeout_s=plan.timeout_s)
            except (asyncio.TimeoutError, TimeoutError):
                late = st.batch_status(bid)
                extra.append(f"the batch did not end within {plan.timeout_s:g} s (state {late['state']}, step "
                             f"{late['step_index']}): aborted by the test")
                st.abort(bid, "fault matrix: batch timed out")
                status = await st.wait_batch(bid, timeout_s=60)
            if hands is not None:
                hands.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await hands
            if inj is not None:
                if not inj.done():
                    inj.cancel()
                    extra.append("the fault was never injected: the batch ended first "
                                 f"({status['state']}: {status['error']})")
                try:
                    await inj
                except asyncio.CancelledError:
                    pass
                except Exception as exc:  # noqa: BLE001
                    extra.append(f"injection failed: {type(exc).__name__}: {exc}")
            if sim.modbus.relay_offline:  # the relay's own host watchdog must switch the lamp off
                try:
                    await wait_for(lambda: not sim.world.lamp_on, 30, "the relay watchdog switches the lamp off")
                except AssertionError as exc:
                    extra.append(str(exc))
                sim.modbus.relay_offline = False
            elif await coil(sim):
                extra.append("lamp coil still on after the batch")
            try:
                if ctx.filler is not None:  # full disk: the operator frees space, the held records go in
                    ctx.filler.unlink()
                    await wait_for(lambda: st.storage_status() == "ok", 60, "database writes recover")
                status = st.batch_status(bid)
                await collect_and_check(plan, st, st.db, bid, status, extra)
            finally:  # whatever broke above, the daemon must be able to store its last events and close
                if ctx.filler is not None and ctx.filler.exists():
                    ctx.filler.unlink()


@dataclasses.dataclass
class KillCtx:
    sim: SimStation
    db_url: str
    plan: Plan

    def batch_row(self) -> tuple[str, int | None] | None:
        from sqlalchemy import select
        from sqlalchemy.exc import OperationalError

        from db.database import Database
        from db.models import Batch

        db = Database(self.db_url)
        try:
            with db.session() as s:
                row = s.execute(select(Batch.state, Batch.last_completed_step).where(Batch.id == 1)).first()
        except OperationalError:
            return None
        finally:
            db.dispose()
        return None if row is None else (row[0], row[1])

    async def wait_completed(self, step: int, timeout_s: float = 150.0) -> None:
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        while True:
            row = await asyncio.to_thread(self.batch_row)
            if row is not None and row[1] is not None and row[1] >= step:
                return
            if loop.time() > end:
                raise AssertionError(f"{self.plan.name}: step {step} never completed (batch row {row})")
            await asyncio.sleep(0.2)


async def _run_kill_plan(plan: Plan, tmp: Path) -> None:
    """`station serve --start-batch` in a subprocess against this process's SimStation (which
    outlives it, like real hardware), SIGKILL at plan.kill's moment, then a daemon in this process
    does what `station serve --resume` does (mark interrupted, judge the killed runs, resume)."""
    from cli.commands.demo import sim_config
    from station.config import parse_config
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station
    from tests.test_daemon_e2e import _to_toml

    db_path = tmp / "station.db"
    db_url = f"sqlite:///{db_path}"
    async with SimStation(n_serial=plan.n_serial, n_can=plan.n_can, seed=plan.seed, speed=plan.speed) as sim:
        if plan.arm is not None:
            plan.arm(sim)
        cfg_dict = sim_config(sim, speed=plan.speed, db_url=db_url, limits=LIMITS, **plan.kw)
        toml = tmp / "station.toml"
        toml.write_text(_to_toml(cfg_dict))
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cli", "serve", "--config", str(toml), "--no-web", "--start-batch", plan.profile,
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE, env=env, cwd=str(ROOT))
        extra: list[str] = []
        try:
            kctx = KillCtx(sim, db_url, plan)
            await plan.kill(kctx)
            if proc.returncode is not None:
                err = (await proc.stderr.read()).decode()[-2000:]
                raise AssertionError(f"the daemon ended before the kill (rc {proc.returncode}): {err}")
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        cfg = parse_config(cfg_dict, "<fault-matrix>")
        db = open_database(cfg.database_url, station=cfg.name)  # as `station serve` opens it
        interrupted = db.mark_interrupted("station restarted")
        st = Station(cfg, db=db)
        try:
            await st.start()
            st.judge_interrupted(interrupted)
            bid = st.resume_batch(interrupted[-1] if interrupted else 1, "fault-matrix --resume")
            status = await st.wait_batch(bid, timeout_s=plan.timeout_s)
            if await coil(sim):
                extra.append("lamp coil still on after the resumed batch")
            await collect_and_check(plan, st, db, bid, status, extra)
        finally:
            await st.close()
            db.dispose()


async def run_all(plans: list[Plan], tmp: Path, parallel: int = 3) -> None:
    sem = asyncio.Semaphore(parallel)

    async def one(p: Plan) -> None:
        async with sem:
            await run_plan(p, tmp / p.name)

    # longest first: whole batches before the aborts, a late abort before an early one
    order = sorted(plans, key=lambda p: ("abort" in p.name, -plans.index(p) if "abort" in p.name else 0))
    await asyncio.gather(*(one(p) for p in order))
