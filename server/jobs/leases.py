"""Worker leases: a job whose worker process died is re-run by another worker, a bounded number
of times.

Huey consumes a queue message when a worker takes the job; if that worker process dies (kill -9,
a lost host) the message is gone. Our ``jobs`` row therefore carries the running worker's claim
(``worker_id``: random per process, ``worker_host``, ``worker_pid``) and a lease
(``heartbeat_at``, ``lease_expires_at``) that the worker's heartbeat thread renews every
``heartbeat_s``. Every worker, on every host, also *reaps* every ``heartbeat_s``: a ``running``
job of another worker is orphaned when

* its lease expired (any host: the worker stopped renewing it for ``lease_s``), or
* its worker ran on this host and its pid no longer exists (found at once, no lease wait).

An orphaned job is put back to ``queued`` (progress 0, message naming the dead worker) and its
Huey task enqueued again, so that any worker runs it from the start, until it has been started
``max_attempts`` times; then it is ``failed`` with the reason. A job someone asked to cancel is
``cancelled`` instead. Claims and re-queues are conditional updates (``WHERE status='running' AND
worker_id=<dead one>``), so two reapers never both re-queue one job, and a worker only starts a
``queued`` job (server.jobs.store.JobStore.start), so a stale queue message never runs a job twice.

Timestamps are each worker's UTC clock: hosts' clocks must agree (NTP) to well within
``lease_s`` (default 15 s).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
from dataclasses import dataclass, field
from datetime import timedelta

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import Job
from server.db.session import rowcount
from server.db.types import utcnow

log = logging.getLogger(__name__)

HEARTBEAT_S = 2.0
"""Default period of lease renewal and reaping, seconds."""
LEASE_S = 15.0
"""Default lease: a worker silent this long (seconds) is taken for dead by workers on other hosts."""
MAX_ATTEMPTS = 3
"""Default number of starts of one job before a dead worker fails it instead of re-queueing it."""


@dataclass(frozen=True)
class WorkerIdentity:
    """Who runs a job: ``id`` random per process, ``host`` (socket.gethostname()), ``pid``."""

    id: str = field(default_factory=lambda: uuid.uuid4().hex)
    host: str = field(default_factory=socket.gethostname)
    pid: int = field(default_factory=os.getpid)

    @property
    def name(self) -> str:
        """``host:pid``, the ``jobs.worker`` column shown in the console."""
        return f"{self.host}:{self.pid}"


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (signal 0)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Leases:
    """Renews this worker's leases and re-queues (or fails) jobs of dead workers.

    Args:
        sessions: database session factory (the ``jobs`` table).
        me: this worker.
        requeue: ``requeue(job_id, kind)`` enqueues the job's task again (JobQueue.enqueue).
        lease_s: lease written with each renewal, seconds (> heartbeat_s).
        heartbeat_s: renewal and reaping period, seconds.
        max_attempts: starts of one job before it is failed instead of re-queued (>= 1).

    Raises:
        ValueError: non-positive periods, lease not longer than the heartbeat, max_attempts < 1.
    """

    def __init__(self, sessions: sessionmaker[Session], me: WorkerIdentity, requeue, lease_s: float = LEASE_S,
                 heartbeat_s: float = HEARTBEAT_S, max_attempts: int = MAX_ATTEMPTS):
        if not (heartbeat_s > 0 and lease_s > heartbeat_s):
            raise ValueError(f"need 0 < heartbeat_s < lease_s, got heartbeat_s={heartbeat_s}, lease_s={lease_s}")
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {max_attempts}")
        self.sessions, self.me, self.requeue = sessions, me, requeue
        self.lease_s, self.heartbeat_s, self.max_attempts = float(lease_s), float(heartbeat_s), int(max_attempts)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def renew(self) -> int:
        """Extend the lease of every job this worker runs; returns how many."""
        now = utcnow()
        with self.sessions.begin() as db:
            res = db.execute(update(Job).where(Job.worker_id == self.me.id, Job.status == "running")
                             .values(heartbeat_at=now, lease_expires_at=now + timedelta(seconds=self.lease_s)))
            return rowcount(res)

    def reap(self) -> list[tuple[str, str]]:
        """Re-queue, fail or cancel ``running`` jobs of dead workers (see the module doc).
        Returns ``[(job_id, new_status)]``."""
        now = utcnow()
        with self.sessions() as db:
            rows = db.execute(select(Job.id, Job.kind, Job.worker, Job.worker_id, Job.worker_host, Job.worker_pid,
                                     Job.lease_expires_at, Job.attempts, Job.cancel_requested)
                              .where(Job.status == "running")).all()
        out = []
        for r in rows:
            if r.worker_id == self.me.id:
                continue
            if r.worker_host == self.me.host and r.worker_pid is not None and not pid_alive(r.worker_pid):
                why = f"worker {r.worker} died (pid {r.worker_pid} gone)"
            elif r.lease_expires_at is not None and r.lease_expires_at < now:
                why = f"worker {r.worker} died (lease expired at {r.lease_expires_at.isoformat(timespec='seconds')})"
            else:
                continue
            status = self._orphaned(r.id, r.kind, r.worker_id, r.attempts, r.cancel_requested, why)
            if status:
                out.append((r.id, status))
        return out

    def release_own(self, why: str) -> list[tuple[str, str]]:
        """At this worker's exit: its running jobs are re-queued (or failed at the limit)."""
        with self.sessions() as db:
            rows = db.execute(select(Job.id, Job.kind, Job.attempts, Job.cancel_requested)
                              .where(Job.status == "running", Job.worker_id == self.me.id)).all()
        out = []
        for r in rows:
            status = self._orphaned(r.id, r.kind, self.me.id, r.attempts, r.cancel_requested,
                                    f"worker {self.me.name} {why}")
            if status:
                out.append((r.id, status))
        return out

    def _orphaned(self, job_id: str, kind: str, worker_id: str | None, attempts: int, cancel: bool, why: str) -> str | None:
        values: dict[str, object]
        if cancel:
            status, values = "cancelled", {"message": f"cancelled ({why})"}
        elif attempts >= self.max_attempts:
            status, values = "failed", {"error": f"{why} on attempt {attempts} of {self.max_attempts}; "
                                                 f"not re-run (limit of {self.max_attempts} attempts reached)"}
        else:
            status, values = "queued", {"progress": 0.0, "message": f"re-queued: {why} on attempt {attempts} of "
                                                                    f"{self.max_attempts}; it starts over"}
        if status != "queued":
            values["finished_at"] = utcnow()
        with self.sessions.begin() as db:
            res = db.execute(update(Job).where(Job.id == job_id, Job.status == "running", Job.worker_id == worker_id)
                             .values(status=status, lease_expires_at=None, **values))
            if not rowcount(res):
                return None  # another reaper got there first, or the worker finished it meanwhile
        if status == "queued":
            self.requeue(job_id, kind)
            log.warning("job %s (%s) %s", job_id, kind, values["message"])
        else:
            log.warning("job %s (%s) %s: %s", job_id, kind, status, values.get("error") or values["message"])
        return status

    # --- the heartbeat thread -------------------------------------------------------------
    def start(self) -> None:
        """Renew and reap every ``heartbeat_s`` on a daemon thread until :meth:`stop`."""
        self._thread = threading.Thread(target=self._loop, name="job-leases", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.heartbeat_s + 5)

    def _loop(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            try:
                self.renew()
                self.reap()
            except Exception:  # a database hiccup must not end the heartbeat
                log.exception("job lease renewal/reaping failed; retrying in %.1f s", self.heartbeat_s)
