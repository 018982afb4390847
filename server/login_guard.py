"""Log-in throttling: failed-log-in lockout per user name and per client address, and a small
bounded executor for the password check, so that a flood of log-ins cannot starve the API.

Why: an argon2id check (argon2-cffi defaults: 64 MiB, 3 passes, 4 lanes) costs ~50 ms of CPU
and 64 MiB; run on the API's request threads (40 by default), a flood of wrong passwords
occupied all of them and every core: /api/health took 9.6 s. Now

- failures are counted in moving windows (the ``limits`` library, in memory, per server
  process): more than ``per_user`` failures for one user name, or ``per_address`` from one client
  address, answer 429 with ``Retry-After`` (seconds until the oldest failure leaves the window)
  without touching the hash;
- the check itself (database + argon2) runs in :attr:`LoginGuard.pool` (``workers`` threads,
  by default a quarter of the cores: on a 2-core machine one, so the API keeps a core);
  when ``max_pending`` checks are already queued or running, a further log-in is refused at once
  with 429 and ``Retry-After: 1``.

A successful log-in clears its user name's failures. Behind a reverse proxy the client address
is what uvicorn's proxy-header handling makes of ``X-Forwarded-For`` (trusted from
``--forwarded-allow-ips``, loopback by default); the per-user limit holds regardless.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from limits import parse
from limits.storage import MemoryStorage
from limits.strategies import MovingWindowRateLimiter

log = logging.getLogger(__name__)
T = TypeVar("T")


class LoginBusy(RuntimeError):
    """Too many log-in checks in progress; retry in a second."""


class LoginGuard:
    """Args:
        per_user / per_address: failed log-ins allowed per window, ``limits`` notation
            (e.g. ``"5/5minutes"``).
        workers: threads that check passwords (argon2 runs outside the GIL: one core each).
        max_pending: checks queued or running at most; more are refused (:class:`LoginBusy`).
    """

    def __init__(self, per_user: str = "5/5minutes", per_address: str = "20/5minutes", workers: int = 2,
                 max_pending: int = 8):
        if workers < 1 or max_pending < 1:
            raise ValueError(f"need workers >= 1 and max_pending >= 1, got {workers}, {max_pending}")
        self._limiter = MovingWindowRateLimiter(MemoryStorage())
        self._limits = {"user": parse(per_user), "address": parse(per_address)}
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="login-check")
        self.max_pending = max_pending
        self._pending = 0
        self._lock = threading.Lock()

    def retry_after_s(self, username: str, address: str) -> int | None:
        """Whole seconds until this user name and address may try again, or None if they may now."""
        for kind, key in (("user", username), ("address", address)):
            limit = self._limits[kind]
            if not self._limiter.test(limit, kind, key):
                reset = self._limiter.get_window_stats(limit, kind, key).reset_time
                return max(1, math.ceil(reset - time.time()))
        return None

    def failed(self, username: str, address: str) -> None:
        """Count a failed log-in against the user name and the address."""
        for kind, key in (("user", username), ("address", address)):
            self._limiter.hit(self._limits[kind], kind, key)
        if self.retry_after_s(username, address) is not None:
            log.warning("log-in locked for user %r / address %s after repeated failures", username, address)

    def succeeded(self, username: str) -> None:
        """Forget the user name's failures (the address keeps its count)."""
        self._limiter.clear(self._limits["user"], "user", username)

    async def run(self, fn: Callable[..., T], *args) -> T:
        """``fn(*args)`` in the check pool.

        Raises:
            LoginBusy: ``max_pending`` checks are already queued or running.
        """
        with self._lock:
            if self._pending >= self.max_pending:
                raise LoginBusy("too many log-ins in progress: try again in a second")
            self._pending += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)
        finally:
            with self._lock:
                self._pending -= 1

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
