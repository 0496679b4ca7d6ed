"""IPC-CFX (IPC-2591) over AMQP 1.0 against the real broker on 127.0.0.1 (docs/cfx.md).

A simulated station runs a short fast-thermal batch with [cfx] enabled; an independent AMQP 1.0
consumer (a proton receiver written here, not the station's sender) reads what the broker got and
checks each message against the IPC-2591 shapes written below from the standard's message classes
(the CFX SDK's CFXEnvelope, WorkStarted, WorkCompleted, UnitsTested, StationStateChanged,
CalibrationPerformed), not from the station's builder. The second test stops the broker mid-batch
and starts it again: every message still arrives, once, in the order the outbox queued it.

The broker is the RabbitMQ on this machine with its AMQP 1.0 plugin, which the session fixture
enables (`rabbitmq-plugins enable rabbitmq_amqp1_0`, idempotent; needs root, as CI runs here).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import threading
import time
import uuid
from contextlib import asynccontextmanager
from datetime import datetime

import pytest

proton = pytest.importorskip("proton")
from proton.reactor import DurableSubscription  # noqa: E402
from proton.utils import BlockingConnection  # noqa: E402

from cli.commands.demo import sim_config  # noqa: E402
from db import queries_cfx as Q  # noqa: E402
from db.models import Outbox  # noqa: E402
from drivers.sim.station_sim import SimStation  # noqa: E402
from station.config import parse_config  # noqa: E402
from station.daemon.storage import open_database  # noqa: E402
from station.daemon.supervisor import Station  # noqa: E402

BROKER = "amqp://guest:guest@127.0.0.1:5672"
SPEED = 300.0
N_DUTS = 3

# ------------------------------------------------------------------ the broker


def _amqp10_up(timeout_s: float) -> str:
    """'' once an AMQP 1.0 connection opens, else the last error."""
    end, err = time.monotonic() + timeout_s, "not tried"
    while time.monotonic() < end:
        try:
            BlockingConnection(BROKER, timeout=3).close()
            return ""
        except Exception as exc:  # noqa: BLE001 - retried until the plugin listens
            err = f"{type(exc).__name__}: {exc}"
            time.sleep(0.5)
    return err


@pytest.fixture(scope="session")
def amqp10_broker() -> str:
    """The RabbitMQ on 127.0.0.1 with rabbitmq_amqp1_0 enabled (idempotent)."""
    if shutil.which("rabbitmq-plugins") is None or shutil.which("rabbitmqctl") is None:
        pytest.skip("RabbitMQ's rabbitmq-plugins/rabbitmqctl are not installed: no AMQP 1.0 broker to test against")
    r = subprocess.run(["rabbitmq-plugins", "enable", "rabbitmq_amqp1_0"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"rabbitmq-plugins enable rabbitmq_amqp1_0 failed: {r.stdout}{r.stderr}"
    err = _amqp10_up(60)
    assert not err, f"no AMQP 1.0 listener on 127.0.0.1:5672 after enabling the plugin: {err}"
    return BROKER


def rabbitmqctl(*args: str) -> None:
    r = subprocess.run(["rabbitmqctl", *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"rabbitmqctl {' '.join(args)}: {r.stdout}{r.stderr}"


# ------------------------------------------------------------------ the independent consumer


def _decode(msg) -> dict:
    body = msg.body
    raw = bytes(body) if isinstance(body, (bytes, bytearray, memoryview)) else str(body).encode("utf-8")
    return {"subject": msg.subject, "content_type": msg.content_type, "id": msg.id, "durable": msg.durable,
            "properties": dict(msg.properties or {}), "envelope": json.loads(raw.decode("utf-8"))}


class Collector(threading.Thread):
    """A proton receiver on its own thread (the station's loop must not block): every message of
    `address`, accepted, in arrival order."""

    def __init__(self, address: str, options=None) -> None:
        super().__init__(daemon=True)
        self.address, self.options = address, options
        self.got: list[dict] = []
        self.ready = threading.Event()
        self.halt = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            conn = BlockingConnection(BROKER, timeout=10)
            rcv = conn.create_receiver(self.address, credit=200, options=self.options)
            self.ready.set()
            while not self.halt.is_set():
                try:
                    msg = rcv.receive(timeout=0.3)
                except proton.Timeout:
                    continue
                self.got.append(_decode(msg))
                rcv.accept()
            conn.close()
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc
            self.ready.set()


def drain_queue(queue: str, expect_at_least: int, timeout_s: float = 20.0) -> list[dict]:
    """Every message in a durable queue (/queue/NAME), read after the fact, accepted."""
    conn = BlockingConnection(BROKER, timeout=10)
    try:
        rcv = conn.create_receiver(f"/queue/{queue}", credit=200, options=DurableSubscription())
        out: list[dict] = []
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                msg = rcv.receive(timeout=2.0 if len(out) >= expect_at_least else 0.5)
            except proton.Timeout:
                if len(out) >= expect_at_least:
                    break
                continue
            out.append(_decode(msg))
            rcv.accept()
        return out
    finally:
        conn.close()


# ------------------------------------------------------------------ IPC-2591 shapes (from the standard)

UUID_RE = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")
TIMESPAN_RE = re.compile(r"^(\d+\.)?\d{2}:\d{2}:\d{2}(\.\d{1,7})?$")  # .NET TimeSpan


def is_uuid(v) -> bool:
    return isinstance(v, str) and bool(UUID_RE.match(v))


def is_iso(v) -> bool:
    """ISO 8601 with a time zone (CFX: a TimeStamp must include it)."""
    if not isinstance(v, str):
        return False
    try:
        return datetime.fromisoformat(v).tzinfo is not None
    except ValueError:
        return False


def opt(check):
    return lambda v: v is None or check(v)


def is_str(v) -> bool:
    return isinstance(v, str)


def is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def is_bool(v) -> bool:
    return isinstance(v, bool)


def one_of(*values):
    return lambda v: v in values


def list_of(shape):
    return lambda v: isinstance(v, list) and all(conforms(x, shape) == [] for x in v)


def obj(shape):
    return lambda v: isinstance(v, dict) and conforms(v, shape) == []


ENVELOPE = {"MessageName": is_str, "Version": is_str, "TimeStamp": is_iso, "UniqueID": is_uuid, "Source": is_str,
            "Target": opt(is_str), "RequestID": opt(is_str), "MessageBody": lambda v: isinstance(v, dict)}
UNIT_POSITION = {"UnitIdentifier": is_str, "PositionNumber": is_int, "PositionName": opt(is_str), "X": is_num,
                 "Y": is_num, "Rotation": is_num, "FlipX": is_bool, "FlipY": is_bool,
                 "Status": one_of("Pass", "Fail", "Scrap", "Skip")}
WORK_ORDER = {"WorkOrderId": is_str, "Batch": opt(is_str)}
WORK_STARTED = {"TransactionID": is_uuid, "PrimaryIdentifier": opt(is_str), "HermesIdentifier": opt(is_str),
                "Lane": opt(is_int), "UnitCount": is_int, "Units": list_of(UNIT_POSITION), "RecipeName": opt(is_str),
                "WorkOrderIdentifier": opt(obj(WORK_ORDER))}
WORK_COMPLETED = {"TransactionID": is_uuid, "Result": one_of("Completed", "Failed", "Aborted", "Skipped"),
                  "PrimaryIdentifier": opt(is_str), "HermesIdentifier": opt(is_str), "UnitCount": is_int,
                  "Units": list_of(UNIT_POSITION)}
TEST_RESULT = one_of("Passed", "Failed", "Error", "Aborted", "Skipped")
TEMPERATURE = {"$type": one_of("CFX.Structures.Temperature, CFX"), "StartTime": opt(is_iso), "EndTime": opt(is_iso),
               "MeanValue": is_num, "MedianValue": is_num, "MaxValue": is_num, "MinValue": is_num}
NUMERIC_VALUE = {"Value": is_num, "ValueUnits": is_str, "ExpectedValue": opt(is_num),
                 "MinimumAcceptableValue": opt(is_num), "MaximumAcceptableValue": opt(is_num)}
MEASUREMENT = {"$type": one_of("CFX.Structures.NumericMeasurement, CFX"), "UniqueIdentifier": is_str,
               "MeasurementName": is_str, "TimeRecorded": opt(is_iso), "Sequence": is_int, "Result": TEST_RESULT,
               "MeasuredValue": obj(NUMERIC_VALUE)}
TEST = {"UniqueIdentifier": is_str, "TestName": is_str, "TestStartTime": opt(is_iso), "TestEndTime": opt(is_iso),
        "TestConditions": list_of(TEMPERATURE), "Result": TEST_RESULT, "Error": opt(is_str),
        "SymptomsFound": lambda v: isinstance(v, list), "DefectsFound": lambda v: isinstance(v, list),
        "Measurements": list_of(MEASUREMENT)}
TESTED_UNIT = {"UnitIdentifier": is_str, "UnitPositionNumber": opt(is_int), "OverallResult": TEST_RESULT,
               "Tests": list_of(TEST)}
OPERATOR = {"OperatorIdentifier": opt(is_str), "ActorType": one_of("Human", "Robot", "RemoteSystem"),
            "LoginName": opt(is_str)}
UNITS_TESTED = {"TransactionId": is_uuid, "TestMethod": one_of("Human", "Automated", "ICT", "FPT", "FCT", "BST"),
                "Tester": opt(obj(OPERATOR)), "RecipeName": opt(is_str),
                "SamplingInformation": obj({"SamplingMethod": is_str}), "TestedUnits": list_of(TESTED_UNIT)}
RESOURCE_STATES = {1000, 1100, 1200, 1300, 1400, 2000, 2100, 2200, 2201, 2202, 2300, 2400, 2500, 3000, 3100, 3200,
                   4000, 4100, 4200, 4300, 4400, 4500, 4600, 4700, 5000, 5100, 5200, 5300, 5400, 5500, 5600,
                   6000, 6100, 6200}
STATION_STATE_CHANGED = {"OldState": one_of(*RESOURCE_STATES), "NewState": one_of(*RESOURCE_STATES),
                         "OldStateDuration": opt(lambda v: isinstance(v, str) and bool(TIMESPAN_RE.match(v))),
                         "RelatedFault": opt(lambda v: isinstance(v, dict))}
CALIBRATION = {"CalibrationCode": is_str, "CalibrationType": is_str, "Comments": opt(is_str),
               "Status": opt(one_of("Unknown", "Failed", "Ok")), "CalibrationTime": opt(is_iso),
               "Measurements": lambda v: isinstance(v, list)}
CALIBRATION_PERFORMED = {"TransactionID": opt(is_uuid), "Calibration": obj(CALIBRATION)}
BODIES = {
    "CFX.Production.WorkStarted": WORK_STARTED,
    "CFX.Production.WorkCompleted": WORK_COMPLETED,
    "CFX.Production.TestAndInspection.UnitsTested": UNITS_TESTED,
    "CFX.ResourcePerformance.StationStateChanged": STATION_STATE_CHANGED,
    "CFX.ResourcePerformance.CalibrationPerformed": CALIBRATION_PERFORMED,
}


def conforms(value: dict, shape: dict) -> list[str]:
    """The keys of `shape` that `value` lacks or holds with a wrong type."""
    return [f"{k}={value.get(k, '<missing>')!r}" for k, check in shape.items() if k not in value or not check(value[k])]


def check_message(m: dict, handle: str) -> dict:
    """One received AMQP message is a CFX envelope of the station, with a conforming body."""
    env = m["envelope"]
    assert conforms(env, ENVELOPE) == [], env
    name = env["MessageName"]
    assert name in BODIES, name
    assert m["subject"] == name  # the topic convention: subject (routing key) = MessageName
    assert m["content_type"].startswith("application/json")
    assert m["id"] == env["UniqueID"] and m["durable"] is True
    assert m["properties"].get("cfx-message") == name and m["properties"].get("cfx-handle") == handle
    assert env["Source"] == handle and env["Version"].startswith("2.")
    bad = conforms(env["MessageBody"], BODIES[name])
    assert bad == [], (name, bad)
    return env


def expected_names(n_units: int) -> list[str]:
    return (["CFX.ResourcePerformance.CalibrationPerformed", "CFX.ResourcePerformance.StationStateChanged",
             "CFX.Production.WorkStarted"] + ["CFX.Production.TestAndInspection.UnitsTested"] * n_units
            + ["CFX.Production.WorkCompleted", "CFX.ResourcePerformance.StationStateChanged"])


# ------------------------------------------------------------------ the station


@asynccontextmanager
async def cfx_station(sim, tmp_path, handle: str, address: str):
    cfg_dict = sim_config(sim, speed=SPEED, db_url=f"sqlite:///{tmp_path / 'station.db'}", chamber=False, fixture=True)
    cfg_dict["name"] = f"cfx-test-{uuid.uuid4().hex[:6]}"
    cfg_dict["certificate"] = {"reference_thermometer": "PT100 ref, certificate DKD-K-12345 2026-03, due 2027-03"}
    cfg_dict["cfx"] = {"enabled": True, "broker_url": BROKER, "address": address, "handle": handle, "poll_s": 0.3,
                       "base_delay_s": 0.3, "max_delay_s": 2.0, "timeout_s": 5.0, "complete_after_s": 10.0}
    cfg = parse_config(cfg_dict, "<test>")
    db = open_database(cfg.database_url, station=cfg.name)
    st = Station(cfg, db=db)
    await st.start()
    try:
        yield st
    finally:
        await st.close()
        db.dispose()


async def wait_until(pred, timeout_s: float, what: str) -> None:
    import asyncio

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if await asyncio.to_thread(pred):
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def outbox_order(db, station: str) -> list[tuple[str, str]]:
    """(UniqueID, MessageName) of the station's CFX outbox rows, in id (queue) order."""
    with db.session() as s:
        rows = s.query(Outbox).filter(Outbox.topic == Q.CFX_TOPIC,
                                      Outbox.idempotency_key.startswith(Q.cfx_prefix(station))).order_by(Outbox.id).all()
        return [(r.payload["UniqueID"], r.payload["MessageName"]) for r in rows]


def check_batch(envs: list[dict], n_units: int, slots: list[str]) -> None:
    names = [e["MessageName"] for e in envs]
    assert names == expected_names(n_units), names
    bodies = [e["MessageBody"] for e in envs]
    tx = bodies[2]["TransactionID"]
    assert bodies[0]["TransactionID"] == tx and bodies[-2]["TransactionID"] == tx
    assert all(b["TransactionId"] == tx for b in bodies[3:3 + n_units])
    assert bodies[1]["OldState"] == 2200 and bodies[1]["NewState"] == 1100  # idle -> regular work
    assert bodies[-1]["OldState"] == 1100 and bodies[-1]["NewState"] == 2200 and bodies[-1]["OldStateDuration"]
    assert bodies[-2]["Result"] == "Completed" and bodies[-2]["UnitCount"] == n_units
    assert bodies[0]["Calibration"]["Status"] == "Ok" and "DKD-K-12345" in bodies[0]["Calibration"]["Comments"]
    positions = set()
    for b in bodies[3:3 + n_units]:
        (unit,) = b["TestedUnits"]
        assert unit["OverallResult"] in ("Passed", "Failed")  # a fast-thermal of healthy boards is judged
        positions.add(unit["UnitPositionNumber"])
        (test,) = unit["Tests"]
        (temp,) = test["TestConditions"]
        assert temp["MinValue"] <= temp["MeanValue"] <= temp["MaxValue"] and temp["MaxValue"] - temp["MinValue"] > 5.0
        assert {m["MeasurementName"] for m in test["Measurements"]} >= {"TDB_X", "TDB_Y", "TDB_Z"}
    assert positions == {slots.index(s) + 1 for s in slots[:n_units]}
    stamps = [datetime.fromisoformat(e["TimeStamp"]) for e in envs]
    assert stamps == sorted(stamps), stamps  # the events' own times, in order
    assert len({e["UniqueID"] for e in envs}) == len(envs)


# ------------------------------------------------------------------ tests


@pytest.mark.timeout(120)
async def test_batch_messages_reach_an_independent_consumer(amqp10_broker, tmp_path):
    """A batch's CFX messages, published to the topic exchange, read by a consumer bound to CFX.#."""
    handle = f"//pytest/ThermalCal/{uuid.uuid4().hex[:8]}"
    col = Collector("/exchange/amq.topic/CFX.#")
    col.start()
    assert col.ready.wait(15) and col.error is None, col.error
    try:
        async with SimStation(n_serial=N_DUTS, n_can=0, seed=21, speed=SPEED) as sim:
            async with cfx_station(sim, tmp_path, handle, "/exchange/amq.topic") as st:
                bid = st.start_batch("fast-thermal", None, "pytest operator")
                status = await st.wait_batch(bid, timeout_s=60)
                assert status["state"] == "finished", status.get("error")
                n = len(expected_names(N_DUTS))
                await wait_until(lambda: len([m for m in col.got if m["envelope"].get("Source") == handle]) >= n,
                                 20, "the batch's CFX messages at the consumer")
                order = outbox_order(st.db, st.config.name)
                slots = [s.name for s in st.config.slots]
        mine = [m for m in col.got if m["envelope"].get("Source") == handle]
        envs = [check_message(m, handle) for m in mine]
        check_batch(envs, N_DUTS, slots)
        assert [(e["UniqueID"], e["MessageName"]) for e in envs] == order  # once each, in the outbox's order
    finally:
        col.halt.set()
        col.join(10)


@pytest.mark.timeout(180)
async def test_broker_stopped_mid_batch_every_message_once_in_order(amqp10_broker, tmp_path):
    """The broker stops while the batch runs (after its first messages went out) and starts again
    after the batch ended: the outbox keeps the rest, retries, and the durable queue ends up with
    every message once, in queue order."""
    handle = f"//pytest/ThermalCal/{uuid.uuid4().hex[:8]}"
    queue = f"cfx-test-{uuid.uuid4().hex[:8]}"
    # the durable queue exists before the station sends (declared by a durable subscription)
    BlockingConnection(BROKER, timeout=10).create_receiver(f"/queue/{queue}", options=DurableSubscription()).connection.close()
    stopped = False
    try:
        async with SimStation(n_serial=N_DUTS, n_can=0, seed=22, speed=SPEED) as sim:
            async with cfx_station(sim, tmp_path, handle, f"/queue/{queue}") as st:
                name = st.config.name
                bid = st.start_batch("fast-thermal", None, "pytest operator")
                await wait_until(lambda: Q.cfx_counts(st.db, name)[0] >= 3, 20, "the batch's first CFX messages sent")
                assert st.batch_status(bid)["state"] not in ("finished", "failed", "aborted")
                rabbitmqctl("stop_app")
                stopped = True
                status = await st.wait_batch(bid, timeout_s=90)
                assert status["state"] == "finished", status.get("error")
                await st.flush_db()
                n = len(expected_names(N_DUTS))
                await wait_until(lambda: sum(Q.cfx_counts(st.db, name)) >= n, 30, "every CFX message queued")
                assert Q.cfx_counts(st.db, name)[1] > 0  # the rest waits in the outbox
                # a send in flight when the broker stopped fails only at its settlement timeout (timeout_s):
                # on a loaded machine that can come after the batch's last message was queued
                await wait_until(lambda: st.cfx is not None and st.cfx.failures > 0, 60,
                                 "a send failed while the broker was down")
                rabbitmqctl("start_app")
                stopped = False
                assert _amqp10_up(60) == ""
                await wait_until(lambda: Q.cfx_counts(st.db, name) == (n, 0), 60, "the outbox drained after the restart")
                order = outbox_order(st.db, name)
                slots = [s.name for s in st.config.slots]
        got = drain_queue(queue, expect_at_least=n)
        envs = [check_message(m, handle) for m in got]
        ids = [e["UniqueID"] for e in envs]
        assert len(ids) == len(set(ids)), "a message arrived twice"
        assert [(e["UniqueID"], e["MessageName"]) for e in envs] == order  # every one, once, in order
        check_batch(envs, N_DUTS, slots)
    finally:
        if stopped:
            rabbitmqctl("start_app")
            _amqp10_up(60)
        subprocess.run(["rabbitmqctl", "delete_queue", queue], capture_output=True, timeout=60)


# ------------------------------------------------------------------ without a broker


def _facts(state: str, reason: str = ""):
    from datetime import timedelta, timezone

    t0 = datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone.utc)
    runs = (Q.RunFacts(run_id=7, slot="s02", serial="SN2", state="done", verdict="fail", route_check=None, result_seq=4,
                       started_at=t0, ended_at=t0 + timedelta(seconds=90)),
            Q.RunFacts(run_id=6, slot="s01", serial="SN1", state="done", verdict=None, route_check="refused",
                       result_seq=3, started_at=t0, ended_at=t0))
    return Q.BatchFacts(batch_id=5, station="st", profile="fast-thermal", operator="", state=state, reason=reason,
                        created_at=t0, ended_at=t0 + timedelta(days=1, seconds=3725.5), work_order="WO-1", lot="L7",
                        slots=("s01", "s02"), thermometer=None, thermometer_calibration="", runs=runs)


def test_builder_maps_ends_faults_and_timespans():
    """The pure builder (no broker): a failed batch puts the station down with the reason as its
    fault, a refused part is skipped, durations are .NET TimeSpans, ids are stable."""
    from station.cfx import messages as M

    b = _facts("failed", "lamp relay did not answer")
    end = M.station_state_changed(b, "//h", starting=False).envelope
    assert conforms(end, ENVELOPE) == [] and conforms(end["MessageBody"], STATION_STATE_CHANGED) == []
    body = end["MessageBody"]
    assert body["NewState"] == 5000 and body["OldStateDuration"] == "1.01:02:05.5000000"
    assert body["RelatedFault"]["Description"] == "lamp relay did not answer"
    done = M.work_completed(b, "//h").envelope["MessageBody"]
    assert conforms(done, WORK_COMPLETED) == [] and done["Result"] == "Failed"
    assert [(u["PositionNumber"], u["Status"]) for u in done["Units"]] == [(1, "Skip"), (2, "Fail")]
    started = M.work_started(b, "//h").envelope
    assert started["MessageBody"]["WorkOrderIdentifier"] == {"WorkOrderId": "WO-1", "Batch": "L7"}
    assert started == M.work_started(b, "//h").envelope  # rebuilt: the same message, the same UniqueID
    assert M.calibration_performed(b, "//h") is None  # no reference thermometer in the batch's config
    assert M.work_completed(_facts("interrupted"), "//h").envelope["MessageBody"]["Result"] == "Aborted"
    assert M.test_result("marginal", None) == "Failed" and M.test_result("error", None) == "Error"
    assert M.test_result(None, "refused") == "Skipped" and M.timespan(59.0) == "00:00:59"


def test_webhook_and_cfx_share_the_outbox_but_not_their_messages(tmp_path):
    """The MES webhook's pending list never holds a CFX row, and the CFX head only this station's."""
    from db import Database
    from db import repository as repo

    db = Database(f"sqlite:///{tmp_path / 'x.db'}", station="a")
    db.upgrade()
    repo.outbox_enqueue(db, "run-1-result-1", {"serial": "SN1"})
    repo.outbox_enqueue(db, "cfx/a/work-started/1", {"MessageName": "x"}, topic=Q.CFX_TOPIC)
    repo.outbox_enqueue(db, "cfx/b/work-started/1", {"MessageName": "y"}, topic=Q.CFX_TOPIC)
    assert [e["idempotency_key"] for e in repo.outbox_pending(db)] == ["run-1-result-1"]
    assert [e["idempotency_key"] for e in Q.cfx_head(db, "a")] == ["cfx/a/work-started/1"]
    assert Q.cfx_counts(db, "b") == (0, 1)
    db.dispose()
