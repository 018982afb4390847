"""Heavy work as jobs in worker processes, on the Huey task queue.

The API process never imports MuJoCo: evaluations of uploaded policies, diagnoses, adaptations,
Monte Carlo previews and the effects catalogue run in ``slinger worker`` processes (``slinger
up`` starts one; start more on any host that reaches the queue and the database).

* :mod:`server.jobs.queue`: the Huey queue of each lane on SQLite (embedded default),
  PostgreSQL or Redis, and :class:`~server.jobs.queue.JobQueue` (submit, wait, cancel).
* :mod:`server.jobs.store`: the ``jobs`` table: status, progress, result, cancellation.
* :mod:`server.jobs.tasks`: what each job kind does (imports sim_twin inside the functions).
* :mod:`server.jobs.worker`: ``slinger worker``.

Two lanes so that a 3 s preview never waits behind a 30 s diagnosis: ``fast`` (previews, the
effects catalogue) and ``heavy`` (evaluations, diagnoses, adaptations, probes).
"""

from server.jobs.queue import LANES, JobQueue, lane_of, queue_url
from server.jobs.store import JobCancelled, JobLimit, JobStore

__all__ = ["LANES", "JobCancelled", "JobLimit", "JobQueue", "JobStore", "lane_of", "queue_url"]
