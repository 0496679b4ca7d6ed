"""The station's journal: events the database has not taken yet, durable on the station's own disk.

Why: a station must keep testing, judging and ending its batches while its database blinks (a
PostgreSQL restart, a hung server, a network outage of hours on a line, a SQLite file locked by
another process). The writer (db/writer.py) commits straight to the database while it answers;
from the moment a commit fails, it writes what it holds, and every event after it, here instead, and
forwards them to the database, oldest first, once it takes writes again. An event in the journal is
as safe as one in the database (a SQLite file with synchronous=FULL: fsync'd before `append`
returns), so a batch may end `finished` and its runs be judged while their records wait here;
`/api/health` and the page say how many wait ("forwarding").

Order and exactly-once: every event gets a sequence number when it is submitted (`seq`); the
journal keeps them by that number and gives them back in that order, so a forwarded record lands as
it would have without the outage (samples before their run's end, a verdict after its results). An
entry is removed in the same step that confirms the database committed it; a crash between the two
can forward a batch of entries twice only if the database committed and the station died before
`remove` returned (a window of one fsync).

The file is a SQLite database of one table (seq, kind, payload), separate from the station's
database on purpose: the database may be the thing that is locked, deleted or down. Payloads are
JSON (zlib-compressed); numpy arrays travel as their float64 bytes (base64), so a forwarded sample
is bit-identical to the one the board sent. Only this station's own event types are read back
(contracts/events.py): the file is never a way to run code.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import logging
import sqlite3
import threading
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from contracts import events as ev_mod
from contracts.events import Event
from contracts.run_records import ProgramRecord, ThermalReport
from contracts.sfem_result import SfemResult
from contracts.types import SampleBlock, Segment

log = logging.getLogger(__name__)

_EVENT_TYPES: dict[str, type] = {
    cls.__name__: cls for cls in vars(ev_mod).values()
    if isinstance(cls, type) and issubclass(cls, Event) and cls is not Event
}
_NESTED: dict[str, type] = {"SampleBlock": SampleBlock, "Segment": Segment}
# typed run records travel as their own JSON (their one codec, contracts/run_records.py)
_RECORDS: dict[str, type[ThermalReport] | type[SfemResult] | type[ProgramRecord]] = {
    "ThermalReport": ThermalReport, "SfemResult": SfemResult, "ProgramRecord": ProgramRecord}


def _encode(value: Any) -> Any:
    if isinstance(value, (ThermalReport, SfemResult, ProgramRecord)):
        return {"__record__": type(value).__name__, "json": _encode(value.to_json())}
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value, dtype=np.float64)
        return {"__nd__": base64.b64encode(arr.tobytes()).decode("ascii"), "shape": list(arr.shape)}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = {f.name: _encode(getattr(value, f.name)) for f in dataclasses.fields(value)}
        out["__type__"] = type(value).__name__
        return out
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v) for v in value]}
    if isinstance(value, list):
        return [_encode(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _encode(v) for k, v in value.items()}
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value


def _decode(value: Any) -> Any:
    if isinstance(value, list):
        return [_decode(v) for v in value]
    if not isinstance(value, dict):
        return value
    if "__nd__" in value:
        return np.frombuffer(base64.b64decode(value["__nd__"]), dtype=np.float64).reshape(value["shape"]).copy()
    if "__tuple__" in value:
        return tuple(_decode(v) for v in value["__tuple__"])
    if "__record__" in value:
        record = _RECORDS.get(value["__record__"])
        if record is None:
            raise ValueError(f"journal: unknown record {value['__record__']!r}")
        return record.from_json(_decode(value["json"]))
    kind = value.get("__type__")
    if kind is not None:
        cls = _EVENT_TYPES.get(kind) or _NESTED.get(kind)
        if cls is None:
            raise ValueError(f"journal: unknown type {kind!r}")
        return cls(**{k: _decode(v) for k, v in value.items() if k != "__type__"})
    return {k: _decode(v) for k, v in value.items()}


def encode_event(event: Event) -> bytes:
    """One event as the journal stores it (compressed JSON; arrays exact)."""
    if type(event).__name__ not in _EVENT_TYPES:
        raise ValueError(f"journal: not a station event: {type(event).__name__}")
    return zlib.compress(json.dumps(_encode(event), allow_nan=True, separators=(",", ":")).encode("utf-8"), 1)


def decode_event(payload: bytes) -> Event:
    """The event `encode_event` stored (ValueError for anything else)."""
    data = json.loads(zlib.decompress(payload).decode("utf-8"))
    if not isinstance(data, dict) or data.get("__type__") not in _EVENT_TYPES:
        raise ValueError("journal: an entry that is not a station event")
    event = _decode(data)
    assert isinstance(event, Event)
    return event


class Journal:
    """One station's journal file: `append` (durable on return), `oldest`, `remove`, `pending`."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path).expanduser()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._conn = sqlite3.connect(str(self.path), timeout=5.0, check_same_thread=False, isolation_level=None)
        self._conn.execute("PRAGMA journal_mode=WAL")
        self._conn.execute("PRAGMA synchronous=FULL")
        # token: the writer transaction these entries were in when its answer was lost (a commit
        # that may have happened: the writer asks the database for the token before it stores them
        # again); NULL for entries never sent
        self._conn.execute("CREATE TABLE IF NOT EXISTS journal (seq INTEGER PRIMARY KEY, kind TEXT NOT NULL, "
                           "batch_id INTEGER NOT NULL, payload BLOB NOT NULL, token TEXT)")
        self._pending = int(self._conn.execute("SELECT COUNT(*) FROM journal").fetchone()[0])
        self._max_seq = int(self._conn.execute("SELECT COALESCE(MAX(seq), 0) FROM journal").fetchone()[0])

    @property
    def pending(self) -> int:
        """Entries waiting to be forwarded (kept in memory: read by health every poll)."""
        return self._pending

    @property
    def max_seq(self) -> int:
        """The highest sequence number held (a restarted writer numbers its events after it)."""
        return self._max_seq

    def append(self, entries: list[tuple[int, Event]], token: str | None = None) -> int:
        """Store (seq, event) pairs in one fsync'd transaction; a seq already held is kept once.
        token: the writer transaction they were in, if its outcome is unknown. Returns how many
        were new."""
        if not entries:
            return 0
        rows = [(int(seq), e.kind, int(e.batch_id or 0), encode_event(e), token) for seq, e in entries]
        with self._lock:
            before = self._conn.total_changes
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                self._conn.executemany("INSERT OR IGNORE INTO journal (seq, kind, batch_id, payload, token) "
                                       "VALUES (?, ?, ?, ?, ?)", rows)
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            added = self._conn.total_changes - before
            self._pending += added
            self._max_seq = max(self._max_seq, max(r[0] for r in rows))
        return added

    def oldest(self, limit: int) -> list[tuple[int, Event]]:
        """Up to `limit` entries, oldest first. An entry that cannot be read back (a file damaged
        by hand) is logged and removed: it would block every later one for ever."""
        with self._lock:
            rows = self._conn.execute("SELECT seq, payload FROM journal ORDER BY seq LIMIT ?", (int(limit),)).fetchall()
        out: list[tuple[int, Event]] = []
        bad: list[int] = []
        for seq, payload in rows:
            try:
                out.append((int(seq), decode_event(payload)))
            except Exception as exc:  # noqa: BLE001 - any damage: one entry, named, never the rest
                log.error("journal %s: entry %d unreadable (%s): removed", self.path, seq, exc)
                bad.append(int(seq))
        if bad:
            self.remove(bad)
        return out

    def remove(self, seqs: list[int]) -> None:
        """Forget entries the database has committed."""
        if not seqs:
            return
        with self._lock:
            before = self._conn.total_changes
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                self._conn.executemany("DELETE FROM journal WHERE seq = ?", [(int(s),) for s in seqs])
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._pending -= self._conn.total_changes - before

    def tokens(self, seqs: list[int]) -> dict[str, list[int]]:
        """{token: [seqs]} of those entries that were in a transaction whose outcome is unknown."""
        if not seqs:
            return {}
        out: dict[str, list[int]] = {}
        with self._lock:
            for i in range(0, len(seqs), 500):
                part = [int(x) for x in seqs[i:i + 500]]
                q = f"SELECT token, seq FROM journal WHERE token IS NOT NULL AND seq IN ({','.join('?' * len(part))})"
                for token, seq in self._conn.execute(q, part):
                    out.setdefault(str(token), []).append(int(seq))
        return out

    def set_token(self, seqs: list[int], token: str | None) -> None:
        """Mark entries held as in a transaction whose outcome is unknown (token), or, once it is
        known not to have happened, as plain entries again (None)."""
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                self._conn.executemany("UPDATE journal SET token = ? WHERE seq = ?", [(token, int(x)) for x in seqs])
                self._conn.execute("COMMIT")
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise

    def batches(self) -> dict[int, int]:
        """Entries waiting per batch id (the page's 'waiting to be forwarded')."""
        with self._lock:
            rows = self._conn.execute("SELECT batch_id, COUNT(*) FROM journal GROUP BY batch_id").fetchall()
        return {int(b): int(n) for b, n in rows}

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def journal_path_for(url: str, station: str = "") -> Path | None:
    """Where a database's journal lives by default: beside a SQLite file (`<file>.journal`); for a
    server database, in the station's state folder (~/.local/state/station/<station>.journal).
    None for a temporary database (a test or a quick demo without a URL: nothing to survive)."""
    from sqlalchemy.engine import make_url

    from contracts.filenames import safe_name

    u = make_url(url)
    if u.get_backend_name() == "sqlite":
        db = u.database or ""
        if db in ("", ":memory:") or db.startswith("file:"):
            return None
        p = Path(db).expanduser()
        return p.with_name(p.name + ".journal")
    name = safe_name(f"{station or 'station'}-{u.host or 'local'}-{u.port or ''}-{u.database or ''}")
    return Path("~/.local/state/station").expanduser() / f"{name}.journal"


__all__ = ["Journal", "encode_event", "decode_event", "journal_path_for"]
