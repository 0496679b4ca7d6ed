"""Which board is this? The identity rules a run's serial must pass (design 3.1), pure.

A station keys a board's whole history on the serial its identity reply gives: attempts, yields,
`GET /api/duts/{serial}`, the certificate and every record the MES receives. A serial that is not
unique in the batch (a cloned firmware image, an unprovisioned EEPROM's default serial), empty,
or not a serial at all would file one board's run under another's history: a false pass through
identity. So before any run is made (before the lamp heats), each slot's serial must be:

- non-empty, at most SERIAL_MAX_CHARS characters, of SERIAL_CHARS (the characters a serial keeps
  as its own file name, contracts/filenames.py), starting with a letter or a digit;
- unique within the batch, compared as label serials are (trimmed, case-insensitive).

And the board must stay the same from the run's start to its end: `identity_change` names what
differs between the identity a run started with and the one its board gives at the end (or before
it is programmed): a different serial, sensor, firmware or scaling is another board, or a board
whose firmware was changed under the run. Its health (contracts/board_health.py: reset cause,
boots, record, ...) is not part of WHICH board it is, but `board_restart` reads it: a `boots` that
moved between the two replies is the same board restarted during the run (a watchdog, a fault),
and a run that spans a restart is not one run of one board's life either.
"""

from __future__ import annotations

import re
from collections import defaultdict

from contracts.board_health import reset_words
from contracts.trace import serial_key
from contracts.types import Identity

SERIAL_MAX_CHARS = 32  # a CAN board's serial is at most 14, or 28 with identity frames 12/13 (design 3.2); a serial board's 32
SERIAL_CHARS = "A-Z a-z 0-9 . _ + -"
_SERIAL = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+\-]*")
# what must not change within a run; the ODR may (the station sets it)
SAME_BOARD_FIELDS = ("serial", "sensor", "fw", "ug_per_lsb", "t_lsb_per_c", "t_lsb_at_25c")


def serial_problem(serial: str) -> str | None:
    """Why `serial` cannot key a board's record (None: it can)."""
    if serial == "":
        return "reports an empty serial (an unprovisioned board?)"
    shown = serial if len(serial) <= 40 else serial[:37] + "..."
    if len(serial) > SERIAL_MAX_CHARS:
        return f"reports a {len(serial)}-character serial {shown!r} (at most {SERIAL_MAX_CHARS})"
    if not _SERIAL.fullmatch(serial):
        return (f"reports the serial {shown!r}, not a serial (letters, digits and . _ + -, "
                f"starting with a letter or digit)")
    return None


def batch_identity_problems(serials: dict[str, str]) -> dict[str, str]:
    """slot -> the reason its run cannot start, for the slots of one batch given their board's
    serial: an invalid serial, or one that another slot of the batch reports too (every slot that
    shares it is stopped: the station cannot tell which board is the part with that serial)."""
    out: dict[str, str] = {}
    same: dict[str, list[str]] = defaultdict(list)
    for slot, serial in serials.items():
        problem = serial_problem(serial)
        if problem is not None:
            out[slot] = f"{slot} {problem}: its run is not started"
        else:
            same[serial_key(serial)].append(slot)
    for slots in same.values():
        if len(slots) < 2:
            continue
        names = f"{', '.join(slots[:-1])} and {slots[-1]}"
        serial = serials[slots[0]]
        for slot in slots:
            out[slot] = (f"{names} all report {serial}" if len(slots) > 2 else f"{names} both report {serial}") + \
                ": a cloned image or an unprovisioned board? No run is stored under a serial two boards claim"
    return out


def identity_change(before: Identity, after: Identity) -> str | None:
    """What differs between the identity a run started with and its board's identity now (None:
    the same board as far as its identity tells)."""
    changed = [f"{name} {getattr(before, name)!r} -> {getattr(after, name)!r}" for name in SAME_BOARD_FIELDS
               if getattr(before, name) != getattr(after, name)]
    return ", ".join(changed) or None


def board_restart(before: Identity, after: Identity) -> str | None:
    """Did the board restart between the identity a run started with and its identity now? Yes when
    both report `boots` and it moved (a power cycle gives boots 1 again: only a board that was at 1
    already hides one). Returns the reason the run cannot stand, with the cause the board gives
    ("the board restarted during the run: watchdog reset (boots 1 -> 2)"; a fault with its PC in
    hex), or None."""
    if before.boots is None or after.boots is None or before.boots == after.boots:
        return None
    cause = reset_words(after.reset_cause, after.fault_cfsr, after.fault_pc)
    return f"the board restarted during the run: {cause} (boots {before.boots} -> {after.boots})"
