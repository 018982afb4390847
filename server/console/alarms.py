"""Alarms kept on the server, after ISA-18.2 / IEC 62682 (alarm management for process plants).

An alarm is a condition that needs an operator's response: it is **raised** when the condition
starts, **cleared** when the condition is gone (return to normal), **acknowledged** by an
operator (who and when are kept), and may be **shelved** by an operator for a bounded time
(hidden from the banner, still listed). It leaves the active list only once it is both cleared
and acknowledged; the row stays as the alarm history. Each change is written to the audit log
(``alarm_raise``, ``alarm_clear``, ``alarm_ack``, ``alarm_shelve``, ``alarm_unshelve``) and
published to every open console (``alarm`` events over ``/api/live``).

What raises alarms (:meth:`AlarmService.on_event`, a consumer of the fleet's events, and
:meth:`AlarmService.on_drift`):

* a runtime going offline (``RuntimeOffline``), high; cleared when it is back online;
* a throw that failed or was lost (``ResultStored``), with its cause named from the reason
  (:func:`failure_cause`: the host fell behind real time, the runtime did not answer, the link
  was lost, a machine fault), high; cleared at once (the throw is over), so it stays until acknowledged;
* an open drift alert (:mod:`server.analysis.drift`), medium; cleared when the alert is acknowledged.

The operator's own acts are events, not alarms: a throw aborted by an operator's E-STOP or
abort is in the throw history and the audit log, never in the alarm list.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.accounts.auth import audit
from server.db.models import Alarm, Throw
from server.db.types import utcnow
from server.errors import Conflict, NotFound, Refused
from server.fleet.events import FleetEvent, ResultStored, RuntimeOffline, RuntimeOnline

log = logging.getLogger(__name__)

MAX_SHELVE_MIN = 8 * 60
"""Longest shelving, minutes (one shift): a shelved alarm always comes back."""
HISTORY_LIMIT = 500
"""Most rows one history request returns."""
LOADED_PER_CORE = 1.5
"""This host's 1-minute load per CPU core above which a link fault names the load as its likely cause."""


def host_load() -> tuple[float, int] | None:
    """This host's 1-minute load average and its CPU count (None where the OS has no load average)."""
    try:
        return os.getloadavg()[0], os.cpu_count() or 1
    except (OSError, AttributeError):
        return None


def failure_cause(machine_id: str, reason: str | None, simulated: bool = False,
                  load: tuple[float, int] | None = None) -> tuple[str, str, str, str] | None:
    """The cause of a failed throw in the operator's words, or None for the operator's own stop.

    Args:
        machine_id: the machine.
        reason: the throw's failure reason (from its runtime or the server's reconciliation).
        simulated: the machine is the simulated one (its "control computer" is this host's plant).
        load: (1-minute load average, CPU count) of the server's host, or None.

    Returns:
        (cause, title, text, todo): ``cause`` one of ``host_behind_real_time``,
        ``runtime_not_answering``, ``link_lost``, ``machine_fault``; or None when the throw was
        stopped by an operator (E-STOP, abort): an event, not an alarm.
    """
    r = (reason or "").lower()
    sim = "simulated " if simulated else ""
    busy = ""
    if load is not None and load[0] / max(load[1], 1) > LOADED_PER_CORE:
        busy = (f" This server's host is loaded (load {load[0]:.1f} on {load[1]} cores): a slow host delays "
                "messages, so check its load before the network.")
    if "e-stop" in r or "abort" in r:
        return None
    if "real time" in r:
        return ("host_behind_real_time", f"{machine_id}: control computer behind real time",
                f"The {sim}machine's control computer fell behind real time ({reason}); the runtime stopped the "
                "swing and set the valves to neutral. This is the computer's load, not the network.",
                "Reduce the load on that computer, wait until the state is READY, then preview and throw again.")
    if any(w in r for w in ("not answering", "no result", "restarted", "not running the throw", "runtime")):
        return ("runtime_not_answering", f"{machine_id}: runtime not answering",
                f"The runtime of {machine_id} did not answer during the throw ({reason})." + busy,
                "Check on the Fleet page that its runtime runs; preview again once the machine is READY.")
    if "link" in r or "offline" in r:
        return ("link_lost", f"{machine_id}: machine link lost",
                f"The link between the runtime and the {sim}machine {machine_id} was lost during the throw ({reason})." + busy,
                "Check the machine's network and its computer's load; preview again once it is READY.")
    return ("machine_fault", f"{machine_id}: machine fault",
            f"The machine {machine_id} reported a fault ({reason or 'no reason given'}).",
            "Look at the machine; return it to the ready pose if offered, then preview again.")


def alarm_dict(a: Alarm, now: datetime | None = None) -> dict:
    """The API's and the live event's view of an alarm row; ``state`` is the ISA-18.2 state:
    ``unacked`` (active, not acknowledged), ``acked`` (active, acknowledged), ``rtn_unacked``
    (cleared, not acknowledged), ``normal`` (cleared and acknowledged: history); ``shelved``
    while its shelving lasts; ``revision`` orders one alarm's records (models.Alarm.revision)."""
    now = now or utcnow()
    if a.cleared_at is None:
        state = "acked" if a.acked_at else "unacked"
    else:
        state = "normal" if a.acked_at else "rtn_unacked"
    shelved = a.shelved_until is not None and a.shelved_until > now and a.active
    iso = lambda t: t.isoformat() if t is not None else None  # noqa: E731
    return {"id": a.id, "key": a.key, "machine_id": a.machine_id, "priority": a.priority, "cause": a.cause,
            "title": a.title, "text": a.text, "todo": a.todo, "subject": a.subject, "state": state,
            "active": a.active, "shelved": shelved, "raised_at": iso(a.raised_at), "cleared_at": iso(a.cleared_at),
            "acked_at": iso(a.acked_at), "acked_by": a.acked_by, "revision": a.revision,
            "shelved_until": iso(a.shelved_until) if shelved else None, "shelved_by": a.shelved_by if shelved else None}


class AlarmService:
    """The server's alarms (module doc).

    Args:
        sessions: database session factory.
        publish: ``publish(event, data)`` (the live hub's), called with ``("alarm", alarm_dict)``
            on every change; None: not published.
        drift_ack: ``drift_ack(machine_id, username)`` acknowledges a machine's drift alert
            (server.analysis.drift.DriftWatch.acknowledge), called when a drift alarm is acknowledged.
        simulated: ``simulated(machine_id) -> bool`` (the fleet's word), for the alarm texts.
    """

    def __init__(self, sessions: sessionmaker[Session], publish: Callable[[str, dict], None] | None = None,
                 drift_ack: Callable[[str, str], object] | None = None,
                 simulated: Callable[[str], bool] | None = None):
        self.sessions, self.publish, self.drift_ack = sessions, publish, drift_ack
        self.simulated = simulated or (lambda mid: False)
        self._lock = threading.Lock()

    # --- conditions -----------------------------------------------------------------------------
    def raise_alarm(self, key: str, machine_id: str | None, priority: str, cause: str, title: str, text: str,
                    todo: str, subject: str | None = None, cleared: bool = False) -> dict:
        """Raise the alarm of condition ``key``; while an alarm of that key is active and not
        cleared, it is returned as it is (one alarm per standing condition). ``cleared``: the
        condition is over already (a failed throw): the alarm waits for its acknowledgement."""
        with self._lock, self.sessions.begin() as db:
            cur = db.scalars(select(Alarm).where(Alarm.key == key, Alarm.active, Alarm.cleared_at.is_(None))).first()
            if cur is not None:
                return alarm_dict(cur)
            now = utcnow()
            a = Alarm(key=key, machine_id=machine_id, priority=priority, cause=cause, title=title[:200], text=text,
                      todo=todo, subject=subject, raised_at=now, cleared_at=now if cleared else None, active=True,
                      revision=1)
            db.add(a)
            audit(db, "system", "alarm_raise", machine_id, key=key, priority=priority, cause=cause, title=title)
            db.flush()
            out = alarm_dict(a)
        log.warning("alarm %s (%s): %s", key, priority, title)
        self._publish(out)
        return out

    def clear(self, key: str) -> list[dict]:
        """The condition ``key`` is gone: its active alarms are cleared (an acknowledged one
        leaves the active list)."""
        changed = []
        with self._lock, self.sessions.begin() as db:
            now = utcnow()
            for a in db.scalars(select(Alarm).where(Alarm.key == key, Alarm.active, Alarm.cleared_at.is_(None))):
                a.cleared_at = now
                a.active = a.acked_at is None
                a.revision += 1
                audit(db, "system", "alarm_clear", a.machine_id, key=key)
                changed.append(alarm_dict(a, now))
        for out in changed:
            self._publish(out)
        return changed

    # --- operator actions -----------------------------------------------------------------------
    def acknowledge(self, alarm_id: str, username: str) -> dict:
        """Acknowledge one alarm (a second acknowledgement keeps the first's who and when); returns
        its state after the acknowledgement's consequences (a drift alarm is then cleared).

        Raises:
            NotFound: no such alarm.
        """
        with self._lock, self.sessions.begin() as db:
            a = db.get(Alarm, alarm_id)
            if a is None:
                raise NotFound(f"no alarm {alarm_id}")
            changed = self._ack(db, a, username)
            out = alarm_dict(a)
        if changed:
            self._after_ack(out, username)
            out = self._current(alarm_id)  # a drift alarm was cleared meanwhile: the answer is its state now
        return out

    def acknowledge_all(self, username: str, machine_id: str | None = None) -> list[dict]:
        """Acknowledge every unacknowledged active alarm (of ``machine_id``, or of all machines);
        returns those acknowledged now."""
        with self._lock, self.sessions.begin() as db:
            q = select(Alarm).where(Alarm.active, Alarm.acked_at.is_(None))
            if machine_id is not None:
                q = q.where(Alarm.machine_id == machine_id)
            outs = [alarm_dict(a) for a in db.scalars(q).all() if self._ack(db, a, username)]
        for out in outs:
            self._after_ack(out, username)
        return [self._current(out["id"]) for out in outs]

    def shelve(self, alarm_id: str, username: str, minutes: float) -> dict:
        """Shelve an active alarm for ``minutes`` (0 < minutes <= :data:`MAX_SHELVE_MIN`): hidden
        from the banner, still listed; it comes back by itself when the time is up.

        Raises:
            Refused: minutes out of range.
            Conflict: the alarm is no longer active.
            NotFound: no such alarm.
        """
        if not 0 < minutes <= MAX_SHELVE_MIN:
            raise Refused(f"shelve for 1 to {MAX_SHELVE_MIN} minutes, not {minutes:g}")
        with self._lock, self.sessions.begin() as db:
            a = db.get(Alarm, alarm_id)
            if a is None:
                raise NotFound(f"no alarm {alarm_id}")
            if not a.active:
                raise Conflict("the alarm is cleared and acknowledged: nothing to shelve")
            a.shelved_until = utcnow() + timedelta(minutes=minutes)
            a.shelved_by = username
            a.revision += 1
            audit(db, username, "alarm_shelve", a.machine_id, alarm=a.id, key=a.key, minutes=minutes)
            out = alarm_dict(a)
        self._publish(out)
        return out

    def unshelve(self, alarm_id: str, username: str) -> dict:
        """End an alarm's shelving now.

        Raises:
            NotFound: no such alarm.
        """
        with self._lock, self.sessions.begin() as db:
            a = db.get(Alarm, alarm_id)
            if a is None:
                raise NotFound(f"no alarm {alarm_id}")
            if a.shelved_until is not None:
                a.shelved_until = None
                a.revision += 1
                audit(db, username, "alarm_unshelve", a.machine_id, alarm=a.id, key=a.key)
            out = alarm_dict(a)
        self._publish(out)
        return out

    # --- reading --------------------------------------------------------------------------------
    def active(self) -> list[dict]:
        """The active alarms (not yet both cleared and acknowledged), newest first."""
        with self.sessions() as db:
            now = utcnow()
            return [alarm_dict(a, now) for a in db.scalars(select(Alarm).where(Alarm.active)
                                                           .order_by(Alarm.raised_at.desc())).all()]

    def history(self, machine_id: str | None = None, limit: int = 100, offset: int = 0) -> list[dict]:
        """Every alarm, newest first (``limit`` at most :data:`HISTORY_LIMIT`)."""
        q = select(Alarm).order_by(Alarm.raised_at.desc()).limit(min(max(limit, 1), HISTORY_LIMIT)).offset(max(offset, 0))
        if machine_id is not None:
            q = q.where(Alarm.machine_id == machine_id)
        with self.sessions() as db:
            now = utcnow()
            return [alarm_dict(a, now) for a in db.scalars(q).all()]

    # --- sources --------------------------------------------------------------------------------
    def on_event(self, event: FleetEvent) -> None:
        """The fleet's consumer: offline runtimes and failed throws raise alarms, a runtime back
        online clears its offline alarm. Never raises (a consumer must not break the fleet)."""
        try:
            if isinstance(event, RuntimeOffline):
                mid = event.machine_id
                self.raise_alarm(f"offline:{mid}", mid, "high", "runtime_not_answering", f"{mid}: runtime offline",
                                 f"The runtime of {mid} stopped answering (its liveliness token is gone)."
                                 + _load_words(host_load()),
                                 "Check the machine's computer (its load first) and network; start its runtime again "
                                 "(slinger runtime).")
            elif isinstance(event, RuntimeOnline):
                self.clear(f"offline:{event.machine_id}")
            elif isinstance(event, ResultStored):
                self.on_result(event.throw_id)
        except Exception:
            log.exception("alarms: fleet event %s not handled", type(event).__name__)

    def on_result(self, throw_id: str) -> dict | None:
        """A stored result: a failed or lost throw raises an alarm naming its cause (cleared at
        once: the throw is over; it stays until acknowledged); returns it, else None."""
        with self.sessions() as db:
            t = db.get(Throw, throw_id)
            if t is None or t.status not in ("failed", "lost", "aborted"):
                return None
            mid, status, reason = t.machine_id, t.status, t.failure_reason
        found = failure_cause(mid, reason, self.simulated(mid), host_load())
        if found is None:
            return None  # the operator's own stop: an event (throw history, audit log), not an alarm
        cause, title, text, todo = found
        return self.raise_alarm(f"throw:{throw_id}", mid, "high", cause, f"{title} (throw {throw_id[:8]} {status})",
                                text, todo, subject=throw_id, cleared=True)

    def on_lost(self, throw_id: str) -> None:
        """A throw the reconciler closed as lost (server.fleet.reconcile: its result can never come,
        so no ResultStored event does either): the high alarm :meth:`on_result` raises for it.
        Never raises (the reconciler's sweep goes on)."""
        try:
            self.on_result(throw_id)
        except Exception:
            log.exception("alarms: lost throw %s not handled", throw_id)

    def on_drift(self, alert: dict) -> None:
        """A drift alert (server.analysis.drift): an open one raises a medium alarm, an acknowledged one
        clears it. Never raises."""
        try:
            mid = alert.get("machine_id")
            if not mid:
                return
            key = f"drift:{mid}:{alert.get('raised_at')}"
            if alert.get("status") == "open":
                self.raise_alarm(key, mid, "medium", "drift", f"{mid}: accuracy drift",
                                 alert.get("text") or "The impacts drifted beyond what noise explains.",
                                 "A diagnosis of the recent throws was started: read it on the Diagnosis page before "
                                 "throwing on.", subject=str(alert.get("raised_at"))[:64])
            else:
                self.clear(key)
        except Exception:
            log.exception("alarms: drift alert not handled")

    # --- helpers --------------------------------------------------------------------------------
    def _current(self, alarm_id: str) -> dict:
        with self.sessions() as db:
            a = db.get(Alarm, alarm_id)
            if a is None:
                raise NotFound(f"no alarm {alarm_id}")
            return alarm_dict(a)

    def _ack(self, db: Session, a: Alarm, username: str) -> bool:
        if a.acked_at is not None:
            return False
        a.acked_at, a.acked_by = utcnow(), username
        a.active = a.cleared_at is None
        a.revision += 1
        audit(db, username, "alarm_ack", a.machine_id, alarm=a.id, key=a.key, title=a.title)
        return True

    def _after_ack(self, out: dict, username: str) -> None:
        self._publish(out)
        if out["cause"] == "drift" and out["machine_id"] and self.drift_ack is not None:
            try:
                self.drift_ack(out["machine_id"], username)  # its "drift" event clears this alarm
                with self.sessions.begin() as db:
                    audit(db, username, "drift_ack", out["machine_id"], alarm=out["id"])
            except Exception:
                log.exception("alarms: drift alert of %s not acknowledged", out["machine_id"])

    def _publish(self, out: dict) -> None:
        if self.publish is not None:
            self.publish("alarm", out)


def _load_words(load: tuple[float, int] | None) -> str:
    if load is None or load[0] / max(load[1], 1) <= LOADED_PER_CORE:
        return ""
    return (f" This server's host is loaded (load {load[0]:.1f} on {load[1]} cores): a slow host is the likelier cause "
            "than the network.")
