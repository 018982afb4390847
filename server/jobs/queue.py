"""The job queue: one Huey instance per lane on the configured storage, and :class:`JobQueue`.

Queue URLs (``Settings.job_queue_url``, ``slinger worker --queue-url``):

* ``sqlite:///path/jobs.db``: embedded default on one host (``<data_dir>/jobs.db``), Huey's
  SqliteStorage; any number of worker processes on that host.
* ``postgresql://user@host/db`` (``+psycopg`` is accepted): Huey's PostgresStorage (tables
  ``huey_*`` beside ours, LISTEN/NOTIFY wake-ups); workers on any host that reaches the database.
* ``redis://host:6379/0``: Huey's RedisStorage (blocking pops); workers on any host.
* ``immediate``: no queue, jobs run inside the calling process when submitted (tests of code
  that submits jobs; never the API in production: it would import MuJoCo).

A job is one Huey task ``slinger.job(job_id)``: the task carries only the id, the row in the
``jobs`` table (server.jobs.store) carries kind, parameters, progress and result. Tasks are
registered when the queue is built, never at import time.
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

from huey import MemoryHuey, PostgresHuey, RedisHuey, SqliteHuey
from huey.api import Huey

from server.jobs.store import JobStore

log = logging.getLogger(__name__)

LANES = ("fast", "heavy")
FAST_KINDS = ("preview", "catalog")


def lane_of(kind: str) -> str:
    """The lane a job kind runs on: ``fast`` for previews and the catalogue, else ``heavy``."""
    return "fast" if kind in FAST_KINDS else "heavy"


def queue_url(settings) -> str:
    """The queue URL of ``settings``: ``job_queue_url``, or SQLite ``<data_dir>/jobs.db``."""
    return settings.job_queue_url or f"sqlite:///{(Path(settings.data_dir) / 'jobs.db').as_posix()}"


def make_huey(url: str, lane: str) -> Huey:
    """The Huey instance of ``lane`` on the storage named by ``url`` (see the module doc).

    Raises:
        ValueError: unknown lane or URL scheme.
    """
    if lane not in LANES:
        raise ValueError(f"unknown job lane {lane!r}; one of {LANES}")
    name = f"slinger-{lane}"
    if url == "immediate":
        return MemoryHuey(name, immediate=True, results=False)
    if url.startswith("sqlite:///"):
        path = Path(url[len("sqlite:///"):])
        path.parent.mkdir(parents=True, exist_ok=True)
        return SqliteHuey(name, filename=str(path), results=False, timeout=10)
    if url.startswith(("postgresql://", "postgresql+psycopg://", "postgres://")):
        dsn = "postgresql://" + url.split("://", 1)[1]
        return PostgresHuey(name, dsn=dsn, results=False)
    if url.startswith(("redis://", "rediss://", "unix://")):
        return RedisHuey(name, url=url, results=False)
    raise ValueError(f"unsupported job queue URL {url!r}: use sqlite:///FILE, postgresql://..., redis://... "
                     "or 'immediate'")


class JobQueue:
    """Submit jobs, wait for them, cancel them.

    Args:
        url: queue URL (see the module doc).
        store: the ``jobs`` table.
        execute: ``execute(job_id)`` runs a job (server.jobs.tasks.execute in the worker, or in
            this process for ``immediate``); registered as the Huey task of every lane.
    """

    def __init__(self, url: str, store: JobStore, execute):
        self.url, self.store = url, store
        self.hueys = {lane: make_huey(url, lane) for lane in LANES}
        self.tasks = {lane: h.task(name="slinger.job")(execute) for lane, h in self.hueys.items()}

    def submit(self, kind: str, params: dict, subject: str | None = None, requested_by: str | None = None) -> str:
        """Create the job row and enqueue it on its lane; returns the job id.

        Raises:
            ValueError: unknown kind.
        """
        job_id = self.store.create(kind, params, subject=subject, requested_by=requested_by)
        self.enqueue(job_id, kind)
        return job_id

    def enqueue(self, job_id: str, kind: str) -> None:
        """Put the task of an existing ``queued`` job on its lane (submit, and the re-queue of a
        job whose worker died: server.jobs.leases)."""
        self.tasks[lane_of(kind)](job_id)

    def cancel(self, job_id: str) -> dict | None:
        """Cancel a job (server.jobs.store.JobStore.cancel); None if unknown."""
        return self.store.cancel(job_id)

    def wait(self, job_id: str, timeout_s: float) -> dict | None:
        """Block until the job is finished or ``timeout_s`` passed; returns the job (None if
        unknown). Not from inside a running event loop: use :meth:`wait_async` there."""
        return asyncio.run(self.wait_async(job_id, timeout_s))

    async def wait_async(self, job_id: str, timeout_s: float) -> dict | None:
        """Poll the job's row until it is finished or ``timeout_s`` passed; for async routes: it
        sleeps on the event loop and reads in a thread, so no request thread is held while a
        worker computes (the E-STOP route keeps its threads)."""
        deadline, delay = time.monotonic() + timeout_s, 0.01
        while True:
            job = await asyncio.to_thread(self.store.get, job_id)
            if job is None or job["status"] in ("done", "failed", "cancelled") or time.monotonic() >= deadline:
                return job
            await asyncio.sleep(delay)
            delay = min(0.1, delay * 1.5)
