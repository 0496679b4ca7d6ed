"""JSON-safe copies of what the station stores and reports (results, verdicts, audit details).

Strict JSON has no NaN or inf (PostgreSQL's JSON refuses them; other tools' parsers too): an
uncertainty that cannot be estimated becomes null. numpy arrays and scalars become Python values,
tuples lists, dataclasses dicts. One function, so a result reads the same in the daemon, the
database and a command's --json output.
"""

from __future__ import annotations

import math
from typing import Any


def finite_or_none(value: Any) -> float | None:
    """A stored number as a finite float, or None (missing, not a number, NaN or inf)."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def plain_json(value: Any) -> Any:
    """JSON-safe copy: numpy to Python, tuples to lists, NaN/inf to None (PostgreSQL rejects NaN)."""
    if isinstance(value, dict):
        return {str(k): plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    if hasattr(value, "tolist"):
        return plain_json(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if hasattr(value, "__dataclass_fields__"):
        return plain_json({k: getattr(value, k) for k in value.__dataclass_fields__})
    return value
