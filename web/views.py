"""Shape the daemon's status dicts into the REST schemas (tolerant of extra or missing keys), and
helpers the routes share, so that route functions stay thin."""

from __future__ import annotations

import inspect
import math
from typing import Any

from fastapi import HTTPException

from contracts.types import NotFound, StorageUnavailable


async def call(fn, *args, conflict: bool = False, **kwargs):
    """Call a Station method that may be sync or async; map the facade's errors (contract:
    unknown batch -> contracts.types.NotFound, bad request -> ValueError) to 404 / 422 with the
    message. Any other exception (a plain KeyError too) is a bug: 500, never "not found".

    conflict=True: a ValueError means the request does not fit the batch's current state
    (already ended, no prompt open): 409 Conflict rather than 422."""
    try:
        out = fn(*args, **kwargs)
        if inspect.isawaitable(out):
            out = await out
    except NotFound as exc:
        raise HTTPException(status_code=404, detail=_msg(exc, "not found")) from None
    except StorageUnavailable as exc:
        raise HTTPException(status_code=503, detail=_msg(exc, "the database is not available")) from None
    except ValueError as exc:
        raise HTTPException(status_code=409 if conflict else 422, detail=_msg(exc, "invalid request")) from None
    return out


def _msg(exc: Exception, default: str) -> str:
    if exc.args and isinstance(exc.args[0], str) and exc.args[0]:
        return exc.args[0]
    if exc.args:
        return f"{default}: {exc.args[0]}"
    return default


def not_found(what: str) -> HTTPException:
    return HTTPException(status_code=404, detail=f"{what} not found")


def clean(value: Any) -> Any:
    """JSON-safe: NaN/inf -> None, numpy -> python, tuples -> lists.

    Hot path (every status poll walks the whole batch): exact builtin types first, by identity."""
    t = type(value)
    if t is str or t is int or t is bool or value is None:
        return value
    if t is float:
        return value if math.isfinite(value) else None
    if t is dict:
        return {k if type(k) is str else str(k): clean(v) for k, v in value.items()}
    if t is list or t is tuple:
        return [clean(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if hasattr(value, "tolist"):
        return clean(value.tolist())
    if hasattr(value, "item") and callable(value.item):
        try:
            return clean(value.item())
        except (TypeError, ValueError):
            return value
    return value


def _first(d: dict, *keys, default=None):
    for k in keys:
        if k in d and d[k] is not None:
            return d[k]
    return default


DECISION_FIELDS = ("verdict", "grade", "tray", "reason", "attempt", "limits_name", "limits_version")


def slot_view(raw: dict | Any, name: str | None = None, *, cleaned: bool = True) -> dict:
    d = dict(raw) if isinstance(raw, dict) else {"state": str(raw)}
    segs = _first(d, "segments", "segments_logged", "n_segments", default=0)
    if isinstance(segs, (list, tuple)):
        segs = len(segs)
    out = dict(d)
    decision = d.get("decision")
    if isinstance(decision, dict):  # the station's verdict (station/decisions/moment.py), flat for clients
        for k in DECISION_FIELDS:
            out.setdefault(k, decision.get(k))
    out.update(
        slot=str(_first(d, "slot", "name", default=name or "")),
        serial=_first(d, "serial"),
        state=_first(d, "state"),
        segments=int(segs or 0),
        error=_first(d, "error", "fault_reason", "fault") or None,
    )
    run_id = d.get("run_id")
    if isinstance(run_id, int) and not isinstance(run_id, bool):
        out["plot_url"] = f"/api/runs/{run_id}/plot.png"  # by run, never by the serial's latest run
    return clean(out) if cleaned else out


def batch_view(raw: dict, batch_id: int) -> dict:
    d = dict(raw)
    step = d.get("step")
    if not isinstance(step, dict):
        step = {
            "index": _first(d, "step_index", default=step if isinstance(step, int) else None),
            "name": _first(d, "step_name", default=step if isinstance(step, str) else None),
            "count": _first(d, "step_count", "n_steps"),
        }
    else:
        step = {
            **step,
            "index": _first(step, "index", "step_index", default=d.get("step_index")),
            "name": _first(step, "name", "step_name"),
            "count": _first(step, "count", default=_first(d, "step_count", "n_steps")),
        }
    slots = d.get("slots") or []
    if isinstance(slots, dict):  # cleaned once below, with the rest
        slots = [slot_view(v, k, cleaned=False) for k, v in slots.items()]
    else:
        slots = [slot_view(s, cleaned=False) for s in slots]
    out = dict(d)
    out.update(
        id=int(_first(d, "id", "batch_id", default=batch_id)),
        state=str(_first(d, "state", default="unknown")),
        step=step,
        slots=slots,
        error=_first(d, "error", "reason", "fault_reason") or None,
        prompt=prompt_view(d.get("prompt")),
    )
    out = clean(out)
    out["current_step"] = next((r for r in out.get("steps") or [] if isinstance(r, dict) and r.get("state") == "running"),
                               None)
    out["slot_live"] = slot_live(out["slots"])
    return out


# What the operator page polls of every slot (SlotLive, GET /api/batches/{id}?view=compact): the
# fields that change while a batch runs. The page fetches a slot's other fields once, again only when
# its `rev` moves (GET /api/batches/{id}/slots).
LIVE_SLOT_FIELDS = ("state", "segments", "samples", "steps_done", "waiting_for")
# What `rev` fingerprints: what the page shows of a slot besides its live fields (its result it
# reads from GET /api/runs/{run_id} once the run is stored).
REV_SLOT_FIELDS = ("serial", "label_serial", "sensor", "error", "run_id", "program", "verification",
                   "program_verify") + DECISION_FIELDS


def _shallow(value: object) -> object:
    """A field made hashable and cheap: a nested record (program, verification) by its scalar items
    and the sizes of its lists, a list by its size. Such records are written once per run (a new
    program or verification is a new record, whose flags, CRC or pass differ), and reading every
    float of them in each render would cost the poll more than the fingerprint saves."""
    if type(value) is list:
        return ("list", len(value))
    if type(value) is not dict:
        return value
    return tuple((k, v if v is None or type(v) in (str, int, bool) else len(v) if type(v) in (list, dict) else 0)
                 for k, v in value.items())


def slot_rev(slot: dict) -> str:
    """Fingerprint of REV_SLOT_FIELDS of one shaped slot: 8 hex digits of Python's hash (salted per
    process, so it compares within one daemon's life: after a restart the page fetches once more)."""
    return f"{hash(tuple(_shallow(slot.get(k)) for k in REV_SLOT_FIELDS)) & 0xFFFFFFFF:08x}"


def slot_live(slots: list[dict]) -> dict[str, list[object]]:
    """SlotLive of the shaped slots: their live fields as columns and each slot's rev."""
    cols: dict[str, list[object]] = {k: [s.get(k) for s in slots] for k in LIVE_SLOT_FIELDS}
    cols["rev"] = [slot_rev(s) for s in slots]
    return cols


def prompt_view(raw: dict | None) -> dict | None:
    """The sequencer's prompt ({"id", "text", ...}) as the API's Prompt ({"prompt_id", ...})."""
    if not raw:
        return None
    d = dict(raw)
    d["prompt_id"] = int(_first(d, "prompt_id", "id"))
    return clean(d)


def dut_view(raw: dict) -> dict:
    """`thermal` per axis from a stored result, which is the calibrate JSON ({"axes": ...}) or axes."""
    d = dict(raw)
    thermal = d.get("thermal")
    if isinstance(thermal, dict):
        axes = thermal.get("axes") if "axes" in thermal else thermal
        if isinstance(axes, dict) and all(k in ("x", "y", "z") for k in axes):
            d["thermal"] = axes
        else:
            d["thermal"] = None
        d.setdefault("streaming", thermal.get("streaming"))
        d.setdefault("offline", thermal.get("offline"))
    return clean(d)
