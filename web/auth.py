"""Bearer-token auth with roles (design 5.3): tokens come from the station config, never from code.

Roles: `operator` starts/aborts batches and answers prompts, `mes` reads results, `admin` does
everything. Any valid token may read the live station (slots, batches, DUT history). Tokens are
compared in constant time and never logged or echoed in an error message.
"""

from __future__ import annotations

import hmac
import logging
import re
from dataclasses import dataclass
from typing import Any, Iterable

from fastapi import HTTPException, Request, Security, status
from fastapi.security import APIKeyQuery, HTTPBearer

ROLES = ("operator", "mes", "admin")

# What each permission needs; admin is in every set.
READ = frozenset({"operator", "mes", "admin"})
CONTROL = frozenset({"operator", "admin"})
RESULTS = frozenset({"mes", "admin"})
ADMIN = frozenset({"admin"})


@dataclass(frozen=True)
class Principal:
    """Who made a request: the token's name (never the token itself) and role."""

    name: str
    role: str


class TokenStore:
    """Token -> Principal. Built from config; constant-time lookup against every token."""

    def __init__(self, entries: Iterable[tuple[str, str, str]] = ()) -> None:
        self._entries: list[tuple[bytes, Principal]] = []
        for token, role, name in entries:
            if role not in ROLES:
                raise ValueError(f"token {name!r}: unknown role {role!r} (expected one of {', '.join(ROLES)})")
            if not token or len(token) < 8:
                raise ValueError(f"token {name!r}: a token must be at least 8 characters")
            self._entries.append((token.encode(), Principal(name=name, role=role)))

    def __len__(self) -> int:
        return len(self._entries)

    def lookup(self, token: str | None) -> Principal | None:
        if not token:
            return None
        given = token.encode()
        found = None
        for stored, principal in self._entries:  # no early exit: timing does not tell which matched
            if hmac.compare_digest(stored, given):
                found = principal
        return found

    @classmethod
    def from_config(cls, config: Any) -> "TokenStore":
        """Accepts the shapes a TOML config gives (attribute or dict access):

        [web.tokens] or [auth.tokens] as a table `token = "role"`, or a list of
        {token = "...", role = "...", name = "..."}.
        """
        raw = None
        for section in ("web", "auth", "api"):
            sec = _get(config, section)
            if sec is not None:
                raw = _get(sec, "tokens")
                if raw is not None:
                    break
        if raw is None:
            raw = _get(config, "tokens")
        return cls(_normalize(raw))


def _get(obj: Any, key: str) -> Any:
    if obj is None:
        return None
    if isinstance(obj, dict):
        return obj.get(key)
    return getattr(obj, key, None)


def _normalize(raw: Any) -> list[tuple[str, str, str]]:
    if raw is None:
        return []
    out: list[tuple[str, str, str]] = []
    if isinstance(raw, dict):
        for i, (token, role) in enumerate(raw.items()):
            out.append((str(token), str(role), f"{role}-{i + 1}"))
        return out
    for i, item in enumerate(raw):
        token, role, name = _get(item, "token"), _get(item, "role"), _get(item, "name")
        out.append((str(token or ""), str(role or ""), str(name or f"{role}-{i + 1}")))
    return out


_BEARER = re.compile(r"^\s*Bearer\s+(\S+)\s*$", re.IGNORECASE)


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(
        status_code=status.HTTP_401_UNAUTHORIZED, detail=detail, headers={"WWW-Authenticate": "Bearer"}
    )


def authenticate(request: Request, allow_query_token: bool = False) -> Principal:
    store: TokenStore = request.app.state.tokens
    header = request.headers.get("authorization")
    token = None
    if header:
        m = _BEARER.match(header)
        if not m:
            raise _unauthorized("malformed Authorization header: expected 'Bearer <token>'")
        token = m.group(1)
    elif allow_query_token:
        token = request.query_params.get("token")
    if not token:
        how = "an 'Authorization: Bearer <token>' header"
        if allow_query_token:
            how += " or a ?token= query parameter"
        raise _unauthorized(f"missing token: send {how}")
    principal = store.lookup(token)
    if principal is None:
        raise _unauthorized("invalid token")
    return principal


# Declared for the OpenAPI document only (securitySchemes + each operation's `security`): they
# never reject (auto_error=False); `authenticate` does, with its own messages.
BEARER_SCHEME = HTTPBearer(auto_error=False, scheme_name="bearer",
                           description="a station token from the config ([[tokens]]); roles operator, mes, admin")
QUERY_TOKEN_SCHEME = APIKeyQuery(name="token", auto_error=False, scheme_name="query_token",
                                 description="the same token as ?token= (only GET /api/events: EventSource cannot send headers)")


def require(roles: frozenset[str], *, allow_query_token: bool = False):
    """FastAPI dependency factory: authenticate, then check the role."""

    def check(request: Request) -> Principal:
        principal = authenticate(request, allow_query_token=allow_query_token)
        if principal.role not in roles:
            raise HTTPException(
                status_code=status.HTTP_403_FORBIDDEN,
                detail=f"role '{principal.role}' may not do this; needs one of: {', '.join(sorted(roles))}",
            )
        request.state.principal = principal
        return principal

    if allow_query_token:
        async def dependency(request: Request, _bearer=Security(BEARER_SCHEME),
                             _query=Security(QUERY_TOKEN_SCHEME)) -> Principal:
            return check(request)
    else:
        async def dependency(request: Request, _bearer=Security(BEARER_SCHEME)) -> Principal:  # async: no thread-pool hop
            return check(request)

    return dependency


require_read = require(READ)
require_read_sse = require(READ, allow_query_token=True)
require_control = require(CONTROL)
require_results = require(RESULTS)
require_admin = require(ADMIN)


# --- keep tokens out of logs -------------------------------------------------------------------

_TOKEN_IN_QUERY = re.compile(r"([?&]token=)[^&\s\"]*", re.IGNORECASE)


def redact(text: str) -> str:
    return _TOKEN_IN_QUERY.sub(r"\1***", text)


class RedactTokenFilter(logging.Filter):
    """Rewrites `?token=...` in access-log records (uvicorn logs the full path with its query)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and record.args:
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        if isinstance(record.msg, str) and "token=" in record.msg.lower():
            record.msg = redact(record.msg)
        return True


def install_log_redaction() -> None:
    """Idempotent: attach the filter to uvicorn's access and error loggers."""
    for name in ("uvicorn.access", "uvicorn.error", "uvicorn"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactTokenFilter) for f in logger.filters):
            logger.addFilter(RedactTokenFilter())
