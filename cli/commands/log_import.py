"""Bring your own log: read delimited text from other tools into a DutLog (design 5.1 columns).

Engineers have logs from data loggers, flight stacks and test templates: comma, tab or semicolon
separated, with their own column names and units. This reader maps them onto the station's log:

    import_log("sweep.tsv", columns="time=timestamp,ax=acc_x,ay=acc_y,az=acc_z,temp=temperature",
               accel_units="m/s2", time_units="ms")

- delimiter: sniffed from the header line (comma, tab, semicolon) unless given;
- columns: `key=name` pairs for time, ax, ay, az, temp (and optional position, lamp); without a
  mapping, common names are recognised (time_s/time/timestamp/t, ax_g/ax/acc_x/accel_x/x, ...);
- accel_units: g, mg (divided by 1000), m/s2 (divided by 9.80665) or counts (divided by counts_per_g);
- time_units: s, ms, us, ns; time is made relative to the first sample;
- temp_units: C or K (273.15 subtracted);
- leading `# key: value` lines become metadata (serial, sensor, ...); the serial defaults to the
  file name.

Rows with another field count, or a required field that is not a number, are skipped (another
sensor's line in a shared log). What is left is checked like a design-5.1 log before any science
(contracts.log_checks.LogChecker): units by the static magnitude (the median |a| must be about 1 g
once converted; m/s2, mg or raw counts are named with the option that converts them), plausible
temperatures (kelvin named), strictly increasing time, finite header numbers in range.

Pure parsing (text in, DutLog out), a few MB at a time; every user mistake is one StationError line.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from contracts.log_checks import (  # G0_M_S2: part of this module's surface (m/s2 per g)
    G0_M_S2,
    LogChecker,
    check_meta,
    g_divisor,
)
from contracts.logfile import DutLog, _blocks_of_file, _blocks_of_text, _Header, _kept, _parse_rows
from contracts.types import StationError

TIME_SCALE = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ACCEL_UNITS = ("g", "mg", "m/s2", "counts")
TEMP_UNITS = ("C", "K")
KELVIN_OFFSET = 273.15
KEYS = ("time", "ax", "ay", "az", "temp")
REF_KEYS = ("ref_x", "ref_y", "ref_z")
ALIASES = {
    "time": ("time_s", "time", "timestamp", "t", "time_ms", "time_us", "timestamp_us", "t_s"),
    "ax": ("ax_g", "ax", "acc_x", "accel_x", "x", "accx", "acc_x_m_s2", "xacc"),
    "ay": ("ay_g", "ay", "acc_y", "accel_y", "y", "accy", "acc_y_m_s2", "yacc"),
    "az": ("az_g", "az", "acc_z", "accel_z", "z", "accz", "acc_z_m_s2", "zacc"),
    "temp": ("temp_c", "temp", "temperature", "temperature_c", "t_c", "imu_temp"),
    "position": ("position", "pos"),
    "lamp": ("lamp",),
    "ref_x": ("ref_x",),
    "ref_y": ("ref_y",),
    "ref_z": ("ref_z",),
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


def _check_options(accel_units: str, time_units: str, temp_units: str, counts_per_g: float | None) -> None:
    if accel_units not in ACCEL_UNITS:
        raise StationError(f"--accel-units must be one of {', '.join(ACCEL_UNITS)} (got {accel_units!r})")
    if time_units not in TIME_SCALE:
        raise StationError(f"--time-units must be one of {', '.join(TIME_SCALE)} (got {time_units!r})")
    if str(temp_units).upper() not in TEMP_UNITS:
        raise StationError(f"--temp-units must be one of {', '.join(TEMP_UNITS)} (got {temp_units!r})")
    if accel_units == "counts":
        if counts_per_g is None:
            raise StationError("--accel-units counts needs --counts-per-g (the sensor's LSB per g)")
        if not (math.isfinite(counts_per_g) and counts_per_g > 0):
            raise StationError(f"--counts-per-g must be a positive number (got {counts_per_g:g})")


def _is_meta(line: str) -> bool:
    return not line.strip() or line.lstrip().startswith("#")


def parse_import(text: str, source: str = "<log>", columns: str | dict | None = None, accel_units: str = "g",
                 time_units: str = "s", counts_per_g: float | None = None, delimiter: str | None = None,
                 temp_units: str = "C") -> DutLog:
    return _import(_blocks_of_text(text, source=source), source, len(text), columns=columns,
                   accel_units=accel_units, time_units=time_units, counts_per_g=counts_per_g, delimiter=delimiter,
                   temp_units=temp_units)


def _import(blocks, source: str, size: int, columns=None, accel_units: str = "g", time_units: str = "s",
            counts_per_g: float | None = None, delimiter: str | None = None, temp_units: str = "C",
            keep_optional: Iterable[str] | None = None) -> DutLog:
    _check_options(accel_units, time_units, temp_units, counts_per_g)
    kelvin = str(temp_units).upper() == "K"
    head = _Header(blocks, _is_meta)
    meta = head.meta
    if head.line is None:
        raise StationError(f"{source}: no header row")
    delim = delimiter or sniff_delimiter(head.line)
    header = [h.strip().strip('"') for h in head.line.split(delim)]
    lower = {h.lower(): i for i, h in enumerate(header)}
    mapping = parse_columns(columns)
    idx: dict[str, int] = {}
    for key in ALIASES:
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
    check_meta(meta, source)
    has_ref = all(k in idx for k in REF_KEYS)
    names = {k: header[idx[k]] for k in ("time", "ax", "ay", "az", "temp", "lamp", "position") if k in idx}
    req = [idx[key] for key in KEYS]
    acc_cols = [idx["ax"], idx["ay"], idx["az"]]
    keep = _kept(keep_optional)
    chk: LogChecker | None = None
    parsed = 0
    for rows, nos in head.rows():
        data, nos = _parse_rows(rows, nos, len(header), delim, source, lenient=True)
        parsed += len(data)
        ok = np.all(np.isfinite(data[:, req]), axis=1)  # incomplete rows (another sensor's line) are skipped
        if not ok.all():
            data, nos = data[ok], nos[ok]
        if chk is None:  # capacity from the first block's bytes per row
            per_row = max(1.0, sum(map(len, rows)) / len(rows))
            chk = LogChecker(source, names, capacity=int(size / per_row * 1.02) + 1024,
                             lamp="lamp" in idx and "lamp" in keep, position="position" in idx and "position" in keep,
                             ref=has_ref and "ref_dir" in keep,
                             accel_units=accel_units, counts_per_g=counts_per_g)
        temp = data[:, idx["temp"]]
        if kelvin:
            temp = temp - KELVIN_OFFSET
        chk.add(data[:, idx["time"]], data[:, acc_cols], temp,
                data[:, idx["lamp"]] if "lamp" in idx else None,
                data[:, idx["position"]] if "position" in idx else None,
                data[:, [idx[k] for k in REF_KEYS]] if has_ref else None, lines=nos)
    if parsed == 0:
        raise StationError(f"{source}: no data rows with {len(header)} fields")
    if chk is None or chk.n < 2:
        raise StationError(f"{source}: fewer than 2 complete rows")
    chk.finish(meta, accel_units=accel_units, counts_per_g=counts_per_g, temp_units=temp_units,
               time_scale=TIME_SCALE[time_units])
    t = chk.time  # converted in place: seconds from the first sample
    t *= TIME_SCALE[time_units]
    t0 = float(t[0])
    t -= t0
    if (meta.get("t_power_on_s") or "").strip():  # on the log's clock (seconds): moved with it
        meta["t_power_on_s"] = repr(float(meta["t_power_on_s"]) - t0)
    acc = chk.acc
    if accel_units != "g":
        acc /= g_divisor(accel_units, counts_per_g)
    meta.setdefault("serial", Path(source).stem)
    meta.setdefault("source", f"imported from {Path(source).name}")
    return DutLog(time_s=t, acc_g=acc, temp_c=chk.temp, meta=meta, lamp=chk.lamp, position=chk.position,
                  ref_dir=chk.ref)


def import_log(path: str | Path, **kw) -> DutLog:
    """Read a delimited text log from another tool (see module doc), a few MB at a time."""
    p = Path(path)
    if not p.is_file():
        raise StationError(f"{p}: no such file")
    try:
        with open(p, encoding="utf-8-sig", errors="replace") as f:  # a leading BOM skipped
            return _import(_blocks_of_file(f, str(p)), str(p), p.stat().st_size, **kw)
    except OSError as exc:
        raise StationError(f"{p}: cannot read ({exc.strerror})") from None


# ---- the command line: the same import options on calibrate, sfem and diagnose ------------------
IMPORT_OPTIONS = ("columns", "accel_units", "time_units", "temp_units", "delimiter", "counts_per_g")


def add_import_arguments(parser) -> None:
    """--columns, --accel-units, --counts-per-g, --time-units, --temp-units, --delimiter: read a log
    from another tool, or a design-5.1 log written in other units."""
    parser.add_argument("--columns", metavar="MAP",
                        help="read a log from another tool: key=name pairs for time, ax, ay, az, temp "
                             "(e.g. time=timestamp,ax=acc_x,ay=acc_y,az=acc_z,temp=temperature); "
                             "comma, tab or semicolon delimited, header row required")
    parser.add_argument("--accel-units", choices=ACCEL_UNITS, default=None,
                        help="acceleration units of the log (default g; m/s2 divided by 9.80665, mg by 1000, "
                             "counts by --counts-per-g)")
    parser.add_argument("--counts-per-g", type=float, default=None, help="LSB per g for --accel-units counts")
    parser.add_argument("--time-units", choices=tuple(TIME_SCALE), default=None,
                        help="time units of the log (default s)")
    parser.add_argument("--temp-units", choices=TEMP_UNITS, type=str.upper, default=None,
                        help="temperature units of the log (default C; K has 273.15 subtracted)")
    parser.add_argument("--delimiter", default=None, help="field delimiter of an imported log (default: sniffed)")


def read_any_log(path: str, args=None, keep_optional: Iterable[str] | None = None) -> DutLog:
    """A station log (design 5.1), or with any import option (args from add_import_arguments) a
    log read by import_log; a log without the station's columns is imported with the column names
    recognised. Both are checked before any science (contracts.log_checks.LogChecker).
    keep_optional: the optional fields (lamp, position, ref_dir) the command uses (None: all); the
    others are checked and not kept, so a long log costs the command only the columns it reads."""
    from contracts.logfile import read_log

    opts = {k: getattr(args, k, None) for k in IMPORT_OPTIONS}
    kw = dict(columns=opts["columns"], accel_units=opts["accel_units"] or "g", time_units=opts["time_units"] or "s",
              counts_per_g=opts["counts_per_g"], delimiter=opts["delimiter"], temp_units=opts["temp_units"] or "C",
              keep_optional=keep_optional)
    if any(v is not None for v in opts.values()):
        return import_log(path, **kw)
    try:
        return read_log(path, keep_optional)
    except StationError as exc:
        if "missing column" not in str(exc):
            raise
        try:
            return import_log(path, **kw)
        except StationError:
            raise exc from None


__all__ = ["import_log", "parse_import", "parse_columns", "sniff_delimiter", "add_import_arguments", "read_any_log",
           "ACCEL_UNITS", "TIME_SCALE", "TEMP_UNITS"]
