"""The MES's route check, pure: what to ask, how to read the answer, what it means for the part.

Every EMS line's MES answers "may this serial be tested at this operation now?" before a unit is
tested (a wrong route, a part on quality hold, too many retests). The station asks it per DUT once
the board's identity and its label are known, before the lamp heats (station/daemon/route_gate.py
makes the call; design 5.4). This module holds the rules, so the daemon, the tests and the docs
read one:

- `request_for` fills the configured URL (and the JSON body of a POST) with the part's fields;
- `read_answer` turns the MES's HTTP answer into one of three outcomes: `allowed`, `refused` (the
  MES said no: a refusal status, or its yes/no field says no) or `unanswered` (no usable answer: a
  timeout, a refused connection, a 5xx, a 2xx the station cannot read). A "no" the station cannot
  read is never taken as a yes: an unreadable answer is `unanswered`, and the site's policy decides;
- `may_test` applies that policy (`refuse` or `proceed_and_flag`);
- `fault_words` / `flag_words` are the sentences the record and the page show (the daemon's own
  English; station/records/causes.py names the cause "route refused (MES)").

The MES's reason is the MES's own text: shown and stored as it came, cut to REASON_MAX_CHARS and
stripped of control characters (it is shown on the operator's page and stored in the record).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Literal
from urllib.parse import quote

Outcome = Literal["allowed", "refused", "unanswered"]
Policy = Literal["refuse", "proceed_and_flag"]

REASON_MAX_CHARS = 200
YES_WORDS = frozenset({"yes", "ok", "allowed", "allow", "pass", "true", "go"})
NO_WORDS = frozenset({"no", "hold", "on hold", "refused", "refuse", "blocked", "deny", "denied", "false", "stop"})
# the words a refusal's reason starts with in the record: station/records/causes.py matches them
FAULT_PREFIX = "MES route check"


@dataclass(frozen=True)
class RoutePart:
    """What the MES is asked about: one part, at this station's operation."""

    serial: str
    slot: str
    operation: str
    station: str
    label_serial: str = ""
    work_order: str = ""
    part_number: str = ""
    lot: str = ""

    def fields(self) -> dict[str, str]:
        return {"serial": self.serial, "label_serial": self.label_serial, "operation": self.operation,
                "station": self.station, "slot": self.slot, "work_order": self.work_order,
                "part_number": self.part_number, "lot": self.lot}


@dataclass(frozen=True)
class RouteRequest:
    method: Literal["GET", "POST"]
    url: str
    json_body: dict[str, str] | None


@dataclass(frozen=True)
class RouteAnswer:
    """The MES's answer for one part, as the station read it."""

    outcome: Outcome
    reason: str  # the MES's words (refused), what went wrong (unanswered), "" or the MES's words (allowed)
    http_status: int | None = None
    elapsed_s: float = 0.0

    def to_json(self) -> dict[str, str | int | float | None]:
        return {"outcome": self.outcome, "reason": self.reason, "http_status": self.http_status,
                "elapsed_s": round(self.elapsed_s, 3)}


def request_for(url_template: str, method: Literal["GET", "POST"], part: RoutePart) -> RouteRequest:
    """The call for `part`: each {field} of the URL replaced by its URL-quoted value (a serial with
    '+' or '/' cannot change the path or the query); a POST also sends every field as JSON."""
    values = part.fields()

    def fill(m: re.Match[str]) -> str:
        name = m.group(1)
        if name not in values:
            raise ValueError(f"route check URL names {{{name}}}: not one of {', '.join(sorted(values))}")
        return quote(values[name], safe="")

    url = re.sub(r"\{([a-z_]+)\}", fill, url_template)
    return RouteRequest(method, url, dict(values) if method == "POST" else None)


def clean_reason(text: str) -> str:
    """The MES's words as the page and the record may hold them: one line, no control characters,
    at most REASON_MAX_CHARS."""
    one = " ".join(re.sub(r"[\x00-\x1f\x7f]", " ", text).split())
    return one if len(one) <= REASON_MAX_CHARS else one[: REASON_MAX_CHARS - 3] + "..."


def _field(data: object, path: str) -> object:
    """The value at a dotted path of a JSON object (None: absent)."""
    for key in path.split("."):
        if not isinstance(data, dict) or key not in data:
            return None
        data = data[key]
    return data


def _decision(value: object) -> bool | None:
    """True: a yes; False: a no; None: not a yes/no the station can read."""
    if isinstance(value, bool):
        return value
    if isinstance(value, str):
        word = value.strip().lower()
        if word in YES_WORDS:
            return True
        if word in NO_WORDS:
            return False
    return None


def read_answer(status: int, body: bytes, *, allowed_field: str, reason_field: str,
                refuse_statuses: frozenset[int] | set[int] | list[int], elapsed_s: float = 0.0) -> RouteAnswer:
    """What an HTTP answer of the MES means (see the module's docstring for the rules)."""
    try:
        data: object = json.loads(body.decode("utf-8")) if body.strip() else None
    except (UnicodeDecodeError, ValueError):
        data = None
    said = _field(data, reason_field)
    words = clean_reason(said if isinstance(said, str) else "")
    if status in set(refuse_statuses):
        if not words:
            text = "" if data is not None else body.decode("utf-8", "replace")
            words = clean_reason(text) or f"HTTP {status}"
        return RouteAnswer("refused", words, status, elapsed_s)
    if not 200 <= status < 300:
        return RouteAnswer("unanswered", f"HTTP {status}" + (f": {words}" if words else ""), status, elapsed_s)
    if not isinstance(data, dict):
        return RouteAnswer("unanswered", "its answer is not a JSON object", status, elapsed_s)
    decision = _decision(_field(data, allowed_field))
    if decision is None:
        return RouteAnswer("unanswered", f"its answer has no yes/no in {allowed_field!r}", status, elapsed_s)
    if decision:
        return RouteAnswer("allowed", words, status, elapsed_s)
    return RouteAnswer("refused", words or "no reason given", status, elapsed_s)


def no_answer(error: str, elapsed_s: float = 0.0) -> RouteAnswer:
    """The MES could not be asked or did not answer in time (`error` in words)."""
    return RouteAnswer("unanswered", clean_reason(error) or "no answer", None, elapsed_s)


def may_test(answer: RouteAnswer, policy: Policy) -> bool:
    """The part is tested: the MES said yes, or it gave no usable answer and the site proceeds."""
    return answer.outcome == "allowed" or (answer.outcome == "unanswered" and policy == "proceed_and_flag")


def fault_words(part: RoutePart, answer: RouteAnswer, policy: Policy) -> str:
    """The fault reason of a part the route check stopped (record, page, MES message)."""
    if answer.outcome == "refused":
        return (f"{FAULT_PREFIX}: the MES refused {part.serial} at {part.operation!r}: {answer.reason}; "
                f"not tested")
    return (f"{FAULT_PREFIX}: the MES did not answer for {part.serial} ({answer.reason}); the site's "
            f"policy '{policy}' stops it: not tested")


def flag_words(part: RoutePart, answer: RouteAnswer) -> str:
    """The note of a part tested without the MES's yes (policy proceed_and_flag)."""
    return (f"{FAULT_PREFIX}: the MES did not answer for {part.serial} ({answer.reason}); tested by the "
            f"site's policy 'proceed_and_flag', not route-checked")
