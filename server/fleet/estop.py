"""The server's E-STOP path: a fire-and-forget put per machine, confirmed separately.

An E-STOP press becomes a signed (when it can be) AbortRequest with a fresh ``request_id``, put on
``keys.estop(machine_id)`` at once on the caller's thread: a Zenoh put with congestion control
DROP, priority REAL_TIME and express, so it never blocks on a slow or frozen peer and never waits
for a query, a thread pool or another machine. The runtime latches, writes the latch to disk and
publishes an AbortAck with the same ``request_id`` on ``keys.estop_ack``; :meth:`EstopLine.on_ack`
(a Zenoh callback) resolves the press's Future. Until then the put is repeated every
``resend_s`` (a dropped put is sent again) up to the press's own deadline, after which its
Future fails with :class:`server.fleet.commands.RuntimeUnavailable` ("not confirmed").

Presses of a machine whose stop is still unconfirmed join it (coalesced: one put stream, one
Future for all of them); a press after the confirmation sends a new stop. Nothing here is shared
between machines but one timer thread that only re-puts (non-blocking) and expires deadlines.

**A stop that could not be delivered stays pressed.** A press not confirmed by its deadline
becomes the machine's server-side :class:`Latch` (as does a confirmed one whose runtime could not
write its own latch to disk): the stop is put again, freshly signed, every ``relatch_s`` until a
runtime acknowledges it, and again whenever the machine's runtime comes (back) online
(:meth:`EstopLine.runtime_online`), so a restarted runtime is latched before the server would
show it ready. While latched the server shows the machine E-STOPPED and refuses its throws and
moves (server.fleet.commands); only :meth:`EstopLine.reset` (after the runtime confirmed a
deliberate reset) clears it. The latches are written to ``latch_file`` (JSON, atomically, on a
thread of their own, retried until it succeeds) and read back at start, so they survive a
restart of the server; while the file cannot be written the in-memory latch holds.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field
from pathlib import Path

import zenoh
from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import ABORT_REASON_CHARS, AbortAck, AbortRequest, decode_on_key, encode
from server.fleet.commands import RuntimeUnavailable

log = logging.getLogger(__name__)

RESEND_S = 0.05
"""An unconfirmed E-STOP put is repeated this often, s."""
DEADLINE_S = 2.0
"""A press not confirmed within this long fails (HTTP 503 "not confirmed"), s; the machine is then
latched on the server and its stop is put every RELATCH_S until a runtime acknowledges it."""
RELATCH_S = 0.25
"""A server-latched stop that no runtime has acknowledged yet is put again this often, s."""
MAX_LATCHES = 1024
"""At most this many machines are latched on the server (ids are validated; more is a fault)."""


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
    reason: str = ""
    user: str = ""


@dataclass
class Latch:
    """A machine's E-STOP held by the server (module docstring).

    Attributes:
        machine_id: the machine.
        reason: the press's reason (with the operator's name).
        user: who pressed.
        request_id: the ``request_id`` its puts carry (acks of it confirm the latch).
        since_unix_s: when it was pressed, Unix s.
        acked: a runtime acknowledged this stop (since it last came online); puts stop until the
            runtime comes online again.
    """

    machine_id: str
    reason: str
    user: str
    request_id: str
    since_unix_s: float
    acked: bool = False
    sent: int = 0
    last_put_s: float = 0.0
    resetting: bool = False

    def describe(self) -> str:
        """The latch in words, for the console and the API."""
        state = "confirmed by the runtime" if self.acked else "NOT confirmed by the runtime: sent until it is"
        return f"E-STOP pressed ({self.reason}); held by the server, {state}; reset to release"


class EstopLine:
    """Per-machine E-STOP sends and their confirmations.

    Args:
        session: an open Zenoh session (the caller declares :meth:`on_ack` on keys.ALL_ESTOP_ACKS).
        sign: ``sign(request, machine_id, user) -> AbortRequest`` (signed, or unchanged when the
            server cannot sign it: aborts are honoured unsigned).
        resend_s: see RESEND_S.
        deadline_s: see DEADLINE_S.
        relatch_s: see RELATCH_S.
        latch_file: where the server's latches are kept across restarts (None: memory only).
    """

    def __init__(self, session: zenoh.Session, sign: Callable[[AbortRequest, str, str], AbortRequest],
                 resend_s: float = RESEND_S, deadline_s: float = DEADLINE_S, relatch_s: float = RELATCH_S,
                 latch_file: Path | None = None):
        self.session = session
        self.sign = sign
        self.resend_s = resend_s
        self.deadline_s = deadline_s
        self.relatch_s = relatch_s
        self.latch_file = latch_file
        self._lock = threading.Lock()
        self._pending: dict[str, Press] = {}
        self._latches: dict[str, Latch] = self._load_latches()
        self._persist_wanted = threading.Event()
        self._persisted_ok = True
        self.coalesced = 0
        """Presses that joined an unconfirmed stop (for tests and diagnostics)."""
        self._wake = threading.Event()
        self._closed = False
        self._timer = threading.Thread(target=self._resend_loop, name="estop-resend", daemon=True)
        self._timer.start()
        self._persister = threading.Thread(target=self._persist_loop, name="estop-latch-file", daemon=True)
        self._persister.start()

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
        request = AbortRequest(machine_id=machine_id, reason=reason[:ABORT_REASON_CHARS], request_id=request_id)
        try:
            request = self.sign(request, machine_id, user)
        except ValueError as e:
            log.warning("E-STOP of %s sent unsigned: %s", machine_id, e)
        press = Press(machine_id, request_id, encode(request), time.monotonic() + self.deadline_s,
                      reason=request.reason, user=user)
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
            latch = self._latches.get(ack.machine_id)
            if latch is not None and not latch.acked and ack.request_id in (latch.request_id, *self._press_ids(ack.machine_id)):
                latch.acked = True
                log.warning("server-latched E-STOP of %s acknowledged by its runtime (%d put(s))", ack.machine_id,
                            latch.sent)
            press = self._pending.get(ack.machine_id)
            if press is None or press.request_id != ack.request_id:
                return  # a repeated ack, or one of another sender
            del self._pending[ack.machine_id]
            if not ack.latch_persisted:  # the runtime's latch would not survive its restart: hold it here
                self._latch_locked(press, acked=True)
        log.info("E-STOP %s confirmed after %.1f ms (%d put(s), %d press(es))", ack.machine_id,
                 (time.monotonic() - press.first_s) * 1e3, press.sent, press.presses)
        if not ack.latch_persisted:
            log.error("E-STOP %s: the runtime could not write its latch to disk", ack.machine_id)
        press.future.set_result(ack)

    def _press_ids(self, machine_id: str) -> tuple[str, ...]:
        press = self._pending.get(machine_id)
        return (press.request_id,) if press is not None else ()

    def latch(self, machine_id: str) -> Latch | None:
        """The server's latch of ``machine_id`` (a copy), None when it holds none."""
        with self._lock:
            latch = self._latches.get(machine_id)
            return Latch(**asdict(latch)) if latch is not None else None

    def latched_ids(self) -> set[str]:
        with self._lock:
            return set(self._latches)

    def runtime_online(self, machine_id: str) -> None:
        """The machine's runtime came (back) online: a latched stop must be acknowledged by it
        again, and is put at once."""
        with self._lock:
            latch = self._latches.get(machine_id)
            if latch is None:
                return
            latch.acked = False
            latch.last_put_s = 0.0
        self._wake.set()

    def begin_reset(self, machine_id: str) -> None:
        """Stop putting ``machine_id``'s latched stop while a reset is asked of its runtime (a put
        arriving after the reset would latch it again); :meth:`end_reset` follows."""
        with self._lock:
            latch = self._latches.get(machine_id)
            if latch is not None:
                latch.resetting = True

    def end_reset(self, machine_id: str, released: bool) -> None:
        """The runtime answered the reset: ``released`` clears the server's latch (persisted);
        otherwise the latch holds and its puts resume."""
        with self._lock:
            latch = self._latches.pop(machine_id, None) if released else self._latches.get(machine_id)
            if latch is not None and not released:
                latch.resetting = False
        if released and latch is not None:
            log.warning("server-latched E-STOP of %s reset", machine_id)
            self._persist_wanted.set()

    def release_unknown(self, machine_id: str) -> None:
        """Drop a latch of a machine that turned out not to exist (an E-STOP of an unknown id)."""
        with self._lock:
            dropped = self._latches.pop(machine_id, None)
        if dropped is not None:
            self._persist_wanted.set()

    @property
    def latches_persisted(self) -> bool:
        """False while the latch file could not be written (the in-memory latches hold)."""
        return self._persisted_ok

    def pending(self) -> dict[str, int]:
        """machine id -> presses waiting for its unconfirmed stop."""
        with self._lock:
            return {m: p.presses for m, p in self._pending.items()}

    def close(self) -> None:
        """Stop resending; unconfirmed presses fail."""
        self._closed = True
        self._wake.set()
        self._timer.join(timeout=2.0)
        self._persister.join(timeout=2.0)
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

    def _latch_locked(self, press: Press, acked: bool) -> None:
        """Hold ``press``'s stop as the machine's latch (caller holds the lock)."""
        if press.machine_id not in self._latches and len(self._latches) >= MAX_LATCHES:
            log.error("E-STOP of %s not latched on the server: %d machines latched already", press.machine_id,
                      len(self._latches))
            return
        reason = press.reason or "E-STOP"
        latch = self._latches.setdefault(press.machine_id, Latch(press.machine_id, reason, press.user,
                                                                 press.request_id, time.time()))
        latch.acked = latch.acked or acked
        self._persist_wanted.set()

    def _put_latch(self, latch: Latch) -> None:
        """Put a latched stop, signed afresh (the runtime may have restarted: a new epoch)."""
        request = AbortRequest(machine_id=latch.machine_id, reason=latch.reason[:ABORT_REASON_CHARS], request_id=latch.request_id)
        try:
            request = self.sign(request, latch.machine_id, latch.user)
        except ValueError as e:
            log.debug("latched E-STOP of %s sent unsigned: %s", latch.machine_id, e)
        try:
            self.session.put(keys.estop(latch.machine_id), encode(request), congestion_control=zenoh.CongestionControl.DROP,
                             priority=zenoh.Priority.REAL_TIME, express=True)
            latch.sent += 1
        except Exception:
            log.exception("latched E-STOP put for %s failed", latch.machine_id)

    def _resend_loop(self) -> None:
        while not self._closed:
            self._wake.wait(self.resend_s)
            self._wake.clear()
            now = time.monotonic()
            expired, again, relatch = [], [], []
            with self._lock:
                for mid, press in list(self._pending.items()):
                    if now >= press.deadline_s:
                        expired.append(self._pending.pop(mid))
                        self._latch_locked(press, acked=False)
                    elif now - press.first_s >= self.resend_s * press.sent:
                        again.append(press)
                for latch in self._latches.values():
                    if not latch.acked and not latch.resetting and latch.machine_id not in self._pending \
                            and now - latch.last_put_s >= self.relatch_s:
                        latch.last_put_s = now
                        relatch.append(latch)
            for press in again:
                self._put(press)
            for latch in relatch:
                self._put_latch(latch)
            for press in expired:
                log.warning("E-STOP of %s not confirmed within %.1f s (%d put(s), %d press(es))", press.machine_id,
                            self.deadline_s, press.sent, press.presses)
                press.future.set_exception(EstopUnconfirmed(
                    f"E-STOP of {press.machine_id} sent {press.sent} times, not confirmed within {self.deadline_s:.1f} s "
                    "(runtime offline, frozen or unreachable); the server holds it latched and sends it until the "
                    "runtime confirms"))

    # --- the latch file ----------------------------------------------------------------------------
    def _load_latches(self) -> dict[str, Latch]:
        if self.latch_file is None or not self.latch_file.exists():
            return {}
        try:
            rows = json.loads(self.latch_file.read_text())
            latches = {keys.validate_machine_id(r["machine_id"]): Latch(
                r["machine_id"], str(r["reason"]), str(r["user"]), str(r["request_id"]), float(r["since_unix_s"]))
                for r in rows}
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("E-STOP latch file %s not read (%s): latches held before the restart are lost", self.latch_file, e)
            return {}
        if latches:
            log.warning("E-STOP latched on the server from before its restart: %s", ", ".join(sorted(latches)))
        return latches

    def _persist_loop(self) -> None:
        while not self._closed:
            if self._persist_wanted.wait(0.5):
                self._persist_wanted.clear()
                if not self._persist_once():
                    self._persist_wanted.set()
                    time.sleep(1.0)
        if self._persist_wanted.is_set():
            self._persist_once()

    def _persist_once(self) -> bool:
        """Write the latches to the latch file; False if it could not be written."""
        if self.latch_file is None:
            return True
        with self._lock:
            rows = [{k: v for k, v in asdict(latch).items() if k in ("machine_id", "reason", "user", "request_id",
                                                                       "since_unix_s")}
                    for latch in self._latches.values()]
        try:
            _write_atomically(self.latch_file, json.dumps(rows, indent=1).encode())
            if not self._persisted_ok:
                log.warning("E-STOP latch file %s written again", self.latch_file)
            self._persisted_ok = True
        except OSError as e:
            if self._persisted_ok:
                log.error("E-STOP latch file %s not written (%s): the latches hold in memory; retrying",
                          self.latch_file, e)
            self._persisted_ok = False
        return self._persisted_ok


def _write_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a fsynced temporary file and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
