"""Limit-set changes in the audit trail (issue 13). Limit sets live in the station config
([products.NAME], versioned), not behind a REST call, so a change is seen where the config is
loaded: at daemon start the limits in force are compared with the ones the last start recorded,
and any difference becomes one `limits.change` audit row (actor `config`).

A set is identified by its name, version and a digest of its full content: a site that edits a
limit but forgets to bump the version is still recorded (the digest changes) and flagged.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

ACTION = "limits.change"
ACTOR = "config"


def fingerprint(products: dict[str, Any]) -> dict[str, dict]:
    """{set key: {"name", "version", "digest"}} of the limit sets in force (pydantic or dicts)."""
    out = {}
    for key, spec in sorted(products.items()):
        data = spec.model_dump(mode="json") if hasattr(spec, "model_dump") else dict(spec)
        digest = hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]
        out[key] = {"name": data.get("name", key), "version": str(data.get("version", "")), "digest": digest}
    return out


def changes(previous: dict[str, dict] | None, current: dict[str, dict]) -> dict | None:
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


def record_limit_changes(db: Any, config: Any) -> dict | None:
    """At daemon start: audit the limit sets in force if they differ from the last recorded ones
    of this station. Returns the recorded detail (None: unchanged, or no database)."""
    if not hasattr(db, "engine"):
        return None
    from db import repository as repo

    last = next((a for a in repo.audit_list(db, limit=1000, station=getattr(db, "station", "") or None)
                 if a["action"] == ACTION), None)
    detail = changes((last or {}).get("detail", {}).get("current"), fingerprint(config.product_specs()))
    if detail is not None:
        repo.audit_append(db, ACTOR, ACTION, "limit sets", detail)
    return detail
