"""The per-DUT log file (design 5.1, CONTRACT): read and write.

    # serial: SIM0001
    # sensor: LIS3DSH
    time_s,ax_g,ay_g,az_g,temp_c[,lamp][,position][,ref_x,ref_y,ref_z]

The station writes this for every DUT run and reads it back for `calibrate`, `sfem`, `diagnose`.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.types import SampleBlock, StationError

REQUIRED_COLUMNS = ("time_s", "ax_g", "ay_g", "az_g", "temp_c")
OPTIONAL_COLUMNS = ("lamp", "position", "ref_x", "ref_y", "ref_z")

# Stored precision: 1 ug and 1 mC are below every sensor's resolution (LIS3DSH 60 ug, ADXL355 3.9 ug).
ACC_DECIMALS = 7
TEMP_DECIMALS = 4
TIME_DECIMALS = 6


@dataclass
class DutLog:
    """A DUT's log in memory: columns as numpy arrays plus the `# key: value` metadata."""

    time_s: np.ndarray
    acc_g: np.ndarray  # (n, 3)
    temp_c: np.ndarray
    meta: dict[str, str] = field(default_factory=dict)
    lamp: np.ndarray | None = None  # (n,) 0/1
    position: np.ndarray | None = None  # (n,) int, -1 where unknown
    ref_dir: np.ndarray | None = None  # (n, 3) unit vectors in the sensor frame

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def block(self) -> SampleBlock:
        return SampleBlock(self.time_s, self.acc_g, self.temp_c)

    @property
    def serial(self) -> str:
        return self.meta.get("serial", "")


def read_log(path: str | Path) -> DutLog:
    """Read a log file; raises StationError with one clear line for any user mistake."""
    p = Path(path)
    if not p.exists():
        raise StationError(f"{p}: no such file")
    if p.is_dir():
        raise StationError(f"{p}: is a directory, expected a CSV log file")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StationError(f"{p}: cannot read ({exc})") from None
    return parse_log(text, source=str(p))


def parse_log(text: str, source: str = "<log>") -> DutLog:
    meta: dict[str, str] = {}
    lines = text.splitlines()
    i = 0
    while i < len(lines) and (lines[i].startswith("#") or not lines[i].strip()):
        line = lines[i].lstrip("#").strip()
        if ":" in line:
            key, value = line.split(":", 1)
            meta[key.strip()] = value.strip()
        i += 1
    if i >= len(lines):
        raise StationError(f"{source}: no header row (expected columns {','.join(REQUIRED_COLUMNS)})")
    header = [h.strip() for h in lines[i].split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise StationError(f"{source}: missing column(s) {', '.join(missing)} (header is {','.join(header)})")
    numbered = [(n + 1, ln) for n, ln in enumerate(lines) if n > i and ln.strip() and not ln.startswith("#")]
    body = [ln for _, ln in numbered]
    if not body:
        return _empty_log(meta, header)
    try:
        data = np.loadtxt(io.StringIO("\n".join(body)), delimiter=",", dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise StationError(f"{source}: malformed data row ({exc})") from None
    if data.shape[1] != len(header):
        raise StationError(f"{source}: rows have {data.shape[1]} fields but the header has {len(header)}")
    col = {name: data[:, k] for k, name in enumerate(header)}
    _check_values(col, [n for n, _ in numbered], source)
    log = DutLog(
        time_s=col["time_s"].copy(),
        acc_g=np.column_stack([col["ax_g"], col["ay_g"], col["az_g"]]),
        temp_c=col["temp_c"].copy(),
        meta=meta,
    )
    if "lamp" in col:
        log.lamp = col["lamp"].astype(np.int8)
    if "position" in col:
        log.position = col["position"].astype(np.int64)
    if all(c in col for c in ("ref_x", "ref_y", "ref_z")):
        log.ref_dir = np.column_stack([col["ref_x"], col["ref_y"], col["ref_z"]])
    return log


def _check_values(col: dict[str, np.ndarray], line_numbers: list[int], source: str) -> None:
    """Samples must be finite and lamp/position small integers: NaN or inf samples passed into
    every analysis, and `position = 1e300` became int64 min by a silent cast. The first bad value
    is reported with its line number (1-based, in the file)."""
    from station.positions import POSITION_NAMES

    def fail(name: str, rows: np.ndarray, why: str) -> None:
        r = int(np.flatnonzero(rows)[0])
        raise StationError(f"{source}: line {line_numbers[r]}: {name} = {float(col[name][r])!r} {why}")

    for name in REQUIRED_COLUMNS:
        bad = ~np.isfinite(col[name])
        if bad.any():
            fail(name, bad, "is not a finite number")
    if "lamp" in col:
        bad = ~np.isin(col["lamp"], (0.0, 1.0))
        if bad.any():
            fail("lamp", bad, "must be 0 or 1")
    if "position" in col:
        p = col["position"]
        bad = ~(np.isfinite(p) & (p == np.round(p)) & (p >= -1) & (p < len(POSITION_NAMES)))
        if bad.any():
            fail("position", bad, f"must be an integer -1 (unknown) .. {len(POSITION_NAMES) - 1}")


def _empty_log(meta: dict[str, str], header: list[str]) -> DutLog:
    return DutLog(np.empty(0), np.empty((0, 3)), np.empty(0), meta=meta)


def format_log(log: DutLog) -> str:
    """The CSV text of a log, at the stored precision."""
    buf = io.StringIO()
    for key, value in log.meta.items():
        buf.write(f"# {key}: {value}\n")
    cols = list(REQUIRED_COLUMNS)
    arrays: list[np.ndarray] = [log.time_s, log.acc_g[:, 0], log.acc_g[:, 1], log.acc_g[:, 2], log.temp_c]
    fmts = [f"%.{TIME_DECIMALS}f"] + [f"%.{ACC_DECIMALS}f"] * 3 + [f"%.{TEMP_DECIMALS}f"]
    if log.lamp is not None:
        cols.append("lamp"), arrays.append(log.lamp), fmts.append("%d")
    if log.position is not None:
        cols.append("position"), arrays.append(log.position), fmts.append("%d")
    if log.ref_dir is not None:
        for k, name in enumerate(("ref_x", "ref_y", "ref_z")):
            cols.append(name), arrays.append(log.ref_dir[:, k]), fmts.append("%.6f")
    buf.write(",".join(cols) + "\n")
    if len(log):
        np.savetxt(buf, np.column_stack(arrays), fmt=fmts, delimiter=",")
    return buf.getvalue()


def write_log(path: str | Path, log: DutLog) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(p.suffix + ".tmp")
    tmp.write_text(format_log(log), encoding="utf-8")
    tmp.replace(p)


__all__ = ["DutLog", "read_log", "parse_log", "format_log", "write_log", "REQUIRED_COLUMNS"]
