"""No throw left hanging: the server's reconciliation of open throws with their runtimes.

A throw row is *open* while its status is not final (requested, preparing, swinging, released).
Only a stored ThrowResult closes it normally (server.fleet.results). When its runtime, plant or the
server itself dies, that result may come late (the runtime's durable outbox re-delivers it after
a server restart) or never (a runtime killed mid-swing keeps no record of a throw it did not
finish). :class:`Reconciler` checks every open throw against what the runtime says about itself
(RuntimeInfo: ``epoch``, ``throw_id``, ``phase``) and marks ``lost``, with the reason, what can
never arrive:

* the runtime is online but not running the throw (another ``throw_id``, or idle) and no result
  arrived within ``result_grace_s``: the outbox delivers on start and retries every 2 s
  (runtime.outbox), so a result it holds arrives well within the grace. The reason says whether
  the runtime restarted (its epoch differs from the one that accepted the throw);
* the runtime has been offline (no liveliness token) for ``runtime_gone_s``.

When it checks: a pass runs on start, at once on each fleet event that can change a verdict
(server.fleet.events: a runtime online or offline, a published RuntimeInfo whose epoch, throw or
busy flag changed), and at the earliest deadline one of its open throws waits for (the end of a
grace, of the offline bound, of a handshake). It reads the RuntimeInfo the runtime publishes (at
2 Hz and on every change; a query only when none was published in the last
:data:`INFO_MAX_AGE_S`). A sweep every ``period_s`` stays as a backstop while throws are open,
and every :data:`IDLE_SWEEP_S` while none is: events are Zenoh samples, which may be dropped, a
frozen runtime publishes nothing (its silence is a condition, not an event), and a throw row
appears in the database without any fleet event (a runtime that never answered its request).

Bounds (defaults, server.config.Settings): a throw is final at most ``runtime_gone_s`` (30 s)
after its runtime disappears, and ``result_grace_s`` (15 s) after a runtime that lost it is back
(each + ``period_s`` (2 s) when the event was lost); a throw whose runtime never answered its
request (no event at all) at most ``result_grace_s`` + :data:`IDLE_SWEEP_S` (10 s) after it was
requested. A plant that dies makes the runtime fail the
throw within its link timeout (0.2 s, runtime.service); a dead server finds the result in the
outbox on its return. A row younger than ``handshake_s`` is left alone: its ThrowRequest may
still be in flight.

A result that arrives after ``lost`` (e.g. a runtime cut off from the server for longer than
the bound, which finished the throw and kept the result) still replaces it (server.fleet.results).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from datetime import timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import FINAL_STATUSES, Throw
from server.db.types import utcnow
from server.fleet.events import FleetEvent, RuntimeInfoEvent, RuntimeOffline, RuntimeOnline
from server.fleet.link import Fleet

log = logging.getLogger(__name__)

RESULT_GRACE_S = 15.0
"""How long a runtime that is not running an open throw has to deliver its result, s."""
RUNTIME_GONE_S = 30.0
"""How long a runtime may stay offline before its open throws are lost, s (3x Zenoh's default
10 s lease, so a short link cut is not mistaken for a dead runtime)."""
PERIOD_S = 2.0
"""Seconds between backstop passes while throws are open."""
IDLE_SWEEP_S = 10.0
"""Seconds between backstop passes while no throw is open (a row that appears without a fleet event)."""
INFO_MAX_AGE_S = 1.0
"""A published RuntimeInfo at most this old is used as is (runtimes publish at 2 Hz), s."""


class Reconciler:
    """Marks open throws ``lost`` when their result can never arrive (see the module doc).

    Register :meth:`on_event` as a fleet consumer (server.app does) so passes follow the fleet's
    events; without it passes run only on the backstop sweep.

    Args:
        fleet: runtime presence (:meth:`Fleet.is_online`, :meth:`Fleet.offline_for_s`) and
            RuntimeInfo (:meth:`Fleet.published_info`, :meth:`Fleet.fresh_info`).
        sessions: database sessions.
        mark_lost: ``(throw_id, reason) -> bool`` closes an open row as lost (ResultStore.mark_lost).
        result_grace_s / runtime_gone_s: the bounds above, s.
        period_s: the backstop sweep while throws are open, s.
        handshake_s: rows younger than this (wall clock) are skipped, s.
        clock: monotonic seconds (tests pass a fake).
        on_lost: called with the id of each throw this closes as lost (no ThrowResult, so no
            ResultStored, tells anyone else: server.services has the live hub announce it,
            :meth:`server.console.live.LiveHub.throw_closed`, and the alarms raise its alarm,
            :meth:`server.console.alarms.AlarmService.on_lost`); None: nobody is told.
    """

    def __init__(self, fleet: Fleet, sessions: sessionmaker[Session], mark_lost: Callable[[str, str], bool],
                 result_grace_s: float = RESULT_GRACE_S, runtime_gone_s: float = RUNTIME_GONE_S,
                 period_s: float = PERIOD_S, handshake_s: float = 7.0, clock: Callable[[], float] = time.monotonic,
                 on_lost: Callable[[str], None] | None = None):
        self.fleet, self.sessions, self.mark_lost, self.on_lost = fleet, sessions, mark_lost, on_lost
        self.result_grace_s, self.runtime_gone_s = float(result_grace_s), float(runtime_gone_s)
        self.period_s, self.handshake_s = float(period_s), float(handshake_s)
        self.clock = clock
        self._not_running_since: dict[str, float] = {}
        self._seen: dict[str, tuple] = {}  # machine id -> (epoch, throw id, busy) last published
        self._next_s = 0.0  # seconds from the last pass to the earliest deadline it waits for
        self._pass_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def on_event(self, event: FleetEvent) -> None:
        """Fleet consumer: wake a pass on an event that can change a verdict (never blocks)."""
        if isinstance(event, (RuntimeOnline, RuntimeOffline)):
            self._seen.pop(event.machine_id, None)
            self.wake()
        elif isinstance(event, RuntimeInfoEvent):
            info = event.info
            key = (info.epoch, info.throw_id, info.busy)
            if self._seen.get(info.machine_id) != key:
                self._seen[info.machine_id] = key
                self.wake()

    def wake(self) -> None:
        """Have the running thread make a pass now."""
        self._wake.set()

    def start(self) -> None:
        """Run a pass now, then on events, deadlines and the backstop sweep, on a daemon thread."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="reconcile", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()  # events from here on wake the next pass
            try:
                self.run_once()
            except Exception:
                log.exception("reconciliation pass failed")
                self._next_s = self.period_s
            self._wake.wait(self._next_s)

    def run_once(self) -> list[tuple[str, str]]:
        """One pass over the open throws; returns the (throw id, reason) pairs marked lost."""
        with self._pass_lock:
            return self._pass()

    def _pass(self) -> list[tuple[str, str]]:
        now_wall = utcnow()
        young = now_wall - timedelta(seconds=self.handshake_s)
        with self.sessions() as db:
            rows = db.execute(select(Throw.id, Throw.machine_id, Throw.runtime_epoch, Throw.requested_at)
                              .where(Throw.status.not_in(FINAL_STATUSES))).all()
        open_ids = {r.id for r in rows}
        for tid in list(self._not_running_since):
            if tid not in open_ids:
                del self._not_running_since[tid]
        lost = []
        infos: dict = {}
        waits = [self.period_s if rows else IDLE_SWEEP_S]
        for r in rows:
            if r.requested_at > young:
                waits.append((r.requested_at - young).total_seconds())
                continue
            reason = self._verdict(r.id, r.machine_id, r.runtime_epoch, infos, waits)
            if reason is not None and self.mark_lost(r.id, reason):
                log.warning("throw %s lost: %s", r.id, reason)
                self._not_running_since.pop(r.id, None)
                lost.append((r.id, reason))
                if self.on_lost is not None:
                    self.on_lost(r.id)
        self._next_s = max(min(waits), 0.01)
        return lost

    def _verdict(self, throw_id: str, machine_id: str, epoch: int | None, infos: dict, waits: list[float]) -> str | None:
        """The reason the throw's result can never arrive, or None (wait; the seconds to the
        deadline it waits for, if any, are appended to ``waits``). ``infos`` caches the
        RuntimeInfo read once per machine and pass: the published one if fresh, else asked."""
        now = self.clock()
        if not self.fleet.is_online(machine_id):
            gone_s = self.fleet.offline_for_s(machine_id)
            if gone_s >= self.runtime_gone_s:
                return (f"runtime of {machine_id} offline for {gone_s:.0f} s (bound {self.runtime_gone_s:.0f} s): "
                        "the throw's result can no longer be expected")
            waits.append(self.runtime_gone_s - gone_s)
            return None
        if machine_id not in infos:
            infos[machine_id] = (self.fleet.published_info(machine_id, INFO_MAX_AGE_S)
                                 or self.fleet.fresh_info(machine_id, max_age_s=0.0, timeout_s=1.0))
        info = infos[machine_id]
        if info is None:
            return None
        if info.throw_id == throw_id:
            self._not_running_since.pop(throw_id, None)
            return None
        since = self._not_running_since.setdefault(throw_id, now)
        if now - since < self.result_grace_s:
            waits.append(self.result_grace_s - (now - since))
            return None
        if epoch is not None and info.epoch != epoch:
            return (f"runtime of {machine_id} restarted (epoch {epoch} -> {info.epoch}) and delivered no result "
                    f"within {self.result_grace_s:.0f} s: the throw died with the old runtime")
        return (f"runtime of {machine_id} is not running the throw and delivered no result within "
                f"{self.result_grace_s:.0f} s")
