"""Limit-set changes in the audit trail: a verdict is only as trustworthy as the record of the
limits it was judged by. Limit sets live in the station config ([products.NAME], versioned), not
behind a REST call, so a change is seen where the config is loaded: at daemon start the limits in
force are compared with the ones the last start recorded, and any difference becomes one
`limits.change` audit row (actor `config`).

A set is identified by its name, version and a digest of its full content: a site that edits a
limit but forgets to bump the version is still recorded (the digest changes) and flagged.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol

from station.decisions.limits import ProductSpec

if TYPE_CHECKING:  # types only: the database is opened by the caller
    from db.database import Database

ACTION = "limits.change"
ACTOR = "config"
Fingerprint = dict[str, dict[str, str]]  # {set key: {"name", "version", "digest"}}


class LimitSets(Protocol):
    """Where the limit sets in force come from (station.config.StationConfig)."""

    def product_specs(self) -> Mapping[str, ProductSpec]: ...


def fingerprint(products: Mapping[str, ProductSpec | Mapping[str, object]]) -> Fingerprint:
    """{set key: {"name", "version", "digest"}} of the limit sets in force (pydantic or dicts)."""
    out = {}
    for key, spec in sorted(products.items()):
        data = spec.model_dump(mode="json") if isinstance(spec, ProductSpec) else dict(spec)
        digest = hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]
        out[key] = {"name": str(data.get("name", key)), "version": str(data.get("version", "")), "digest": digest}
    return out


def changes(previous: Mapping[str, Mapping[str, object]] | None,
            current: Fingerprint) -> dict[str, object] | None:
    """What changed between two fingerprints (None: nothing). The first start records every set."""
    previous = previous or {}
    added = sorted(k for k in current if k not in previous)
    removed = sorted(k for k in previous if k not in current)
    changed = []
    for k in sorted(set(current) & set(previous)):
        a, b = previous[k], current[k]
        if a.get("digest") != b.get("digest"):
            changed.append({"set": k, "old_version": a.get("version"), "new_version": b.get("version"),
                            "version_bumped": a.get("version") != b.get("version")})
    if not (added or removed or changed):
        return None
    return {"added": added, "removed": removed, "changed": changed, "current": current}


def _last_current(detail: object) -> Mapping[str, Mapping[str, object]] | None:
    """The fingerprint a recorded change stored as "current" (None: none readable)."""
    current = detail.get("current") if isinstance(detail, Mapping) else None
    return current if isinstance(current, Mapping) else None


def record_limit_changes(db: Database | None, config: LimitSets) -> dict[str, object] | None:
    """At daemon start: audit the limit sets in force if they differ from the last recorded ones
    of this station. Returns the recorded detail (None: unchanged, or no database)."""
    if getattr(db, "engine", None) is None or db is None:
        return None
    from db import repository as repo

    last = next((a for a in repo.audit_list(db, limit=1000, station=getattr(db, "station", "") or None)
                 if a["action"] == ACTION), None)
    detail = changes(_last_current((last or {}).get("detail", {})), fingerprint(config.product_specs()))
    if detail is not None:
        repo.audit_append(db, ACTOR, ACTION, "limit sets", detail)
    return detail
