"""The ``jobs`` table (server.db.models.Job): what a job is, how far it got, what came of it.

Both sides use it: the API creates rows and reads them (list, get, the progress stream), the
worker moves them ``queued -> running -> done | failed | cancelled`` and writes progress; a job
whose worker died goes back ``running -> queued`` (server.jobs.leases).
Cancellation is cooperative: :meth:`JobStore.cancel` sets ``cancel_requested``; a queued job is
cancelled at once, a running one at its next :meth:`JobStore.progress` call.
"""

from __future__ import annotations

import builtins
import logging
import time
from datetime import datetime, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from server.db.models import FINAL_JOB_STATUSES, JOB_KINDS, Job
from server.db.session import rowcount
from server.db.types import utcnow
from server.errors import Limited
from server.jobs.leases import LEASE_S, WorkerIdentity
from server.jobs.specs import JobSpecError, parse_spec

log = logging.getLogger(__name__)

PROGRESS_MIN_INTERVAL_S = 0.2
"""Progress is written at most this often per job (the last call of a burst is kept in memory)."""


USER_STARTED_KINDS = ("preview", "probe")
"""Job kinds a user starts at will, counted against :attr:`JobStore.max_active_per_user`
(diagnoses and adaptations run one at a time anyway; an evaluation follows each upload)."""
MAX_ACTIVE_PER_USER = 4
"""Default: queued or running jobs of :data:`USER_STARTED_KINDS` one user may have."""


class JobCancelled(Exception):
    """Raised inside a running job when someone asked to cancel it."""


class JobLimit(Limited):
    """The user already has their limit of queued or running jobs; the message says so."""


class JobStore:
    """Rows of the ``jobs`` table.

    Args:
        sessions: database session factory (the API's or the worker's).
    """

    def __init__(self, sessions: sessionmaker[Session], max_active_per_user: int = MAX_ACTIVE_PER_USER):
        self.sessions = sessions
        self.max_active_per_user = max_active_per_user
        self._last_write: dict[str, float] = {}

    # --- API side --------------------------------------------------------------------------
    def create(self, kind: str, params: dict, subject: str | None = None, requested_by: str | None = None) -> str:
        """A new ``queued`` job; returns its id.

        ``params`` are checked against the kind's spec (server.jobs.specs) and stored as the
        spec's JSON (defaults filled in).

        Raises:
            server.jobs.specs.JobSpecError (a ValueError): unknown kind or bad parameters.
            JobLimit: a job of :data:`USER_STARTED_KINDS` for a user who already has
                ``max_active_per_user`` of them queued or running (so that one user's flood
                never starves another user's previews).
        """
        if kind not in JOB_KINDS:
            raise JobSpecError(f"unknown job kind {kind!r}; one of {', '.join(JOB_KINDS)}")
        params = parse_spec(kind, params).model_dump(mode="json")
        with self.sessions.begin() as db:
            if requested_by is not None and kind in USER_STARTED_KINDS:
                active = db.scalar(select(func.count()).select_from(Job).where(
                    Job.requested_by == requested_by, Job.kind.in_(USER_STARTED_KINDS),
                    Job.status.in_(("queued", "running")))) or 0  # COUNT(*) always returns a row
                if active >= self.max_active_per_user:
                    raise JobLimit(f"{requested_by} has {active} previews or probes queued or running, the limit "
                                   "per user: wait for one to finish")
            row = Job(kind=kind, status="queued", params=params, subject=subject, requested_by=requested_by,
                      progress=0.0, cancel_requested=False)
            db.add(row)
            db.flush()
            return row.id

    def get(self, job_id: str) -> dict | None:
        """The job as a dict (see :func:`as_dict`), or None."""
        with self.sessions() as db:
            row = db.get(Job, job_id)
            return as_dict(row) if row is not None else None

    def list(self, kind: str | None = None, subject: str | None = None, status: str | None = None,
             limit: int = 50, with_result: bool = False) -> list[dict]:
        """Jobs newest first, without their results unless asked (they can be large)."""
        stmt = select(Job).order_by(Job.created_at.desc()).limit(limit)
        for col, value in ((Job.kind, kind), (Job.subject, subject), (Job.status, status)):
            if value:
                stmt = stmt.where(col == value)
        with self.sessions() as db:
            return [as_dict(r, with_result=with_result) for r in db.scalars(stmt)]

    def changed_since(self, since: datetime) -> builtins.list[dict]:
        """Jobs that can still change (queued, running) or finished at or after ``since`` (UTC),
        without results: what server.jobs.watch.JobWatcher looks at."""
        stmt = select(Job).where((Job.status.in_(("queued", "running"))) | (Job.finished_at >= since))
        with self.sessions() as db:
            return [as_dict(r, with_result=False) for r in db.scalars(stmt)]

    def cancel(self, job_id: str) -> dict | None:
        """Ask a job to stop: a queued job is cancelled now, a running one at its next progress
        report; finished jobs are left as they are. Returns the job, None if unknown."""
        with self.sessions.begin() as db:
            row = db.get(Job, job_id)
            if row is None:
                return None
            if row.status not in FINAL_JOB_STATUSES:
                row.cancel_requested = True
                if row.status == "queued":
                    row.status, row.finished_at, row.message = "cancelled", utcnow(), "cancelled before it started"
            return as_dict(row)

    # --- worker side -----------------------------------------------------------------------
    def start(self, job_id: str, worker: WorkerIdentity, lease_s: float = LEASE_S) -> dict | None:
        """Claim a ``queued`` job for ``worker``: ``running``, progress 0, one more attempt, a
        lease of ``lease_s`` (server.jobs.leases). None if it is unknown, cancelled, finished or
        already running (a stale queue message): the worker then skips it. Conditional update,
        so of two workers given the same job only one starts it."""
        now = utcnow()
        with self.sessions.begin() as db:
            res = db.execute(update(Job).where(Job.id == job_id, Job.status == "queued", Job.cancel_requested.is_(False))
                             .values(status="running", worker=worker.name, worker_id=worker.id,
                                     worker_host=worker.host, worker_pid=worker.pid, started_at=now,
                                     heartbeat_at=now, lease_expires_at=now + timedelta(seconds=lease_s),
                                     progress=0.0, attempts=Job.attempts + 1))
            if not rowcount(res):
                return None
            row = db.get(Job, job_id)
            if row is None:
                raise RuntimeError(f"job {job_id} vanished inside the transaction that started it")
            return as_dict(row)

    def progress(self, job_id: str, fraction: float, message: str | None = None, force: bool = False,
                 worker_id: str | None = None) -> None:
        """Record progress (``fraction`` in [0, 1]) and check for cancellation. With
        ``worker_id``, only while that worker still holds the running job.

        Raises:
            JobCancelled: the job was asked to stop, or (with ``worker_id``) is no longer this
                worker's (its lease expired and the job was re-queued).
        """
        now = time.monotonic()
        if not force and now - self._last_write.get(job_id, 0.0) < PROGRESS_MIN_INTERVAL_S:
            return
        self._last_write[job_id] = now
        fraction = min(1.0, max(0.0, float(fraction)))
        stmt = update(Job).where(Job.id == job_id)
        if worker_id is not None:
            stmt = stmt.where(Job.worker_id == worker_id, Job.status == "running")
        with self.sessions.begin() as db:
            mine = rowcount(db.execute(stmt.values(progress=fraction, message=message)))
            cancel = db.scalar(select(Job.cancel_requested).where(Job.id == job_id))
        if cancel or not mine:
            raise JobCancelled(job_id)

    def finish(self, job_id: str, status: str, result: dict | None = None, error: str | None = None,
               worker_id: str | None = None) -> bool:
        """Final status ``done`` (with ``result``), ``failed`` (with ``error``) or ``cancelled``.
        With ``worker_id``, only while that worker still holds the running job (a worker whose
        lease expired and whose job was re-queued does not overwrite the new run). Returns
        whether the row was written.

        Raises:
            ValueError: not a final status.
        """
        if status not in FINAL_JOB_STATUSES:
            raise ValueError(f"not a final job status: {status!r}")
        self._last_write.pop(job_id, None)
        values: dict[str, object] = {"status": status, "result": result, "error": error, "finished_at": utcnow(), "lease_expires_at": None}
        if status == "done":
            values["progress"] = 1.0
        if status == "cancelled":
            values["message"] = "cancelled"
        stmt = update(Job).where(Job.id == job_id)
        if worker_id is not None:
            stmt = stmt.where(Job.worker_id == worker_id, Job.status == "running")
        with self.sessions.begin() as db:
            return bool(rowcount(db.execute(stmt.values(**values))))


def as_dict(row: Job, with_result: bool = True) -> dict:
    """JSON-ready view of a job row (timestamps ISO 8601 UTC)."""
    out = {c: getattr(row, c) for c in ("id", "kind", "status", "subject", "params", "progress", "message",
                                        "error", "cancel_requested", "worker", "requested_by", "attempts")}
    for c in ("created_at", "started_at", "finished_at", "heartbeat_at"):
        v: datetime | None = getattr(row, c)
        out[c] = v.isoformat() if v is not None else None
    if with_result:
        out["result"] = row.result
    return out
