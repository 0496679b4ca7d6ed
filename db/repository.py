"""The read side for the web page, REST API and MES, plus the MES outbox: one name to import.

Why a facade: callers write `from db import repository as repo; repo.batch_detail(db, 7)` and need
not know which module answers. Every function takes a db.Database and returns plain JSON-ready
dicts (times as ISO 8601 UTC), or None for an unknown serial / run / batch so the web layer can
answer 404. Where each concern lives:

    db/row_json.py        the JSON shapes (a run, a verdict, results, segments, outbox messages) and
                          run_results, a run's latest results
    db/queries_history.py DUTs, runs, segments, batches, replays, program records, sample bytes
    db/queries_mes.py     the MES feed (results_since) and the outbox (enqueue, pending, delivered)
    db/mes_record.py      a record's idempotency key (mes_key), cursor (take_result_seq), revision
    db/queries_records.py yield, judged runs and their facets (SPC, Pareto, the Records view)
    db/queries_audit.py   the audit trail (append, list)
"""

from __future__ import annotations

from db.mes_record import mes_key, revision_of
from db.queries_audit import audit_append, audit_list
from db.queries_history import (
    batch_detail,
    dut_by_serial,
    is_attempt,
    list_batches,
    program_record,
    real_batches,
    replay_diff,
    replays,
    run_detail,
    run_sample_bytes,
    runs_of_dut,
    search_duts,
    segments_of_run,
)
from db.queries_mes import (
    outbox_enqueue,
    outbox_enqueue_new,
    outbox_mark_delivered,
    outbox_mark_failed,
    outbox_pending,
    results_since,
)
from db.queries_records import judged_facets, judged_runs, yields
from db.row_json import (
    PREFERRED_THERMAL,
    VALID_VERDICTS,
    JsonAnswer,
    outbox_json,
    program_verify_json,
    record_verdict_json,
    run_results,
    segment_json,
    sfem_json,
    thermal_json,
    trace_json,
    verdict_json,
)

result_key = mes_key  # the name this module gave the MES idempotency key; the one definition is mes_key
_run_results = run_results  # the old private name (station/replay/recording.py reads R._run_results)

__all__ = [
    "search_duts",
    "result_key",
    "mes_key",
    "dut_by_serial",
    "runs_of_dut",
    "run_detail",
    "segments_of_run",
    "results_since",
    "revision_of",
    "audit_append",
    "outbox_enqueue_new",
    "judged_runs",
    "judged_facets",
    "audit_list",
    "batch_detail",
    "yields",
    "verdict_json",
    "list_batches",
    "run_sample_bytes",
    "outbox_enqueue",
    "outbox_pending",
    "outbox_mark_delivered",
    "outbox_mark_failed",
    "program_record",
    "replays",
    "replay_diff",
    "run_results",
    "real_batches",
    "is_attempt",
    "JsonAnswer",
    "PREFERRED_THERMAL",
    "VALID_VERDICTS",
    "outbox_json",
    "program_verify_json",
    "record_verdict_json",
    "segment_json",
    "sfem_json",
    "thermal_json",
    "trace_json",
]
