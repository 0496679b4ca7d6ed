"""File names built from data (serials, effect names, run ids): one helper for the whole station.

A serial comes from a log header or a board's identity reply, so it is data, not a trusted name:
`../../../../escape`, `/tmp/x`, `..`, a NUL or a newline must never choose where a file goes.

    safe_name("SIM0001")                 -> "SIM0001"          (a clean value is kept as it is)
    safe_name("../../x")                 -> "x-3f1c0a9b2e"     (changed: a hash of the value added)
    safe_path(out_dir, serial, ".model.json")
                                         -> out_dir/<safe_name(serial)>.model.json, checked inside

safe_name maps a value to a base name: only ASCII letters, digits and `._-+`, no leading dot or
dash, no `..`, no trailing dot, at most MAX_LEN characters, never empty, never a Windows device
name. When sanitising changed the value (or the value ends like a hash suffix), `-` and the first
HASH_LEN hex digits of the value's SHA-256 are appended, so two different values never become the
same name in one folder (a clean name never ends in such a suffix, a changed one always carries
the hash of its own value).

safe_path joins it (with a fixed prefix/suffix of the caller's) under a directory and verifies that
the result, symbolic links resolved, is a direct child of that directory; otherwise StationError.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from contracts.types import StationError

MAX_LEN = 80
HASH_LEN = 10
_ALLOWED = re.compile(r"[A-Za-z0-9._+\-]")
_HASH_TAIL = re.compile(r"-[0-9a-f]{%d}$" % HASH_LEN)
_WINDOWS_DEVICES = {"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(10)), *(f"LPT{i}" for i in range(10))}


def _digest(value: str) -> str:
    return hashlib.sha256(value.encode("utf-8", "surrogatepass")).hexdigest()[:HASH_LEN]


def safe_name(value: object, max_len: int = MAX_LEN, empty: str = "unnamed") -> str:
    """A base name for `value` that is safe in any folder (see the module doc)."""
    if max_len < HASH_LEN + 2:
        raise ValueError(f"max_len must be at least {HASH_LEN + 2}")
    text = "" if value is None else str(value)
    out = "".join(c if _ALLOWED.fullmatch(c) else "_" for c in text)
    out = re.sub(r"\.{2,}", ".", out)  # no '..' anywhere
    out = out.lstrip(".-").rstrip(".")  # no hidden file, no option-like name, no trailing dot
    if not out:
        out = empty
    if out.split(".", 1)[0].upper() in _WINDOWS_DEVICES:
        out = "_" + out
    changed = out != text or len(out) > max_len or bool(_HASH_TAIL.search(out))
    if not changed:
        return out
    keep = max_len - HASH_LEN - 1
    return f"{out[:keep].rstrip('.')}-{_digest(text)}"


def safe_path(directory: str | Path, value: object, suffix: str = "", prefix: str = "") -> Path:
    """`directory / (prefix + safe_name(value) + suffix)`, verified to stay inside `directory`.

    prefix and suffix are the caller's fixed text (".model.json", "_residual_vs_time.png"); they
    must not contain a path separator. A target that resolves outside the directory (a symbolic
    link planted under that name) is refused with StationError."""
    for part in (prefix, suffix):
        if "/" in part or "\\" in part or "\x00" in part:
            raise ValueError(f"file name prefix/suffix must not contain a path separator: {part!r}")
    d = Path(directory)
    p = d / f"{prefix}{safe_name(value)}{suffix}"
    check_inside(d, p)
    return p


def check_inside(directory: str | Path, path: str | Path) -> Path:
    """Raise StationError unless `path` (symbolic links resolved) is directly inside `directory`."""
    d, p = Path(directory), Path(path)
    try:
        root = d.resolve()
        target = p.resolve()
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise StationError(f"{p}: cannot resolve the file name ({exc})") from None
    if target.parent != root or p.name in ("", ".", ".."):
        raise StationError(f"{p}: refusing to write outside {d}")
    return p


__all__ = ["safe_name", "safe_path", "check_inside", "MAX_LEN", "HASH_LEN"]
