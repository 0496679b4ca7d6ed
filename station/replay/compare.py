"""The recorded outcome against the replayed one (pure: dicts in, a ReplayDiff out).

An outcome is what db/repository.py reports for a run (`state`, `verdict`, `grade`,
`thermal_by_method`, `sfem`, `program_verify`). It is flattened to named numbers
(`offline.x.tdb_mg_per_c`, `sfem.steps[1].rmse_after_mg`, `program_verify.written.tdb_mg_per_c.x`,
...) and words (`verdict`, `grade`, `state`, and for a programmed run `programmed`, `program_crc`
(the CRC-32 of the float32 record written: the coefficients written now equal those written
then, to the bit) and `program_error`). A number changed when |after - before| > atol + rtol * |before|; a word changed when
it differs. Numbers present on one side only are listed as appeared/disappeared (a changed
outcome too), except against a `partial` outcome (a log's offline fit), where only what it
holds is compared.

Default tolerance (rtol 1e-6, atol 1e-6 in the number's unit): the replayed samples are the
recorded ones bit for bit, and the science is deterministic in the samples, so the same code
gives the same numbers up to float summation order; where the daemon's timing decides which
samples a step gets (a compressed-time command lands a few samples earlier or later), a
change shows, and it is real: the station is not reproducible to better than that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from contracts.types import AXES

WORDS = ("state", "verdict", "grade")
SKIP_KEYS = {"id", "created_at", "updated_at", "judged_at", "n_segments", "method", "attempts", "crc",
             "readback_crc", "temperature_step"}
DEFAULT_RTOL = 1e-6
DEFAULT_ATOL = 1e-6


def flatten_outcome(outcome: dict[str, Any]) -> tuple[dict[str, float], dict[str, str | None]]:
    """(numbers, words) of an outcome; see module doc for the names."""
    nums: dict[str, float] = {}
    words = {k: outcome.get(k) for k in WORDS if k in outcome}
    for method, axes in (outcome.get("thermal_by_method") or {}).items():
        for ax in AXES:
            for key, v in (axes or {}).get(ax, {}).items():
                if key in ("tdb_mg_per_c", "tdsf_ppm_per_c") and _is_num(v):
                    nums[f"{method}.{ax}.{key}"] = float(v)
    if outcome.get("sfem"):
        _walk(outcome["sfem"], "sfem", nums)
    pv = outcome.get("program_verify") or {}
    for side in ("e_before_mg", "e_after_mg"):
        for ax, v in (pv.get(side) or {}).items():
            if _is_num(v):
                nums[f"program_verify.{side}.{ax}"] = float(v)
    for key, axes in (pv.get("written") or {}).items():  # the coefficients written into the board
        for ax, v in (axes or {}).items():
            if _is_num(v):
                nums[f"program_verify.written.{key}.{ax}"] = float(v)
    if "verified" in pv:
        words["verified"] = str(pv["verified"])
    if pv:
        # written now = written then, to the bit: the CRC-32 over the float32 record (design 3.1)
        words["programmed"] = str(pv.get("programmed"))
        words["program_crc"] = pv.get("crc")
        words["program_error"] = pv.get("error_kind")
    return nums, words


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def _walk(v: Any, path: str, out: dict[str, float]) -> None:
    if isinstance(v, dict):
        for k, x in v.items():
            if k not in SKIP_KEYS:
                _walk(x, f"{path}.{k}", out)
    elif isinstance(v, (list, tuple)):
        for i, x in enumerate(v):
            _walk(x, f"{path}[{i}]", out)
    elif _is_num(v):
        out[path] = float(v)


@dataclass
class Change:
    key: str
    before: Any
    after: Any
    delta: float | None = None  # after - before, for numbers

    def to_json(self) -> dict:
        return {"key": self.key, "before": self.before, "after": self.after, "delta": self.delta}


@dataclass
class DutDiff:
    slot: str
    serial: str
    changes: list[Change] = field(default_factory=list)
    compared: int = 0  # numbers and words compared
    samples_identical: bool | None = None  # what the board sent = the recording, in counts
    note: str = ""

    @property
    def changed(self) -> bool:
        return bool(self.changes) or self.samples_identical is False

    def to_json(self) -> dict:
        return {"slot": self.slot, "serial": self.serial, "changed": self.changed, "compared": self.compared,
                "samples_identical": self.samples_identical, "note": self.note,
                "changes": [c.to_json() for c in self.changes]}


@dataclass
class ReplayDiff:
    source: str
    before_label: str
    rtol: float
    atol: float
    duts: list[DutDiff]
    agreement: dict[str, Any] = field(default_factory=dict)
    replay_batch_id: int | None = None
    replay_state: str | None = None
    replay_error: str | None = None
    recorded_state: str = "finished"
    ended_at_recording_end: bool = False  # the replay stopped where the recording of an unfinished batch ends
    notes: list[str] = field(default_factory=list)  # what the replay did for the recorded line (director.py)

    @property
    def changed(self) -> list[DutDiff]:
        return [d for d in self.duts if d.changed]

    @property
    def end_changed(self) -> bool:
        """The batch ended otherwise than the recorded one. A recording of a batch that did not
        finish (aborted, failed) ends where it ended: a replay stopped there ended as recorded."""
        if self.ended_at_recording_end and self.recorded_state != "finished":
            return False
        return self.replay_state != self.recorded_state

    def largest(self) -> tuple[str, Change] | None:
        best = None
        for d in self.duts:
            for c in d.changes:
                if c.delta is None:
                    continue
                rel = abs(c.delta) / max(abs(float(c.before)), 1e-12)
                if best is None or rel > best[0]:
                    best = (rel, d.serial, c)
        return None if best is None else (best[1], best[2])

    def summary(self) -> dict:
        big = self.largest()
        verdicts = [(d.serial, c.before, c.after) for d in self.duts for c in d.changes if c.key == "verdict"]
        return {
            "duts": len(self.duts), "unchanged": len(self.duts) - len(self.changed), "changed": len(self.changed),
            "verdicts_changed": [{"serial": s, "before": b, "after": a} for s, b, a in verdicts],
            "largest_change": None if big is None else {"serial": big[0], **big[1].to_json()},
        }

    def to_json(self) -> dict:
        return {"source": self.source, "before": self.before_label, "rtol": self.rtol, "atol": self.atol,
                "replay_batch_id": self.replay_batch_id, "replay_state": self.replay_state,
                "replay_error": self.replay_error, "recorded_state": self.recorded_state,
                "ended_at_recording_end": self.ended_at_recording_end, "end_changed": self.end_changed,
                "notes": list(self.notes),
                "summary": self.summary(), "agreement": self.agreement, "duts": [d.to_json() for d in self.duts]}


def compare_outcomes(slot: str, serial: str, before: dict[str, Any], after: dict[str, Any] | None,
                     rtol: float = DEFAULT_RTOL, atol: float = DEFAULT_ATOL) -> DutDiff:
    """One DUT: every number and word of `before` against `after` (None: no replayed run)."""
    out = DutDiff(slot, serial)
    if after is None:
        out.changes.append(Change("run", "recorded", "missing in the replay"))
        return out
    nb, wb = flatten_outcome(before)
    na, wa = flatten_outcome(after)
    partial = bool(before.get("partial"))  # e.g. a log's offline fit: only what it has is compared
    if partial:
        wb = {k: v for k, v in wb.items() if v is not None}
    for k in sorted(set(wb) | (set() if partial else set(wa))):
        out.compared += 1
        if wb.get(k) != wa.get(k):
            out.changes.append(Change(k, wb.get(k), wa.get(k)))
    for k in sorted(set(nb) | (set() if partial else set(na))):
        out.compared += 1
        if k not in nb or k not in na:
            out.changes.append(Change(k, nb.get(k), na.get(k)))
            continue
        d = na[k] - nb[k]
        if abs(d) > atol + rtol * abs(nb[k]):
            out.changes.append(Change(k, nb[k], na[k], d))
    return out
