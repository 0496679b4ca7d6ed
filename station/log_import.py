"""Bring your own log: read delimited text from other tools into a DutLog (design 5.1 columns).

Engineers have logs from data loggers, flight stacks and test templates: comma, tab or semicolon
separated, with their own column names and units. This reader maps them onto the station's log:

    import_log("sweep.tsv", columns="time=timestamp,ax=acc_x,ay=acc_y,az=acc_z,temp=temperature",
               accel_units="m/s2", time_units="ms")

- delimiter: sniffed from the header line (comma, tab, semicolon) unless given;
- columns: `key=name` pairs for time, ax, ay, az, temp (and optional position, lamp); without a
  mapping, common names are recognised (time_s/time/timestamp/t, ax_g/ax/acc_x/accel_x/x, ...);
- accel_units: g, m/s2 (divided by 9.80665) or counts (divided by counts_per_g);
- time_units: s, ms, us, ns; time is made relative to the first sample;
- leading `# key: value` lines become metadata (serial, sensor, ...); the serial defaults to the
  file name.

Pure parsing (text in, DutLog out); every user mistake is one StationError line.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from station.logfile import DutLog
from station.types import StationError

G0_M_S2 = 9.80665
TIME_SCALE = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ACCEL_UNITS = ("g", "m/s2", "counts")
KEYS = ("time", "ax", "ay", "az", "temp")
ALIASES = {
    "time": ("time_s", "time", "timestamp", "t", "time_ms", "time_us", "timestamp_us", "t_s"),
    "ax": ("ax_g", "ax", "acc_x", "accel_x", "x", "accx", "acc_x_m_s2", "xacc"),
    "ay": ("ay_g", "ay", "acc_y", "accel_y", "y", "accy", "acc_y_m_s2", "yacc"),
    "az": ("az_g", "az", "acc_z", "accel_z", "z", "accz", "acc_z_m_s2", "zacc"),
    "temp": ("temp_c", "temp", "temperature", "temperature_c", "t_c", "imu_temp"),
    "position": ("position", "pos"),
    "lamp": ("lamp",),
}


def parse_columns(spec: str | dict | None) -> dict[str, str]:
    """`time=timestamp,ax=acc_x,...` -> {"time": "timestamp", "ax": "acc_x", ...}."""
    if spec is None or spec == "":
        return {}
    if isinstance(spec, dict):
        return {str(k): str(v) for k, v in spec.items()}
    out = {}
    for item in str(spec).split(","):
        if not item.strip():
            continue
        if "=" not in item:
            raise StationError(f"--columns: expected key=name pairs (keys {', '.join(KEYS)}), got {item.strip()!r}")
        k, v = (x.strip() for x in item.split("=", 1))
        if k not in ALIASES:
            raise StationError(f"--columns: unknown key {k!r} (keys: {', '.join(ALIASES)})")
        out[k] = v
    return out


def sniff_delimiter(header: str) -> str:
    counts = {d: header.count(d) for d in (",", "\t", ";")}
    best = max(counts, key=counts.get)
    if counts[best] == 0:
        raise StationError("cannot tell the delimiter: the header has no comma, tab or semicolon")
    return best


def parse_import(text: str, source: str = "<log>", columns: str | dict | None = None, accel_units: str = "g",
                 time_units: str = "s", counts_per_g: float | None = None, delimiter: str | None = None) -> DutLog:
    if accel_units not in ACCEL_UNITS:
        raise StationError(f"--accel-units must be one of {', '.join(ACCEL_UNITS)} (got {accel_units!r})")
    if time_units not in TIME_SCALE:
        raise StationError(f"--time-units must be one of {', '.join(TIME_SCALE)} (got {time_units!r})")
    if accel_units == "counts" and not (counts_per_g and counts_per_g > 0):
        raise StationError("--accel-units counts needs --counts-per-g (the sensor's LSB per g)")
    meta: dict[str, str] = {}
    lines = text.splitlines()
    k = 0
    while k < len(lines) and (not lines[k].strip() or lines[k].lstrip().startswith("#")):
        ln = lines[k].lstrip()[1:].strip() if lines[k].strip() else ""
        if ":" in ln:
            key, val = ln.split(":", 1)
            meta[key.strip()] = val.strip()
        k += 1
    if k >= len(lines):
        raise StationError(f"{source}: no header row")
    delim = delimiter or sniff_delimiter(lines[k])
    header = [h.strip().strip('"') for h in lines[k].split(delim)]
    lower = {h.lower(): i for i, h in enumerate(header)}
    mapping = parse_columns(columns)
    idx: dict[str, int] = {}
    for key in list(KEYS) + ["position", "lamp"]:
        if key in mapping:
            name = mapping[key]
            if name.lower() not in lower:
                raise StationError(f"{source}: no column {name!r} for {key} (columns: {', '.join(header)})")
            idx[key] = lower[name.lower()]
        else:
            hit = next((lower[a] for a in ALIASES[key] if a in lower), None)
            if hit is not None:
                idx[key] = hit
    missing = [key for key in KEYS if key not in idx]
    if missing:
        raise StationError(f"{source}: cannot find column(s) for {', '.join(missing)} (columns: {', '.join(header)}); "
                           f"map them with --columns {','.join(f'{m}=NAME' for m in missing)}")
    body = "\n".join(lines[k + 1:])
    try:
        data = np.genfromtxt(io.StringIO(body), delimiter=delim, dtype=np.float64, invalid_raise=False)
    except ValueError as exc:
        raise StationError(f"{source}: cannot parse the rows ({exc})") from None
    data = np.atleast_2d(data)
    if data.size == 0 or data.shape[1] < len(header):
        raise StationError(f"{source}: no data rows with {len(header)} fields")
    cols = [idx[key] for key in KEYS]
    ok = np.all(np.isfinite(data[:, cols]), axis=1)
    data = data[ok]
    if data.shape[0] < 2:
        raise StationError(f"{source}: fewer than 2 complete rows")
    t = data[:, idx["time"]] * TIME_SCALE[time_units]
    t = t - t[0]
    acc = data[:, [idx["ax"], idx["ay"], idx["az"]]]
    if accel_units == "m/s2":
        acc = acc / G0_M_S2
    elif accel_units == "counts":
        acc = acc / float(counts_per_g)
    meta.setdefault("serial", Path(source).stem)
    meta.setdefault("source", f"imported from {Path(source).name}")
    position = data[:, idx["position"]].astype(np.int64) if "position" in idx else None
    lamp = data[:, idx["lamp"]].astype(np.int8) if "lamp" in idx else None
    return DutLog(time_s=t, acc_g=acc, temp_c=data[:, idx["temp"]], meta=meta, lamp=lamp, position=position)


def import_log(path: str | Path, **kw) -> DutLog:
    """Read a delimited text log from another tool (see module doc)."""
    p = Path(path)
    if not p.is_file():
        raise StationError(f"{p}: no such file")
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise StationError(f"{p}: cannot read ({exc.strerror})") from None
    return parse_import(text, source=str(p), **kw)


__all__ = ["import_log", "parse_import", "parse_columns", "sniff_delimiter", "ACCEL_UNITS", "TIME_SCALE"]
