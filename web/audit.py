"""The audit trail of REST actions: who (the token's name, never the token) did what to which
batch, with what the request carried: batch start, abort, prompt answers, resume.

`record(request, ...)` is called by the route once the action was done, so the trail holds what
happened, not what was attempted. The action has happened by then: a storage failure while
recording is logged loudly but does not turn the operator's successful abort into an error.
"""

from __future__ import annotations

import logging
from typing import Any
from urllib.parse import unquote

from fastapi import Request

from web.db_gate import db_call

log = logging.getLogger("station.web.audit")

# The audited actions (the `action` column).
BATCH_START = "batch.start"
BATCH_ABORT = "batch.abort"
PROMPT_ANSWER = "prompt.answer"
BATCH_RESUME = "batch.resume"
LIMITS_CHANGE = "limits.change"


OPERATOR_HEADER = "X-Operator"  # the person at the page, percent-encoded (a shared kiosk token is not a person)


def actor_of(request: Request) -> str:
    """Who acted: the person the page names in X-Operator, with the token's name ("Ana (token
    line-3 kiosk)"); the token's name alone when no person is named (a script, the MES)."""
    principal = getattr(request.state, "principal", None)
    token = getattr(principal, "name", None) or "unknown"
    person = " ".join(unquote(request.headers.get(OPERATOR_HEADER) or "").split())[:100]  # the page percent-encodes
    return f"{person} (token {token})" if person else token


async def record(request: Request, action: str, target: str, detail: dict[str, Any] | None = None) -> None:
    actor = actor_of(request)
    try:
        await db_call(request, request.app.state.repo.audit_append, actor, action, target, detail or {})
    except Exception:  # noqa: BLE001 - see the module docstring
        log.critical("audit: could not record %s by %s on %s %s", action, actor, target, detail, exc_info=True)
