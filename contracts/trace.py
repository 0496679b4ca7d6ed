"""What a batch was started for, as the line knows it: the work order, the part number and
revision, the lot, and the serial on each part's label (scanned or typed at the start).

Carried by the batch and stamped on every run, result, certificate, export and MES record, so a
part can be traced from its label to the work order it was built under. Empty strings mean "not
given" (a demo or an engineer's replay), never a made-up value.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

TRACE_FIELDS = ("work_order", "part_number", "part_revision", "lot")


@dataclass(frozen=True)
class Trace:
    work_order: str = ""
    part_number: str = ""
    part_revision: str = ""
    lot: str = ""
    labels: dict[str, str] = field(default_factory=dict)  # slot -> label serial

    @classmethod
    def of(cls, data: Any) -> "Trace":
        """From a mapping or an object with the same names (a request body, a database row)."""
        get = data.get if isinstance(data, dict) else (lambda k, d=None: getattr(data, k, d))
        labels = get("labels", None) or {}
        return cls(**{k: str(get(k, "") or "").strip() for k in TRACE_FIELDS},
                   labels={str(k): str(v).strip() for k, v in dict(labels).items() if str(v or "").strip()})

    def fields(self) -> dict[str, str]:
        """The four batch-level fields (no labels)."""
        return {k: getattr(self, k) for k in TRACE_FIELDS}

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def product(self) -> str:
        """The product key SPC groups by: part number and revision ('' when not given)."""
        if not self.part_number:
            return ""
        return f"{self.part_number} rev {self.part_revision}" if self.part_revision else self.part_number


def serial_key(serial: str) -> str:
    """What makes two serials the same part: scanners and typists add stray whitespace and case,
    so serials compare trimmed and case-insensitive (a label with its board, boards in a batch)."""
    return serial.strip().casefold()


def label_mismatch(label: str | None, board_serial: str | None) -> str | None:
    """The reason a slot stops when the label scanned for it is not the board's own serial; None
    when no label was scanned or they agree. Scanners add stray whitespace and case: compared
    trimmed and case-insensitive, reported as typed."""
    if not label:
        return None
    if board_serial is not None and serial_key(label) == serial_key(str(board_serial)):
        return None
    return (f"label serial {label!r} does not match the board's own serial {board_serial!r}: "
            "wrong part in this slot, or a mislabelled part; check the part and its label")
