"""The identity's trailing `key=value` fields (docs/design.md 3.1, issue 42): what a
board says of its own health in its `I` reply and its `C` reply (the `rec_*` keys).

`I,<serial>,<sensor>,<fw>,<ug_per_lsb>,<t_lsb_per_c>,<t_lsb_at_25c>,<odr_hz>[,<key>=<value>...]`
Unknown keys are ignored (a newer board); a field that is no `key=value`, a key given twice, or a
known key with a bad value makes the frame malformed (serial_frames counts it and skips it: a
station asks again rather than half-believe a frame). The records are contracts/board_health.py.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

from contracts.board_health import BoardRecordInfo
from contracts.types import Identity
from drivers.protocol.frame_text import fmt_crc

_U32_MAX = (1 << 32) - 1


HEALTH_KEYS = ("reset", "boots", "fault", "fault_pc", "rec_ver", "rec_gen", "rec_slot", "rec_state", "caps",
               "sensor_reinit")  # the contract's order: the one a board sends and `health_fields` writes
RECORD_KEYS = ("rec_ver", "rec_gen", "rec_slot", "rec_state")
_KEY = re.compile(r"[A-Za-z0-9_]+")
_WORD = re.compile(r"[a-z][a-z0-9_]*")  # a reset cause, a record state, a capability
_UINT = re.compile(r"[0-9]{1,10}")
_HEX8 = re.compile(r"[0-9A-Fa-f]{8}")


def parse_key_values(fields: Iterable[str]) -> dict[str, str]:
    """`key=value` fields -> dict. ValueError for a field without `=`, an empty or odd key, or a
    key given twice (a frame that says two things is not believed)."""
    out: dict[str, str] = {}
    for f in fields:
        key, eq, value = f.partition("=")
        if not eq or not _KEY.fullmatch(key):
            raise ValueError(f"not a key=value field: {f!r}")
        if key in out:
            raise ValueError(f"key {key!r} given twice")
        out[key] = value
    return out


def _uint32(text: str) -> int:
    if not _UINT.fullmatch(text) or int(text) > _U32_MAX:
        raise ValueError(f"not a uint32: {text!r}")
    return int(text)


def _word(text: str) -> str:
    if not _WORD.fullmatch(text):
        raise ValueError(f"not a word: {text!r}")
    return text


def record_info(kv: Mapping[str, str]) -> BoardRecordInfo | None:
    """The `rec_*` keys (None when the board sent none of them). ValueError for a bad value."""
    if not any(k in kv for k in RECORD_KEYS):
        return None
    slot = kv.get("rec_slot")
    return BoardRecordInfo(
        rec_ver=_uint32(kv["rec_ver"]) if "rec_ver" in kv else None,
        rec_gen=_uint32(kv["rec_gen"]) if "rec_gen" in kv else None,
        rec_slot=None if slot is None or slot == "-" else _uint32(slot),
        rec_state=_word(kv["rec_state"]) if "rec_state" in kv else None,
    )


def identity_health(kv: Mapping[str, str]) -> dict[str, Any]:
    """Identity's health fields (contracts/types.Identity) from an `I` frame's key=value fields.
    Unknown keys are ignored (a newer board); a known key with a bad value raises ValueError (the
    frame is malformed: counted and skipped, the station asks again). An unknown WORD for a known
    key (a reset cause, a record state or a capability this station has not heard of) is kept as
    it came: it is a newer board's word, not a corrupt frame."""
    out: dict[str, Any] = {}
    if "reset" in kv:
        out["reset_cause"] = _word(kv["reset"])
    if "boots" in kv:
        out["boots"] = _uint32(kv["boots"])
    for key, name in (("fault", "fault_cfsr"), ("fault_pc", "fault_pc")):
        if key in kv:
            if not _HEX8.fullmatch(kv[key]):
                raise ValueError(f"{key} must be 8 hex digits: {kv[key]!r}")
            out[name] = int(kv[key], 16)
    rec = record_info(kv)
    if rec is not None:
        out["record"] = rec
    if "caps" in kv:
        out["caps"] = frozenset(_word(w) for w in kv["caps"].split("+")) if kv["caps"] else frozenset()
    if "sensor_reinit" in kv:
        out["sensor_reinits"] = _uint32(kv["sensor_reinit"])
    return out


def record_fields(rec: BoardRecordInfo | None) -> list[str]:
    """`rec_*=` fields of a record info, the ones known, in contract order."""
    if rec is None:
        return []
    out: list[str] = []
    if rec.rec_ver is not None:
        out.append(f"rec_ver={rec.rec_ver}")
    if rec.rec_gen is not None:
        out.append(f"rec_gen={rec.rec_gen}")
    if rec.rec_ver is not None or rec.rec_slot is not None:
        out.append(f"rec_slot={'-' if rec.rec_slot is None else rec.rec_slot}")
    if rec.rec_state is not None:
        out.append(f"rec_state={rec.rec_state}")
    return out


def health_fields(i: Identity) -> list[str]:
    """The key=value fields an `I` frame carries for an identity's health (those reported), in
    contract order; none for an identity without health (the frame is the 8-field one)."""
    out: list[str] = []
    if i.reset_cause is not None:
        out.append(f"reset={i.reset_cause}")
    if i.boots is not None:
        out.append(f"boots={i.boots}")
    if i.fault_cfsr is not None:
        out.append(f"fault={fmt_crc(i.fault_cfsr)}")
    if i.fault_pc is not None:
        out.append(f"fault_pc={fmt_crc(i.fault_pc)}")
    out += record_fields(i.record)
    if i.caps:
        out.append("caps=" + "+".join(sorted(i.caps)))
    if i.sensor_reinits is not None:
        out.append(f"sensor_reinit={i.sensor_reinits}")
    return out
