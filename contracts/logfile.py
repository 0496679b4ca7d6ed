"""The per-DUT log file (design 5.1, CONTRACT): read and write.

    # serial: SIM0001
    # sensor: LIS3DSH
    time_s,ax_g,ay_g,az_g,temp_c[,lamp][,position][,ref_x,ref_y,ref_z]

The station writes this for every DUT run and reads it back for `calibrate`, `sfem`, `diagnose`.
Every log read is looked at before any science: the checks themselves (header numbers, units,
temperature, time order, ...) are contracts/log_checks.py, shared with the import of other tools'
logs; `check_log` runs them on a DutLog already in memory.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn, TextIO, TypeVar

import numpy as np

from contracts.log_checks import LogChecker, _show, check_meta
from contracts.log_checks import guess_accel_units  # noqa: F401 - also reachable as contracts.logfile.guess_accel_units
from contracts.types import SampleBlock, StationError

_T = TypeVar("_T")

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


CHUNK_BYTES = 1 << 18  # text read and parsed per step (256 KiB): memory stays ~ the final arrays
# A file that is not text is refused as soon as its first such block is read (2 GB of NUL bytes
# after a valid start were once read as one 2 GB "line": 12.7 GB of memory and 93 s): a NUL byte,
# a byte that is not UTF-8, or a line longer than this. A log's lines are ~100 characters.
MAX_LINE_CHARS = 1 << 16
_NOT_TEXT = re.compile("[\x00\udc80-\udcff]")  # NUL; undecodable bytes (surrogateescape)
BOM = "\ufeff"  # a spreadsheet's "CSV UTF-8" starts with one: not part of the first line


def _check_text(block: str, lines: list[str], before: int, source: str) -> None:
    """One block of a file's text (`before` lines precede it): a NUL byte in a header or data row,
    undecodable bytes or an overlong line is one StationError line naming the file's line. A NUL in
    a `#` line is the metadata's own business (a hostile serial is made safe where it is used)."""
    # ASCII text (what str knows without a look) holds no undecodable byte: only a NUL to find
    if ("\x00" in block) if block.isascii() else (_NOT_TEXT.search(block) is not None):
        for k, ln in enumerate(lines):
            if _NOT_TEXT.search(ln) is None:
                continue
            bad = next((c for c in _NOT_TEXT.findall(ln) if c != "\x00"), None)
            if bad is not None:
                raise StationError(f"{source}: line {before + k + 1}: byte 0x{ord(bad) - 0xDC00:02x} is not UTF-8 "
                                   "text: save the log as UTF-8 (CSV UTF-8)")
            if not ln.lstrip().startswith("#"):
                raise StationError(f"{source}: line {before + k + 1}: NUL byte: not a text log "
                                   "(a binary file or a damaged copy?)")
    if len(block) > MAX_LINE_CHARS and lines and max(map(len, lines)) > MAX_LINE_CHARS:
        k = next(k for k, ln in enumerate(lines) if len(ln) > MAX_LINE_CHARS)
        raise StationError(f"{source}: line {before + k + 1}: longer than {MAX_LINE_CHARS} characters: "
                           "not a text log (a binary file or a damaged copy?)")


def _blocks_of_text(text: str, size: int = CHUNK_BYTES, source: str = "<log>") -> Iterator[list[str]]:
    """The lines of `text` (str.splitlines, as before) a few MB at a time; a leading BOM skipped,
    text that is no log refused (_check_text)."""
    pos, n = (1 if text.startswith(BOM) else 0), len(text)
    before = 0
    while pos < n:
        end = min(pos + size, n)
        if end < n:
            nl = text.find("\n", end)
            end = n if nl < 0 else nl + 1
        block = text[pos:end]
        lines = block.splitlines()
        _check_text(block, lines, before, source)
        before += len(lines)
        yield lines
        pos = end


def _blocks_of_file(f: TextIO, source: str = "<log>") -> Iterator[list[str]]:
    """The lines of a text file (universal newlines, then str.splitlines: what read_text().
    splitlines() gave before) a few MB at a time, never more than CHUNK_BYTES + MAX_LINE_CHARS
    characters in memory; text that is no log refused as soon as it is read (_check_text)."""
    before = 0
    while True:
        block = f.read(CHUNK_BYTES)
        if not block:
            return
        if not block.endswith("\n"):
            block += f.readline(MAX_LINE_CHARS + 1)  # bounded: a longer line fails _check_text
        lines = block.splitlines()
        _check_text(block, lines, before, source)
        before += len(lines)
        yield lines


class _Header:
    """The metadata and header row at the top of a log; `rows()` then yields the data lines."""

    def __init__(self, blocks: Iterator[list[str]], is_meta: Callable[[str], bool]) -> None:
        self.meta: dict[str, str] = {}
        self.line: str | None = None
        self.line_no = 0
        self._blocks = blocks
        self._rest: list[str] = []
        base = 0
        for block in blocks:
            for i, ln in enumerate(block):
                if is_meta(ln):
                    body = ln.strip().lstrip("#").strip()
                    if ":" in body:
                        key, value = body.split(":", 1)
                        self.meta[key.strip()] = value.strip()
                    continue
                self.line, self.line_no = ln.rstrip("\r\n"), base + i + 1
                self._rest = block[i + 1:]
                return
            base += len(block)

    def rows(self) -> Iterator[tuple[list[str], np.ndarray]]:
        """(data lines, their 1-based line numbers in the file) per block; blank lines and
        `#` lines skipped."""
        first = self.line_no + 1
        for block in _chain([self._rest], self._blocks):
            n = len(block)
            keep: Sequence[int]
            if _plain_rows(block):  # the usual block: no line to skip, and no look at each line
                keep = range(n)
            else:
                keep = [k for k, ln in enumerate(block) if ln.strip() and not ln.lstrip().startswith("#")]
            if len(keep) == n:
                rows, nos = block, np.arange(first, first + n, dtype=np.int64)
            else:
                rows, nos = [block[k] for k in keep], first + np.asarray(keep, dtype=np.int64)
            first += n
            if rows:
                yield rows, nos


_SKIP_MARKS = (" ", "\t", "\r", "\x1f", "#")  # what a blank (str.strip) or `#` line of ASCII text must hold


def _plain_rows(block: list[str]) -> bool:
    """True when no line of the block is blank or a `#` line (the test rows() applies line by line),
    decided on the joined text: ASCII text without an empty line, a `#` or any whitespace that
    str.strip() removes ('\n' joins the lines; '\x0b', '\x0c', '\x1c'-'\x1e' end a line in
    str.splitlines, so no line holds one). False means: look at each line."""
    if not block or not block[0] or not block[-1]:
        return False
    text = "\n".join(block)
    return text.isascii() and "\n\n" not in text and not any(c in text for c in _SKIP_MARKS)


def _chain(*iterables: Iterable[_T]) -> Iterator[_T]:
    for it in iterables:
        yield from it


def _parse_rows(rows: list[str], nos: np.ndarray, ncol: int, delimiter: str, source: str,
                lenient: bool) -> tuple[np.ndarray, np.ndarray]:
    """float64 (m, ncol) of the rows. Strict (design 5.1): the first malformed row is an error
    with its line number. Lenient (logs from other tools): rows with another field count are
    skipped and fields that are not numbers are NaN."""
    try:
        data = np.loadtxt(rows, delimiter=delimiter, dtype=np.float64, ndmin=2, quotechar='"' if lenient else None)
        if data.shape[1] == ncol:
            return data, nos
        exc: Exception = ValueError(f"{data.shape[1]} fields")
    except ValueError as e:
        exc = e
    if not lenient:
        _raise_bad_row(rows, nos, ncol, delimiter, source, exc)
    out, keep = [], []
    for k, ln in enumerate(rows):
        fields = ln.split("#", 1)[0].strip().split(delimiter)
        if len(fields) != ncol:
            continue
        out.append([_float_or_nan(x) for x in fields])
        keep.append(k)
    if not out:
        return np.empty((0, ncol)), nos[:0]
    return np.asarray(out, dtype=np.float64), nos[np.asarray(keep)]


def _float_or_nan(x: str) -> float:
    try:
        return float(x.strip().strip('"'))
    except ValueError:
        return math.nan


def _raise_bad_row(rows: list[str], nos: np.ndarray, ncol: int, delimiter: str, source: str,
                   exc: Exception) -> NoReturn:
    for k, ln in enumerate(rows):
        fields = ln.split("#", 1)[0].strip().split(delimiter)
        if len(fields) != ncol:
            raise StationError(f"{source}: line {nos[k]}: malformed data row ({len(fields)} fields, the header has {ncol})")
        for x in fields:
            try:
                float(x)
            except ValueError:
                why = f"cannot read {_show(x)!r} as a number"
                raise StationError(f"{source}: line {nos[k]}: malformed data row ({why})") from None
    raise StationError(f"{source}: malformed data row ({exc})")


def check_log(log: "DutLog", source: str = "<log>") -> None:
    """Every check read_log makes (header numbers, finite samples, lamp/position, units, temperature,
    time order, odr_hz against the times), on a DutLog already in memory; raises StationError with
    one line (rows are counted from 1 here, there are no file lines)."""
    check_meta(log.meta, source)
    chk = LogChecker(source, capacity=len(log), store=False)
    step = 1 << 16
    for a in range(0, len(log), step):
        b = a + step
        chk.add(log.time_s[a:b], np.asarray(log.acc_g[a:b], dtype=np.float64), log.temp_c[a:b],
                None if log.lamp is None else log.lamp[a:b], None if log.position is None else log.position[a:b])
    chk.temp_for_median = log.temp_c  # for the kelvin median in finish (not stored, not resized)
    chk.finish(log.meta)


# What DutLog.lamp, .position and .ref_dir hold a file's optional columns in: `read_log(path,
# keep_optional=...)` names the ones a command uses; the others are still read and checked, not kept
# (a 200 MB log's ref_x/y/z are 24 bytes a row, ~60 MB, that `station calibrate` never looks at).
OPTIONAL_FIELDS = frozenset({"lamp", "position", "ref_dir"})


def _kept(keep_optional: Iterable[str] | None) -> frozenset[str]:
    if keep_optional is None:
        return OPTIONAL_FIELDS
    keep = frozenset(keep_optional)
    unknown = keep - OPTIONAL_FIELDS
    if unknown:
        raise ValueError(f"keep_optional: unknown field(s) {sorted(unknown)} (known: {sorted(OPTIONAL_FIELDS)})")
    return keep


def read_log(path: str | Path, keep_optional: Iterable[str] | None = None) -> DutLog:
    """Read a log file; raises StationError with one clear line for any user mistake, including a
    log whose numbers cannot be right (check_log). The file is read a few MB at a time.
    keep_optional: the DutLog fields among lamp, position, ref_dir to keep when the file has their
    columns (None: all); the others are read and checked all the same, then left as None."""
    p = Path(path)
    if not p.exists():
        raise StationError(f"{p}: no such file")
    if p.is_dir():
        raise StationError(f"{p}: is a directory, expected a CSV log file")
    try:  # utf-8-sig: a leading BOM (a spreadsheet's "CSV UTF-8") is skipped
        with open(p, encoding="utf-8-sig", errors="surrogateescape") as f:
            return _parse(_blocks_of_file(f, str(p)), str(p), size=p.stat().st_size, keep=_kept(keep_optional))
    except (OSError, UnicodeDecodeError) as exc:
        raise StationError(f"{p}: cannot read ({exc})") from None


def parse_log(text: str, source: str = "<log>") -> DutLog:
    return _parse(_blocks_of_text(text, source=source), source, size=len(text))


def _is_meta(line: str) -> bool:
    return line.startswith("#") or not line.strip()


def _parse(blocks: Iterator[list[str]], source: str, size: int, keep: frozenset[str] = OPTIONAL_FIELDS) -> DutLog:
    head = _Header(blocks, _is_meta)
    meta = head.meta
    if head.line is None:
        raise StationError(f"{source}: no header row (expected columns {','.join(REQUIRED_COLUMNS)})")
    header = [h.strip() for h in head.line.split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise StationError(f"{source}: missing column(s) {', '.join(missing)} (header is {','.join(header)})")
    check_meta(meta, source)
    col = {name: k for k, name in enumerate(header)}
    has_ref = all(c in col for c in ("ref_x", "ref_y", "ref_z"))
    acc_cols = [col["ax_g"], col["ay_g"], col["az_g"]]
    ref_cols = [col["ref_x"], col["ref_y"], col["ref_z"]] if has_ref else None
    chk: LogChecker | None = None
    for rows, nos in head.rows():
        data, nos = _parse_rows(rows, nos, len(header), ",", source, lenient=False)
        if chk is None:  # capacity from the first block's bytes per row
            per_row = max(1.0, sum(map(len, rows)) / len(rows))
            chk = LogChecker(source, capacity=int(size / per_row * 1.02) + 1024,
                             lamp="lamp" in col and "lamp" in keep, position="position" in col and "position" in keep,
                             ref=has_ref and "ref_dir" in keep)
        chk.add(data[:, col["time_s"]], data[:, acc_cols], data[:, col["temp_c"]],
                data[:, col["lamp"]] if "lamp" in col else None,
                data[:, col["position"]] if "position" in col else None,
                data[:, ref_cols] if has_ref else None, lines=nos)
    if chk is None or chk.n == 0:
        return _empty_log(meta, header)
    chk.finish(meta)
    assert chk.time is not None and chk.acc is not None and chk.temp is not None  # stored (store=True)
    return DutLog(time_s=chk.time, acc_g=chk.acc, temp_c=chk.temp, meta=meta,
                  lamp=chk.lamp, position=chk.position, ref_dir=chk.ref)


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
        cols.append("lamp")
        arrays.append(log.lamp)
        fmts.append("%d")
    if log.position is not None:
        cols.append("position")
        arrays.append(log.position)
        fmts.append("%d")
    if log.ref_dir is not None:
        for k, name in enumerate(("ref_x", "ref_y", "ref_z")):
            cols.append(name)
            arrays.append(log.ref_dir[:, k])
            fmts.append("%.6f")
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


__all__ = ["DutLog", "read_log", "parse_log", "check_log", "format_log", "write_log", "REQUIRED_COLUMNS",
           "OPTIONAL_FIELDS"]
