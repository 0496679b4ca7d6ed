"""What the web needs from storage, as one small interface.

Routes and the MES outbox call these methods only; `DbRepository` maps them onto the db
package's repository functions. Keeping the mapping here means a change in db/ touches one file.
Every method is synchronous (SQLite); routes call them from the thread pool.
"""

from __future__ import annotations

import abc
from typing import Any

from contracts.logfile import DutLog


class WebRepository(abc.ABC):
    # --- DUT history -------------------------------------------------------------------------
    @abc.abstractmethod
    def search_duts(self, serial_like: str | None, limit: int = 50) -> list[dict]:
        """DUT summaries whose serial contains serial_like (case-insensitive), newest first."""

    @abc.abstractmethod
    def dut(self, serial: str) -> dict | None:
        """The DUT with its latest results, or None when the serial was never tested."""

    @abc.abstractmethod
    def runs_of_dut(self, serial: str) -> list[dict] | None:
        """Every run of a DUT, newest first, each with its results; None for an unknown serial."""

    @abc.abstractmethod
    def run(self, run_id: int) -> dict | None: ...

    def batch(self, batch_id: int) -> dict | None:
        """A stored batch (for batches the daemon no longer holds, e.g. after a restart)."""
        return None

    @abc.abstractmethod
    def segments(self, run_id: int) -> list[dict] | None:
        """Segments logged in a run (None for an unknown run)."""

    @abc.abstractmethod
    def run_log(self, run_id: int) -> DutLog | None:
        """The run's sample stream as a design 5.1 log (None for an unknown run)."""

    # --- MES ---------------------------------------------------------------------------------
    @abc.abstractmethod
    def results_since(self, after_id: int = 0, since_time: float | None = None, limit: int = 100,
                      station: str | None = None) -> list[dict]:
        """Verdict records (a run's final verdict, and each later one that supersedes it) with
        id > after_id (and judged at/after since_time, and of that station when given), oldest
        first.

        Each: {"id", "idempotency_key", "revision", "supersedes", "serial", "run_id", "batch_id",
        "slot", "created_at", "thermal", "sfem", verdict fields}.
        """

    @abc.abstractmethod
    def outbox_enqueue(self, idempotency_key: str, payload: dict) -> bool:
        """Queue a webhook delivery; a key already queued is not queued again (returns False)."""

    @abc.abstractmethod
    def outbox_due(self, now: float, limit: int = 20) -> list[dict]:
        """Undelivered entries due at `now`: {"id","idempotency_key","payload","attempts"}."""

    @abc.abstractmethod
    def outbox_mark_delivered(self, entry_id: int) -> None: ...

    @abc.abstractmethod
    def outbox_mark_failed(self, entry_id: int, error: str, next_attempt_at: float) -> None: ...

    def outbox_high_water(self) -> int:
        """Highest result id already enqueued (0 = scan everything)."""
        return 0

    def outbox_list(self, limit: int = 100) -> list[dict]:
        return []

    def yields(self, batch_id: int | None = None) -> dict:
        """First-pass and final yield (db.repository.yields)."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no yields")

    def audit_append(self, actor: str, action: str, target: str = "", detail: dict | None = None) -> None:
        """Record one audited REST action (web/audit.py); without a database only the log has it."""
        import logging

        logging.getLogger("station.web.audit").info("audit %s by %s: %s %s", action, actor, target, detail or {})

    def audit_list(self, limit: int = 100, before_id: int | None = None, station: str | None = None) -> list[dict]:
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no audit trail")

    def judged_runs(self, limit: int = 5000, station: str | None = None, **filters: Any) -> list[dict]:
        """Judged runs with their verdict checks, oldest first; filters as db.repository.judged_runs."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no SPC")

    def judged_facets(self, judged_from: Any = None, judged_to: Any = None) -> list[dict]:
        """What judged runs can be filtered by (db.repository.judged_facets)."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no SPC")

    def replays(self, limit: int = 50) -> list[dict]:
        """Replay batches with their comparison summary (db.repository.replays)."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no replays")

    def replay(self, batch_id: int) -> dict | None:
        return None

    def certificate_pdf(self, serial: str) -> bytes | None:
        """The calibration certificate (PDF) of a serial (station/records/certificate.py); None for an
        unknown serial; LookupError for a serial without a stored result."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no certificates")

    def export_file(self, fmt: str, batch_id: int | None = None, run_id: int | None = None) -> bytes | None:
        """A batch or run in the registered export format `fmt` ('stdf', 'ocptv', ...:
        station/records/export_formats.py); None for an unknown id;
        station.records.export_model.ExportNotReady while it is still running."""
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no exports")

    def health(self) -> str:
        return "ok"


class NoRepository(WebRepository):
    """Used when the daemon runs without a database: history and MES answer 503, clearly."""

    def _none(self, *args, **kwargs):
        from fastapi import HTTPException

        raise HTTPException(status_code=503, detail="this station runs without a database: no history or results")

    search_duts = dut = runs_of_dut = run = segments = run_log = results_since = certificate_pdf = _none  # type: ignore[assignment]
    outbox_enqueue = outbox_due = outbox_mark_delivered = outbox_mark_failed = _none  # type: ignore[assignment]

    def outbox_list(self, limit: int = 100) -> list[dict]:
        self._none()
        return []

    def batch(self, batch_id: int) -> dict | None:
        return None

    def health(self) -> str:
        return "none"
