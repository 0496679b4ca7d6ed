"""JSON-safe copies of what the station stores and reports (results, verdicts, audit details).

Strict JSON has no NaN or inf (PostgreSQL's JSON refuses them; other tools' parsers too): an
uncertainty that cannot be estimated becomes null. numpy arrays and scalars become Python values,
tuples lists, dataclasses dicts. One function, so a result reads the same in the daemon, the
database and a command's --json output.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, TypeAlias

# A JSON object as the station passes it around (results, verdicts, event payloads): string keys,
# values any JSON value. `object`, not Any: a reader narrows (isinstance) before it uses a value.
JsonDict: TypeAlias = dict[str, object]


# Any, not object: the value truly is anything read back from JSON, a database row or a numpy
# array, and float() is asked to make sense of it (what cannot be read is None).
def finite_or_none(value: Any) -> float | None:
    """A stored number as a finite float, or None (missing, not a number, NaN or inf)."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


# Any in and out: a JSON encoder's input is anything (numpy, dataclasses, nested containers), and
# its output is whatever JSON value the input makes; callers that know the shape use plain_json_dict.
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


def plain_json_dict(value: Mapping[str, object]) -> JsonDict:
    """plain_json of a JSON object, typed as one (the same copy: keys as str, values made safe)."""
    return {str(k): plain_json(v) for k, v in value.items()}
