"""CSV cells a spreadsheet shows as text, never evaluates (CSV injection, OWASP's rule).

A serial, a slot or a station name typed as `=1+2`, `@SUM(1+1)`, `+cmd|...` or `-2+3` would be a
formula when the downloaded CSV is opened in a spreadsheet. A cell starting with = + - @, a tab or a
carriage return gets a single quote in front; a plain number (`-51.7`, `+3`, `1e-5`) stays a number.
"""

from __future__ import annotations

import re
from typing import Any, Iterable

_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def safe_cell(value: Any) -> Any:
    """`value` as a cell a spreadsheet will not evaluate (non-text values pass through)."""
    if not isinstance(value, str) or not value.startswith(_FORMULA_START) or _NUMBER.fullmatch(value):
        return value
    return "'" + value


def safe_row(values: Iterable[Any]) -> list[Any]:
    return [safe_cell(v) for v in values]


__all__ = ["safe_cell", "safe_row"]
