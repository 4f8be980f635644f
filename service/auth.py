"""Bearer tokens: who a caller is, for the API and the page alike.

A token maps to an owner key, stored with each job: an HMAC of the token under a per-deployment secret
(``NEUDF_SECRET_KEY``, else a random key kept in ``DATA_DIR/secret.key``), so the store never holds
anything a token could be recovered from by hashing guesses. A client address that sends too many bad
tokens within a window gets 429 until the window has passed, whatever it sends.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
import threading
import time
from collections import deque
from pathlib import Path

from service.jobs import JobRejected
from service.settings import Settings
from worker.store import JobStore

log = logging.getLogger("neudf.service")

TOKEN_MAX_CHARS = 512
_MAX_TRACKED_CLIENTS = 10_000


def load_secret(settings: Settings) -> bytes:
    """The deployment's key: the setting, else DATA_DIR/secret.key (made once, readable by its owner only)."""
    if settings.secret_key is not None:
        return settings.secret_key.get_secret_value().encode()
    path = settings.root / "secret.key"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return _read_secret(path)
    with os.fdopen(fd, "w") as fh:
        fh.write(secrets.token_hex(32))
    return _read_secret(path)


def _read_secret(path: Path) -> bytes:
    for _ in range(50):  # another process may be between creating the file and writing it
        value = path.read_text().strip()
        if value:
            return value.encode()
        time.sleep(0.02)
    raise RuntimeError(f"{path} is empty; remove it to have a new key made")


class FailureLimiter:
    """Bad attempts per client address in a sliding window."""

    def __init__(self, limit: int, window_s: float) -> None:
        self.limit, self.window_s = limit, window_s
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> deque[float]:
        times = self._failures.get(client, deque())
        while times and now - times[0] > self.window_s:
            times.popleft()
        return times

    def wait_s(self, client: str) -> float:
        """Seconds until ``client`` may try again; 0 when it may now."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(client, now)
            return self.window_s - (now - times[0]) if len(times) >= self.limit else 0.0

    def failed(self, client: str) -> None:
        now = time.monotonic()
        with self._lock:
            if len(self._failures) >= _MAX_TRACKED_CLIENTS:  # forget the clients whose window has passed
                self._failures = {c: t for c, t in self._failures.items() if self._recent(c, now)}
            times = self._recent(client, now)
            times.append(now)
            self._failures[client] = times


class TokenAuth:
    """Checks tokens and derives owner keys; one per app."""

    def __init__(self, settings: Settings, store: JobStore) -> None:
        self.tokens = [t.encode() for t in settings.auth_tokens]
        self.store = store
        self.limiter = FailureLimiter(settings.auth_fail_limit, settings.auth_fail_window_s)
        self._secret = load_secret(settings) if self.tokens else b""
        self._adopted: set[str] = set()
        self._adopt_lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        return bool(self.tokens)

    def owner_key(self, token: str) -> str:
        return hmac.new(self._secret, token.encode(), hashlib.sha256).hexdigest()[:32]

    def owner(self, token: str | None, client: str) -> str | None:
        """The caller's owner key; None when tokens are off. JobRejected: 401 for a missing or bad token, 429 for
        a client that sent too many bad ones lately."""
        if not self.enabled:
            return None
        wait = self.limiter.wait_s(client)
        if wait > 0:
            raise JobRejected(429, f"too many bad tokens from this address; try again in {wait:.0f} s", wait)
        if not token:
            raise JobRejected(401, "a valid bearer token is required (Authorization: Bearer <token>)")
        if len(token) > TOKEN_MAX_CHARS or not any(hmac.compare_digest(token.encode(), t) for t in self.tokens):
            self.limiter.failed(client)
            raise JobRejected(401, "the token is not valid")
        key = self.owner_key(token)
        self._adopt_legacy_jobs(token, key)
        return key

    def _adopt_legacy_jobs(self, token: str, key: str) -> None:
        """Jobs created before keys were keyed by the secret carry sha256(token)[:32]: give them to the new key."""
        with self._adopt_lock:
            if token in self._adopted:
                return
            moved = self.store.rename_owner(hashlib.sha256(token.encode()).hexdigest()[:32], key)
            self._adopted.add(token)
        if moved:
            log.info("moved %d job(s) to a token's new owner key", moved)
