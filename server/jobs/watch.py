"""Job progress and completion as events, for the API process (``job`` events on /api/live).

Workers write a job's progress into its row (server.jobs.store); they share no event bus with
the API. One :class:`JobWatcher` per API process reads the rows that can still change (queued,
running, or finished since its last look) and, for each change of status, progress or message,

* publishes a ``job`` event (``{"id", "kind", "status", "subject", "progress", "message",
  "error", "requested_by"}``) to every open console (the Diagnosis page, a preview wait), and
* resolves the routes awaiting that job (:meth:`JobWatcher.wait`).

It looks every ``period_s`` while nobody waits, every ``busy_period_s`` while a route awaits a
job (a preview), so one small query serves every page and every waiting request.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import defaultdict
from datetime import datetime, timedelta

from server.db.models import FINAL_JOB_STATUSES
from server.db.types import utcnow
from server.jobs.store import JobStore

log = logging.getLogger(__name__)

EVENT_FIELDS = ("id", "kind", "status", "subject", "progress", "message", "error", "requested_by")


def _wake(fut: asyncio.Future) -> None:
    """Resolve a waiter's future (in its event loop) unless it is already done (timed out)."""
    if not fut.done():
        fut.set_result(None)


class JobWatcher:
    """Turns changes of job rows into events and wake-ups.

    Args:
        store: the ``jobs`` table.
        publish: ``publish(event_name, data)`` (server.console.live.LiveHub.publish), thread-safe.
        period_s: seconds between looks while no request waits.
        busy_period_s: seconds between looks while a request waits for a job.
    """

    def __init__(self, store: JobStore, publish, period_s: float = 0.5, busy_period_s: float = 0.02):
        self.store, self.publish = store, publish
        self.period_s, self.busy_period_s = period_s, busy_period_s
        self._seen: dict[str, tuple] = {}
        self._waiters: dict[str, list[tuple[asyncio.AbstractEventLoop, asyncio.Future]]] = defaultdict(list)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._since: datetime = utcnow()

    def start(self) -> None:
        """Start the watching thread (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="job-watcher", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread; pending waits end with their row as it is."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll()
            except Exception:
                log.exception("job watcher: reading the jobs table failed")
            with self._lock:
                busy = bool(self._waiters)
            self._wake.wait(self.busy_period_s if busy else self.period_s)
            self._wake.clear()

    def poll(self) -> list[dict]:
        """One look: publish every changed job, wake the waiters of finished ones; returns the
        changed jobs (event payloads)."""
        since, self._since = self._since, utcnow()
        rows = self.store.changed_since(since - timedelta(seconds=1))
        changed = []
        for job in rows:
            key = (job["status"], job["progress"], job["message"], job["error"])
            if self._seen.get(job["id"]) == key:
                continue
            self._seen[job["id"]] = key
            event = {k: job.get(k) for k in EVENT_FIELDS}
            changed.append(event)
            self.publish("job", event)
            if job["status"] in FINAL_JOB_STATUSES:
                self._resolve(job["id"], job)
        active = {j["id"] for j in rows}
        for job_id in [k for k in self._seen if k not in active]:
            del self._seen[job_id]  # finished and out of the window: forget it
        return changed

    def _resolve(self, job_id: str, job: dict) -> None:
        with self._lock:
            waiters = self._waiters.pop(job_id, [])
        for loop, fut in waiters:
            loop.call_soon_threadsafe(_wake, fut)

    async def wait(self, job_id: str, timeout_s: float) -> dict | None:
        """Await the job's end (or ``timeout_s``); returns its row with the result (None if unknown).

        The row is read once before waiting (a job that ended already, or ran in-process) and
        once after the wake-up; no request thread is held meanwhile.
        """
        loop = asyncio.get_running_loop()
        fut: asyncio.Future = loop.create_future()
        with self._lock:
            self._waiters[job_id].append((loop, fut))
        self._wake.set()
        try:
            job = await asyncio.to_thread(self.store.get, job_id)
            if job is None or job["status"] in FINAL_JOB_STATUSES:
                return job
            try:
                await asyncio.wait_for(fut, timeout_s)
            except TimeoutError:
                pass
            return await asyncio.to_thread(self.store.get, job_id)
        finally:
            with self._lock:
                left = [w for w in self._waiters.get(job_id, []) if w[1] is not fut]
                if left:
                    self._waiters[job_id] = left
                else:
                    self._waiters.pop(job_id, None)
