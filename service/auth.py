"""Tenants: optional API keys, ownership of textures and jobs, per-key rate limits.

Off by default (``TEXSPACE_API_KEYS_ENABLED=false``: the embedded, single-user setup);
turn it on in production. When on:

* every ``/v1/textures...`` and ``/v1/jobs...`` request needs ``X-API-Key`` (401 without
  a valid, unrevoked key);
* textures and jobs belong to the key that created them (``owner_id`` = the key's id);
  another key gets 404 for them, exactly as for ids that do not exist, and lists show
  only its own;
* each key may make ``rate_limit_per_minute`` requests per API process (token bucket of
  ``rate_limit_burst``), then 429 with ``Retry-After``.

Keys are 256-bit random tokens shown once at creation; only HMAC-SHA256(pepper, key) is
stored (the pepper is a server-side setting, never in the database). A slow KDF (scrypt)
buys nothing for keys of this entropy and would cost every request.

Admin: ``texspace keys create NAME | list | revoke KEY_ID`` (the ``keys`` command in :mod:`service.cli`).
"""
from __future__ import annotations

import hashlib
import hmac
import logging
import math
import secrets
import threading
import time
from contextvars import ContextVar
from typing import Any

from fastapi import Depends, Request
from fastapi.security import APIKeyHeader
from sqlalchemy import Select, select
from starlette.concurrency import run_in_threadpool

from .db import session_scope
from .errors import Problem, problem_responses
from .tables import ApiKey, new_id, utcnow

log = logging.getLogger(__name__)
HEADER = "X-API-Key"
DEFAULT_PEPPERS = {"texspace-dev-pepper", "change-me"}
KEY_PREFIX = "tsk_"
KEY_CACHE_SECONDS = 5.0   # a revoked key stops working within this long on every API process

#: the key id of the current request; None when API keys are disabled (no restriction)
owner_var: ContextVar[str | None] = ContextVar("texspace_owner", default=None)
_header = APIKeyHeader(name=HEADER, auto_error=False, description="API key (when keys are enabled)")


def hash_key(pepper: str, key: str) -> str:
    """HMAC-SHA256 of a key under the server's pepper (hex, 64 chars)."""
    return hmac.new(pepper.encode(), key.encode(), hashlib.sha256).hexdigest()


def current_owner() -> str | None:
    """The key id the current request acts for (None: keys disabled, everything visible)."""
    return owner_var.get()


def visible(row: Any) -> bool:
    """True if the current request may see ``row`` (a Texture or Job)."""
    owner = owner_var.get()
    return owner is None or getattr(row, "owner_id", None) == owner


def scoped(query: Select, table: Any) -> Select:
    """Restrict a SELECT to the current owner's rows (no-op when keys are disabled)."""
    owner = owner_var.get()
    return query if owner is None else query.where(table.owner_id == owner)


class RateLimiter:
    """Token buckets per key: ``per_minute`` refill, ``burst`` capacity; thread-safe."""

    def __init__(self, per_minute: float, burst: int) -> None:
        self.rate = per_minute / 60.0
        self.burst = float(burst)
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def take(self, key: str, now: float | None = None) -> float:
        """Spend one token; return 0 if allowed, else the seconds until one is available."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens, last = self._buckets.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._buckets[key] = (tokens - 1.0, now)
                return 0.0
            self._buckets[key] = (tokens, now)
            return (1.0 - tokens) / self.rate


class KeyCache:
    """Recently verified key hashes -> key id, so each request does not hit the database."""

    def __init__(self) -> None:
        self._items: dict[str, tuple[str, float]] = {}
        self._lock = threading.Lock()

    def get(self, key_hash: str) -> str | None:
        with self._lock:
            hit = self._items.get(key_hash)
        return hit[0] if hit and hit[1] > time.monotonic() else None

    def put(self, key_hash: str, key_id: str) -> None:
        with self._lock:
            if len(self._items) > 10_000:
                self._items.clear()
            self._items[key_hash] = (key_id, time.monotonic() + KEY_CACHE_SECONDS)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def _state(services) -> tuple[KeyCache, RateLimiter]:  # noqa: ANN001
    """The per-process key cache and rate limiter, kept on the Services object."""
    state = getattr(services, "_auth_state", None)
    if state is None:
        if services.settings.api_key_pepper in DEFAULT_PEPPERS:
            log.warning("API keys are hashed with a default pepper: set TEXSPACE_API_KEY_PEPPER to a secret")
        state = (KeyCache(), RateLimiter(services.settings.rate_limit_per_minute, services.settings.rate_limit_burst))
        services._auth_state = state
    return state


def lookup_key(services, key: str) -> str | None:  # noqa: ANN001
    """The id of the live key ``key``, or None (unknown or revoked)."""
    key_hash = hash_key(services.settings.api_key_pepper, key)
    cache, _ = _state(services)
    if (key_id := cache.get(key_hash)) is not None:
        return key_id
    with session_scope(services.sessions) as session:
        row = session.scalars(select(ApiKey).where(ApiKey.key_hash == key_hash, ApiKey.revoked_at.is_(None))).first()
    if row is None:
        return None
    cache.put(key_hash, row.id)
    return row.id


async def authenticate(request: Request, key: str | None = Depends(_header)) -> None:
    """Route dependency: check the key, apply the rate limit, set the owner for the request.

    Async on purpose: the context variable it sets is then seen by the route (sync routes
    run in a thread with a copy of this context)."""
    services = request.app.state.services
    if not services.settings.api_keys_enabled:
        owner_var.set(None)
        return
    challenge = {"WWW-Authenticate": f'ApiKey header="{HEADER}"'}
    if not key:
        raise Problem(401, f"this API needs an API key: send it in the {HEADER} header",
                      slug="unauthorized", headers=challenge)
    key_id = await run_in_threadpool(lookup_key, services, key[:200])
    if key_id is None:
        raise Problem(401, "the API key is unknown or revoked", slug="unauthorized", headers=challenge)
    wait = _state(services)[1].take(key_id)
    if wait > 0:
        raise Problem(429, f"rate limit of {services.settings.rate_limit_per_minute:g} requests per minute "
                           f"exceeded for this key; retry in {math.ceil(wait)} s", slug="rate-limited",
                      headers={"Retry-After": str(math.ceil(wait))})
    owner_var.set(key_id)


def router_options() -> dict[str, Any]:
    """``include_router`` keywords for the routers that hold tenants' data."""
    return {"dependencies": [Depends(authenticate)], "responses": problem_responses(401, 429)}


# --- admin ----------------------------------------------------------------------------------


def create_key(services, name: str, note: str | None = None) -> tuple[ApiKey, str]:  # noqa: ANN001
    """Make a key; return (its row, the key itself: shown this once, never stored)."""
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(id=new_id(), name=name[:200], note=note, key_hash=hash_key(services.settings.api_key_pepper, key),
                 created_at=utcnow())
    with session_scope(services.sessions) as session:
        session.add(row)
    return row, key


def list_keys(services) -> list[ApiKey]:  # noqa: ANN001
    with session_scope(services.sessions) as session:
        return list(session.scalars(select(ApiKey).order_by(ApiKey.created_at)))


def revoke_key(services, key_id: str) -> bool:  # noqa: ANN001
    """Revoke a key by id; False if no live key has that id."""
    with session_scope(services.sessions) as session:
        row = session.get(ApiKey, key_id)
        if row is None or row.revoked_at is not None:
            return False
        row.revoked_at = utcnow()
    _state(services)[0].clear()
    return True
