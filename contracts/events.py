"""Events the daemon publishes: sequencer and calibrators produce them, the database writer, the
web page (server-sent events) and the MES outbox consume them. Data flows one way.

Every event is a frozen dataclass with a `kind` string; `to_json()` gives the SSE/REST payload.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

from contracts.types import SampleBlock, Segment


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
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

    def to_json(self) -> dict:
        data = _jsonable(self)
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
    """Results of one DUT run's analysis: thermal (streaming and offline) and/or SFEM, as JSON dicts.
    No verdict: the run is judged once, at its end (DutVerdict)."""

    slot: str
    serial: str
    thermal: dict | None = None
    sfem: dict | None = None


@dataclass(frozen=True)
class DutVerdict(Event):
    """THE decision on a DUT run, final: published once when the run ends (station/decisions/moment.py);
    the database numbers it for the MES (result_seq) and the webhook sends it. A later one for the
    same run (a resumed batch, a re-judge) is a new record that supersedes the earlier."""

    slot: str
    serial: str | None
    verdict: dict


@dataclass(frozen=True)
class DutProgrammed(Event):
    """Program and verify, part 1: the coefficients written to a DUT, read back and compensation
    switched on (program["programmed"]), or why not (program["error_kind"], program["error"])."""

    slot: str
    serial: str
    program: dict


@dataclass(frozen=True)
class DutVerified(Event):
    """Program and verify, part 2: the verified drift error E of the compensated output
    (station.science.verify.VerificationResult.to_json())."""

    slot: str
    serial: str
    verification: dict


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
    """In-process fan-out: each subscriber gets its own bounded queue.

    A slow subscriber (a stalled browser) loses its oldest events rather than stalling the
    daemon; the database writer subscribes with drop=False and gets back-pressure instead.
    """

    def __init__(self) -> None:
        self._subscribers: list[tuple[asyncio.Queue, bool]] = []

    def subscribe(self, maxsize: int = 10000, drop: bool = True) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=maxsize)
        self._subscribers.append((q, drop))
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self._subscribers = [(s, d) for s, d in self._subscribers if s is not q]

    def publish(self, event: Event) -> None:
        for q, drop in self._subscribers:
            if q.full():
                if not drop:
                    # Never drop data for a lossless subscriber; grow instead of losing.
                    q._maxsize = q.maxsize * 2  # type: ignore[attr-defined]
                else:
                    try:
                        q.get_nowait()
                    except asyncio.QueueEmpty:
                        pass
            q.put_nowait(event)
