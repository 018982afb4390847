"""The server's E-STOP path: a fire-and-forget put per machine, confirmed separately.

An E-STOP press becomes a signed (when it can be) AbortRequest with a fresh ``request_id``, put on
``keys.estop(machine_id)`` at once on the caller's thread: a Zenoh put with congestion control
DROP, priority REAL_TIME and express, so it never blocks on a slow or frozen peer and never waits
for a query, a thread pool or another machine. The runtime latches, writes the latch to disk and
publishes an AbortAck with the same ``request_id`` on ``keys.estop_ack``; :meth:`EstopLine.on_ack`
(a Zenoh callback) resolves the press's Future. Until then the put is repeated every
``resend_s`` (a dropped put is sent again) up to the press's own deadline, after which its
Future fails with :class:`server.fleet_commands.RuntimeUnavailable` ("not confirmed").

Presses of a machine whose stop is still unconfirmed join it (coalesced: one put stream, one
Future for all of them); a press after the confirmation sends a new stop. Nothing here is shared
between machines but one timer thread that only re-puts (non-blocking) and expires deadlines.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import zenoh
from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import AbortAck, AbortRequest, decode_on_key, encode
from server.fleet_commands import RuntimeUnavailable

log = logging.getLogger(__name__)

RESEND_S = 0.05
"""An unconfirmed E-STOP put is repeated this often, s."""
DEADLINE_S = 2.0
"""A press not confirmed within this long fails (HTTP 503 "not confirmed"), s; the puts stop."""


class EstopUnconfirmed(RuntimeUnavailable):
    """The runtime did not confirm the stop within the deadline (frozen, offline, unreachable)."""


@dataclass
class Press:
    """One machine's unconfirmed stop (and every press that joined it)."""

    machine_id: str
    request_id: str
    payload: bytes
    deadline_s: float
    future: Future = field(default_factory=Future)
    presses: int = 1
    sent: int = 0
    first_s: float = field(default_factory=time.monotonic)


class EstopLine:
    """Per-machine E-STOP sends and their confirmations.

    Args:
        session: an open Zenoh session (the caller declares :meth:`on_ack` on keys.ALL_ESTOP_ACKS).
        sign: ``sign(request, machine_id, user) -> AbortRequest`` (signed, or unchanged when the
            server cannot sign it: aborts are honoured unsigned).
        resend_s: see RESEND_S.
        deadline_s: see DEADLINE_S.
    """

    def __init__(self, session: zenoh.Session, sign: Callable[[AbortRequest, str, str], AbortRequest],
                 resend_s: float = RESEND_S, deadline_s: float = DEADLINE_S):
        self.session = session
        self.sign = sign
        self.resend_s = resend_s
        self.deadline_s = deadline_s
        self._lock = threading.Lock()
        self._pending: dict[str, Press] = {}
        self.coalesced = 0
        """Presses that joined an unconfirmed stop (for tests and diagnostics)."""
        self._wake = threading.Event()
        self._closed = False
        self._timer = threading.Thread(target=self._resend_loop, name="estop-resend", daemon=True)
        self._timer.start()

    def press(self, machine_id: str, reason: str, user: str) -> Future:
        """Stop ``machine_id`` now: put the AbortRequest (or join its unconfirmed stop) and
        return the Future of its AbortAck (fails with EstopUnconfirmed past the deadline).

        Raises:
            ValueError: a malformed machine id.
        """
        keys.validate_machine_id(machine_id)
        with self._lock:
            press = self._pending.get(machine_id)
            if press is not None:
                press.presses += 1
                self.coalesced += 1
                return press.future
        request_id = secrets.token_hex(8)
        request = AbortRequest(machine_id=machine_id, reason=reason[:200], request_id=request_id)
        try:
            request = self.sign(request, machine_id, user)
        except ValueError as e:
            log.warning("E-STOP of %s sent unsigned: %s", machine_id, e)
        press = Press(machine_id, request_id, encode(request), time.monotonic() + self.deadline_s)
        with self._lock:
            joined = self._pending.get(machine_id)
            if joined is not None:  # another press got there first
                joined.presses += 1
                self.coalesced += 1
                return joined.future
            self._pending[machine_id] = press
        self._put(press)
        return press.future

    def on_ack(self, sample: zenoh.Sample) -> None:
        """An AbortAck on keys.estop_ack: resolve the press it confirms (Zenoh callback)."""
        try:
            ack = decode_on_key(AbortAck, sample.key_expr, sample.payload.to_bytes())
        except (ValidationError, ValueError) as e:
            log.warning("dropped AbortAck on %s: %s", sample.key_expr, e)
            return
        with self._lock:
            press = self._pending.get(ack.machine_id)
            if press is None or press.request_id != ack.request_id:
                return  # a repeated ack, or one of another sender
            del self._pending[ack.machine_id]
        log.info("E-STOP %s confirmed after %.1f ms (%d put(s), %d press(es))", ack.machine_id,
                 (time.monotonic() - press.first_s) * 1e3, press.sent, press.presses)
        if not ack.latch_persisted:
            log.error("E-STOP %s: the runtime could not write its latch to disk", ack.machine_id)
        press.future.set_result(ack)

    def pending(self) -> dict[str, int]:
        """machine id -> presses waiting for its unconfirmed stop."""
        with self._lock:
            return {m: p.presses for m, p in self._pending.items()}

    def close(self) -> None:
        """Stop resending; unconfirmed presses fail."""
        self._closed = True
        self._wake.set()
        self._timer.join(timeout=2.0)
        with self._lock:
            left, self._pending = list(self._pending.values()), {}
        for press in left:
            if not press.future.done():
                press.future.set_exception(EstopUnconfirmed(f"E-STOP of {press.machine_id}: server stopping"))

    # --- internals ------------------------------------------------------------------------------
    def _put(self, press: Press) -> None:
        try:
            self.session.put(keys.estop(press.machine_id), press.payload, congestion_control=zenoh.CongestionControl.DROP,
                             priority=zenoh.Priority.REAL_TIME, express=True)
            press.sent += 1
        except Exception:  # a closed session: the deadline reports it
            log.exception("E-STOP put for %s failed", press.machine_id)

    def _resend_loop(self) -> None:
        while not self._closed:
            self._wake.wait(self.resend_s)
            self._wake.clear()
            now = time.monotonic()
            expired, again = [], []
            with self._lock:
                for mid, press in list(self._pending.items()):
                    if now >= press.deadline_s:
                        expired.append(self._pending.pop(mid))
                    elif now - press.first_s >= self.resend_s * press.sent:
                        again.append(press)
            for press in again:
                self._put(press)
            for press in expired:
                log.warning("E-STOP of %s not confirmed within %.1f s (%d put(s), %d press(es))", press.machine_id,
                            self.deadline_s, press.sent, press.presses)
                press.future.set_exception(EstopUnconfirmed(
                    f"E-STOP of {press.machine_id} sent {press.sent} times, not confirmed within {self.deadline_s:.1f} s "
                    "(runtime offline, frozen or unreachable)"))
