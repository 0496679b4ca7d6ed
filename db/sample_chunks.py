"""The samples part of the database writer (db/writer.py): each run's stream as compressed chunks.

Every writer transaction appends each run's new samples as one small chunk (durable at once); once
a run has `seal_samples` samples in small chunks, they are replaced, in the same transaction, by
one sealed chunk, which compresses far better. A crash at any point leaves either the small chunks
or the sealed one, never both and never neither. After a restart the writer picks up a run's
unsealed chunks (`RunBuf`) and goes on compacting them.

One transaction stores the new samples of every run with a fixed number of statements, each
executed once for all runs (a parameter set per run): the runs' counters in one UPDATE, the small
chunks in one INSERT, and the seals' deletes and sealed chunks in one DELETE and one INSERT. Why:
the writer thread shares the daemon's GIL, so its Python time is latency for the event loop that
ingests the samples and answers the web; with 64 DUTs and a commit every 0.2 s, statements built
per run (two or four ORM statements each) cost it more than the database did.

Runs in the writer thread only; `snapshot()`/`restore()` undo a transaction that rolled back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable

from sqlalchemy import bindparam, delete, insert, select, update
from sqlalchemy.engine import Connection

from contracts.events import SamplesReceived
from db import codec
from db.models import DutRun, SampleChunk


@dataclass
class RunBuf:
    """A run's small chunks not sealed yet: their samples, row ids and first seq."""

    next_seq: int
    pending: list[codec.Quantized] = field(default_factory=list)
    pending_ids: list[int] = field(default_factory=list)
    pending_first_seq: int | None = None
    pending_n: int = 0
    pending_lost: int = 0

    def copy(self) -> "RunBuf":
        return RunBuf(
            self.next_seq, list(self.pending), list(self.pending_ids), self.pending_first_seq, self.pending_n,
            self.pending_lost,
        )


_RUNS = DutRun.__table__
_CHUNKS = SampleChunk.__table__
# Built once (Core, on the tables), each executed with a list of parameter sets.
_ADD_SAMPLES = (update(_RUNS).where(_RUNS.c.id == bindparam("run"))
                .values(n_samples=_RUNS.c.n_samples + bindparam("add_n"),
                        lost_samples=_RUNS.c.lost_samples + bindparam("add_lost")))
_INSERT_CHUNK = insert(_CHUNKS).returning(_CHUNKS.c.id, sort_by_parameter_order=True)
_DELETE_CHUNK = delete(_CHUNKS).where(_CHUNKS.c.id == bindparam("chunk"))


SMALL_CHUNK_LEVEL = 1  # zlib level of a small chunk: it lives until its run's seal replaces it
SEALED_CHUNK_LEVEL = 3  # a sealed chunk: 97 % of level 6's compression at a quarter of its CPU (issue 40)


def chunk_row(run_id: int, seq: int, q: codec.Quantized, lost: int, sealed: bool) -> dict[str, Any]:
    """The sample_chunk row of q (its data compressed by db/codec.py). A small chunk is compressed
    fast (it is replaced by the sealed one within seal_samples samples: its size matters little, the
    writer's CPU time, which shares the GIL with the event loop, does); a sealed one well."""
    return {"run_id": run_id, "seq": seq, "t_first_s": float(q.time[0]) / codec.TIME_SCALE,
            "t_last_s": float(q.time[-1]) / codec.TIME_SCALE, "n": len(q), "lost_samples": int(lost),
            "sealed": sealed,
            "data": codec.encode(q, SEALED_CHUNK_LEVEL if sealed else SMALL_CHUNK_LEVEL)}


class SampleChunks:
    """Each run's chunk bookkeeping (run id -> RunBuf) and the statements that store samples."""

    def __init__(self, seal_samples: int) -> None:
        self.seal_samples = seal_samples
        self.bufs: dict[int, RunBuf] = {}

    def snapshot(self) -> dict[int, RunBuf]:
        return {k: v.copy() for k, v in self.bufs.items()}

    def restore(self, saved: dict[int, RunBuf]) -> None:
        self.bufs = saved

    def buf(self, conn: Connection, run_id: int) -> RunBuf:
        buf = self.bufs.get(run_id)
        if buf is None:
            # First time this process sees the run (fresh or resumed): continue its chunk sequence
            # and take over any unsealed chunks a previous process left.
            rows = conn.execute(
                select(SampleChunk.id, SampleChunk.seq, SampleChunk.sealed, SampleChunk.lost_samples)
                .where(SampleChunk.run_id == run_id)
                .order_by(SampleChunk.seq)
            ).all()
            buf = RunBuf(next_seq=(rows[-1].seq + 1) if rows else 0)
            tail = []
            for r in reversed(rows):
                if r.sealed:
                    break
                tail.append(r)
            data = dict(
                conn.execute(select(SampleChunk.id, SampleChunk.data).where(SampleChunk.id.in_([r.id for r in tail]))).all()
            ) if tail else {}
            for r in reversed(tail):
                q = codec.decode(data[r.id])
                buf.pending.append(q)
                buf.pending_ids.append(r.id)
                buf.pending_n += len(q)
                buf.pending_lost += r.lost_samples
                if buf.pending_first_seq is None:
                    buf.pending_first_seq = r.seq
            self.bufs[run_id] = buf
        return buf

    def store(self, conn: Connection, samples: dict[int, list[SamplesReceived]], seal: set[int]) -> int:
        """Every run's new samples of one transaction (run id -> its SamplesReceived); returns how
        many were stored. A run in `seal` (ended) is sealed now and taken out of the set; a run
        with `seal_samples` samples in small chunks is sealed too."""
        new: list[tuple[int, list[codec.Quantized], int, int]] = []  # run id, parts, n, lost
        counters = []
        for run_id, evs in samples.items():
            parts = []
            lost = 0
            for ev in evs:
                b = ev.block
                lost += b.lost_samples
                if len(b):
                    parts.append(codec.quantize(b.time_s, b.acc_g, b.temp_c, 1 if ev.lamp_on else 0, ev.position))
            n = sum(len(p) for p in parts)
            if n:
                counters.append({"run": run_id, "add_n": n, "add_lost": lost})
            new.append((run_id, parts, n, lost))
        if counters:
            conn.execute(_ADD_SAMPLES, counters)
        total = 0
        rows: list[dict[str, Any]] = []
        owners: list[tuple[RunBuf, int]] = []
        to_seal: list[int] = []
        for run_id, parts, n, lost in new:
            force_seal = run_id in seal
            seal.discard(run_id)
            buf = self.buf(conn, run_id)
            if not n:
                if force_seal:
                    to_seal.append(run_id)
                continue
            total += n
            q = codec.Quantized.concat(parts) if len(parts) > 1 else parts[0]
            buf.pending.append(q)
            buf.pending_n += n
            buf.pending_lost += lost
            if force_seal or buf.pending_n >= self.seal_samples:
                to_seal.append(run_id)
            else:
                seq = buf.next_seq
                buf.next_seq += 1
                rows.append(chunk_row(run_id, seq, q, lost, sealed=False))
                owners.append((buf, seq))
        if rows:
            ids = conn.execute(_INSERT_CHUNK, rows).scalars().all()
            for (buf, seq), cid in zip(owners, ids, strict=True):
                buf.pending_ids.append(int(cid))
                if buf.pending_first_seq is None:
                    buf.pending_first_seq = seq
        self.seal(conn, to_seal)
        return total

    def seal(self, conn: Connection, run_ids: Iterable[int]) -> None:
        """Replace each run's small chunks (plus unwritten samples) by one sealed chunk."""
        gone: list[dict[str, int]] = []
        rows: list[dict[str, Any]] = []
        for run_id in run_ids:
            buf = self.buf(conn, run_id)
            if not buf.pending:
                continue
            if buf.pending_ids:
                gone.extend({"chunk": cid} for cid in buf.pending_ids)
                seq = buf.pending_first_seq
            else:
                seq = buf.next_seq
                buf.next_seq += 1
            q = codec.Quantized.concat(buf.pending) if len(buf.pending) > 1 else buf.pending[0]
            rows.append(chunk_row(run_id, int(seq), q, buf.pending_lost, sealed=True))
            buf.pending, buf.pending_ids, buf.pending_first_seq, buf.pending_n, buf.pending_lost = [], [], None, 0, 0
        if gone:  # first: a sealed chunk takes the seq of the first small chunk it replaces
            conn.execute(_DELETE_CHUNK, gone)
        if rows:
            conn.execute(_INSERT_CHUNK, rows)


__all__ = ["SampleChunks", "RunBuf", "chunk_row"]
