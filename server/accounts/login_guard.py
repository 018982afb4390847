"""Log-in throttling that an attacker cannot aim at other people, and a small bounded executor
for the password check, so that a flood of log-ins cannot starve the API.

Why: an argon2id check (argon2-cffi defaults: 64 MiB, 3 passes, 4 lanes) costs ~50 ms of CPU
and 64 MiB; run on the API's request threads (40 by default), a flood of wrong passwords
occupied all of them and every core: /api/health took 9.6 s. And a lock per user name alone let
anyone lock any account from anywhere with a few wrong passwords. Now failures are counted in
moving windows (the ``limits`` library, in memory, per server process) under three keys:

- ``per_user_address``: failures for one user name from one client address. Past it, that
  user name is refused *from that address* (429 with ``Retry-After``, seconds until the oldest
  failure leaves the window) without touching the hash: this slows a guesser, and the real user
  at another address is not affected;
- ``per_address``: failures from one client address over all user names (a sprayer);
- ``per_user``: failures for one user name from all addresses (a distributed guesser), set
  much higher. Past it, the user name is refused from every address *except* the addresses
  it logged in from successfully within ``known_address_ttl_s``, so even a botnet cannot lock
  the real user out of the machine they work at.

The check itself (database + argon2) runs in :attr:`LoginGuard.pool` (``workers`` threads, by
default a quarter of the cores: on a 2-core machine one, so the API keeps a core); when
``max_pending`` checks are already queued or running, a further log-in is refused at once with
429 and ``Retry-After: 1``.

Refused attempts are audited (server.accounts.auth_routes): a failed check in the check pool itself;
a refusal that never reaches the check (held, or too many in progress) on the guard's one audit
thread (:meth:`LoginGuard.record_later`), at most ``max_audit_backlog`` entries waiting, so a
flood of refused log-ins costs the database one thread's writes; entries past the backlog are
counted and the next entry written carries the count.

A successful log-in clears its (user name, address) failures and remembers the address as known
for that user. The client address is the TCP peer unless the peer is one of the configured
trusted proxies (``Settings.trusted_proxies``; none by default, loopback included), whose
``X-Forwarded-For`` then names the client (uvicorn's ProxyHeadersMiddleware, server.app).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from limits import parse
from limits.storage import MemoryStorage
from limits.strategies import MovingWindowRateLimiter

from server.errors import Limited

log = logging.getLogger(__name__)
T = TypeVar("T")


class LoginBusy(Limited, RuntimeError):
    """Too many log-in checks in progress; retry in a second."""


class LoginGuard:
    """Args:
        per_user / per_address / per_user_address: failed log-ins allowed per window,
            ``limits`` notation (e.g. ``"5/5minutes"``); see the module docstring.
        workers: threads that check passwords (argon2 runs outside the GIL: one core each).
        max_pending: checks queued or running at most; more are refused (:class:`LoginBusy`).
        known_address_ttl_s: how long an address a user logged in from stays exempt from the
            ``per_user`` lock, s.
        max_known: (user, address) pairs remembered at most (oldest forgotten first).
        max_audit_backlog: audit entries of refused log-ins waiting at most (see
            :meth:`record_later`).
    """

    def __init__(self, per_user: str = "100/5minutes", per_address: str = "20/5minutes", workers: int = 2,
                 max_pending: int = 8, per_user_address: str = "5/5minutes",
                 known_address_ttl_s: float = 30 * 86400.0, max_known: int = 100_000, max_audit_backlog: int = 256):
        if workers < 1 or max_pending < 1:
            raise ValueError(f"need workers >= 1 and max_pending >= 1, got {workers}, {max_pending}")
        self._limiter = MovingWindowRateLimiter(MemoryStorage())
        self._limits = {"user": parse(per_user), "address": parse(per_address),
                        "user_address": parse(per_user_address)}
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="login-check")
        self.max_pending = max_pending
        self._pending = 0
        self._lock = threading.Lock()
        self._known: OrderedDict[tuple[str, str], float] = OrderedDict()
        self._known_ttl_s = known_address_ttl_s
        self._max_known = max_known
        self._audit = ThreadPoolExecutor(max_workers=1, thread_name_prefix="login-audit")
        self._audit_backlog = 0
        self._max_audit_backlog = max_audit_backlog
        self._unrecorded = 0

    def _keys(self, username: str, address: str) -> list[tuple[str, str]]:
        return [("user_address", f"{username}\x00{address}"), ("address", address), ("user", username)]

    def known(self, username: str, address: str) -> bool:
        """True if ``username`` logged in successfully from ``address`` within the known-address TTL."""
        with self._lock:
            at = self._known.get((username, address))
            return at is not None and time.monotonic() - at < self._known_ttl_s

    def retry_after_s(self, username: str, address: str) -> int | None:
        """Whole seconds until this user name may try again from this address, or None if it may now."""
        for kind, key in self._keys(username, address):
            if kind == "user" and self.known(username, address):
                continue
            limit = self._limits[kind]
            if not self._limiter.test(limit, kind, key):
                reset = self._limiter.get_window_stats(limit, kind, key).reset_time
                return max(1, math.ceil(reset - time.time()))
        return None

    def failed(self, username: str, address: str) -> None:
        """Count a failed log-in against the (user name, address) pair, the address and the user name."""
        for kind, key in self._keys(username, address):
            self._limiter.hit(self._limits[kind], kind, key)
        if self.retry_after_s(username, address) is not None:
            log.warning("log-in of user %r from address %s held after repeated failures", username, address)

    def succeeded(self, username: str, address: str) -> None:
        """Forget the (user name, address) failures and remember the address as known for the user
        (the address and user-name counts keep theirs)."""
        kind, key = self._keys(username, address)[0]
        self._limiter.clear(self._limits[kind], kind, key)
        with self._lock:
            self._known[(username, address)] = time.monotonic()
            self._known.move_to_end((username, address))
            while len(self._known) > self._max_known:
                self._known.popitem(last=False)

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

    def record_later(self, write: Callable[[int], None]) -> None:
        """Run ``write(unrecorded)`` on the guard's audit thread without waiting; ``unrecorded``
        is the number of entries dropped since the last one handed to ``write``. When
        ``max_audit_backlog`` writes already wait, this one is dropped, counted and logged."""
        with self._lock:
            if self._audit_backlog >= self._max_audit_backlog:
                self._unrecorded += 1
                log.warning("audit entry of a refused log-in dropped (%d waiting)", self._audit_backlog)
                return
            self._audit_backlog += 1

        def run() -> None:
            with self._lock:
                self._audit_backlog -= 1
                unrecorded, self._unrecorded = self._unrecorded, 0
            try:
                write(unrecorded)
            except Exception:
                log.exception("audit entry of a refused log-in not written")

        self._audit.submit(run)

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self._audit.shutdown(wait=True)
