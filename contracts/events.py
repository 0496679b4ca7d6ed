"""Events the daemon publishes: sequencer and calibrators produce them, the database writer, the
web page (server-sent events) and the MES outbox consume them. Data flows one way.

Every event is a frozen dataclass with a `kind` string; `to_json()` gives the SSE/REST payload.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from contracts.json_safe import JsonDict
from contracts.run_records import ProgramRecord, ThermalReport
from contracts.sfem_result import SfemResult
from contracts.types import SampleBlock, Segment

if TYPE_CHECKING:
    from _typeshed import DataclassInstance


def _fields_json(record: DataclassInstance) -> JsonDict:
    return {f.name: _jsonable(getattr(record, f.name)) for f in dataclasses.fields(record)}


def _jsonable(value: object) -> object:
    """A JSON value of what an event carries: a typed record through its own to_json(), a
    dataclass field by field, lists/tuples, dicts and numpy arrays (tolist) item by item."""
    to_json = getattr(value, "to_json", None)
    if callable(to_json) and not isinstance(value, type):
        return _jsonable(to_json())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _fields_json(value)
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


@dataclass(frozen=True)
class Event:
    batch_id: int
    wall_time: float = field(default_factory=time.time, kw_only=True)

    @property
    def kind(self) -> str:
        return type(self).__name__

    def to_json(self) -> JsonDict:
        data = _fields_json(self)
        data["kind"] = self.kind
        return data


@dataclass(frozen=True)
class BatchStateChanged(Event):
    state: str  # created, running, paused, finished, aborted, failed, interrupted
    reason: str = ""


@dataclass(frozen=True)
class StepStarted(Event):
    step_index: int
    step_name: str
    position: int | None
    lamp_on: bool
    chamber_setpoint_c: float | None


@dataclass(frozen=True)
class StepCompleted(Event):
    """A profile step ended; windows = each DUT's board-time span of the step (slot -> (from, to)).

    Stored as the batch's last completed step: a batch interrupted later resumes after it."""

    step_index: int
    windows: dict[str, tuple[float, float]] = field(default_factory=dict)


@dataclass(frozen=True)
class SlotStateChanged(Event):
    slot: str
    serial: str | None
    state: str  # connecting, identified, running, done, faulted
    fault_reason: str = ""


@dataclass(frozen=True)
class SamplesReceived(Event):
    """A block of a DUT's samples; the writer stores the full stream. Not sent over SSE."""

    slot: str
    serial: str
    step_index: int
    block: SampleBlock
    lamp_on: bool = False
    position: int | None = None


@dataclass(frozen=True)
class SegmentLogged(Event):
    slot: str
    serial: str
    step_index: int
    segment: Segment


@dataclass(frozen=True)
class DutResult(Event):
    """Results of one DUT run's analysis: thermal (streaming and offline) and/or SFEM, typed
    (contracts/run_records.py, contracts/sfem_result.py); their JSON is made at the edges.
    No verdict: the run is judged once, at its end (DutVerdict)."""

    slot: str
    serial: str
    thermal: ThermalReport | None = None
    sfem: SfemResult | None = None


@dataclass(frozen=True)
class DutVerdict(Event):
    """THE decision on a DUT run, final: published once when the run ends (station/decisions/moment.py);
    the database numbers it for the MES (result_seq) and the webhook sends it. A later one for the
    same run (a resumed batch, a re-judge) is a new record that supersedes the earlier."""

    slot: str
    serial: str | None
    verdict: JsonDict


@dataclass(frozen=True)
class DutProgrammed(Event):
    """Program and verify, part 1: the coefficients written to a DUT, read back and compensation
    switched on (program.programmed), or why not (program.error_kind, program.error)."""

    slot: str
    serial: str
    program: ProgramRecord


@dataclass(frozen=True)
class DutVerified(Event):
    """Program and verify, part 2: the verified drift error E of the compensated output
    (station.science.verify.VerificationResult.to_json())."""

    slot: str
    serial: str
    verification: JsonDict


@dataclass(frozen=True)
class PromptRaised(Event):
    prompt_id: int
    text: str
    position: int | None = None


@dataclass(frozen=True)
class PromptAnswered(Event):
    prompt_id: int
    answer: str


@dataclass(frozen=True)
class LampChanged(Event):
    on: bool
    reason: str


@dataclass(frozen=True)
class Alarm(Event):
    text: str
    severity: str = "error"


class EventBus:
    """In-process fan-out: each subscriber gets a queue of its own.

    A lossy subscriber (drop=True, the default: the web page's server-sent events, the MES outbox,
    a stalled browser) gets a queue bounded by `maxsize` and loses its oldest events rather than
    stalling the daemon. A lossless subscriber (drop=False: the database writer's forwarder,
    station/daemon/storage.py) gets an unbounded queue (`maxsize` is not used): `publish` never
    blocks and never drops, and nothing here bounds its memory. That subscriber must drain its
    queue promptly; the database writer does, and bounds its own memory by spilling what the
    database cannot take to its journal (db/writer.py).
    """

    def __init__(self) -> None:
        self._subscribers: list[tuple[asyncio.Queue[Event], bool]] = []

    def subscribe(self, maxsize: int = 10000, drop: bool = True) -> asyncio.Queue[Event]:
        """A new queue of every event published from now on; maxsize bounds it only when drop."""
        q: asyncio.Queue[Event] = asyncio.Queue(maxsize=maxsize if drop else 0)
        self._subscribers.append((q, drop))
        return q

    def unsubscribe(self, q: asyncio.Queue[Event]) -> None:
        self._subscribers = [(s, d) for s, d in self._subscribers if s is not q]

    def publish(self, event: Event) -> None:
        for q, drop in self._subscribers:
            if drop and q.full():  # lossy: make room by dropping the oldest event
                try:
                    q.get_nowait()
                except asyncio.QueueEmpty:
                    pass
            q.put_nowait(event)  # a lossless queue is unbounded: never full
