"""``slinger worker``: a worker process of the job queue (server.jobs).

It consumes both lanes by default, each with its own Huey consumer (thread workers): ``fast``
(previews, the effects catalogue; polled every <= FAST_POLL_S = 0.05 s on SQLite: a preview's
pickup is part of the console's aiming time) and ``heavy`` (evaluations,
diagnoses, adaptations, probes). Start as many as you like, on this host (SQLite queue) or on
any host that reaches the queue and the database (PostgreSQL or Redis queue; the data dir, where
policy files and telemetry live, shared)::

    slinger worker --data-dir var                       # embedded: SQLite queue var/jobs.db
    slinger worker --database-url postgresql+psycopg://slinger@db/slinger \\
                   --queue-url postgresql://slinger@db/slinger --data-dir /srv/slinger

SIGINT finishes the running jobs first; SIGTERM stops at once. A heartbeat thread renews the
lease of the jobs this worker runs and re-queues jobs of dead workers, of this host (pid gone)
or of any host (lease expired), up to ``--max-attempts`` starts, then fails them with the reason
(server.jobs.leases); jobs this process was running when it stopped are re-queued the same way.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

from server.jobs import leases, tasks
from server.jobs.queue import LANES, JobQueue, queue_url
from server.site.storage import StorageMonitor

log = logging.getLogger(__name__)

FAST_POLL_S = 0.05
"""Longest wait between two looks of an idle fast-lane consumer at a queue without wake-ups
(SQLite): a preview waits half of it on average before a worker takes it (the console's
nominal preview has 0.5 s in all, tests/benchmarks/bench_console_aim.py); a look is one small
query of the queue's own database file."""


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--database-url", default=None, help="SQLAlchemy URL (default sqlite:///<data-dir>/slinger.db)")
    p.add_argument("--data-dir", type=Path, default=None, help="policy files, telemetry, reports (default ./var)")
    p.add_argument("--queue-url", default=None, help="job queue: sqlite:///FILE, postgresql://..., redis://... "
                                                     "(default sqlite:///<data-dir>/jobs.db)")
    p.add_argument("--lanes", default=",".join(LANES), help="lanes to consume, comma-separated (default fast,heavy)")
    p.add_argument("--heavy-workers", type=int, default=1, help="concurrent heavy jobs (default 1)")
    p.add_argument("--fast-workers", type=int, default=1, help="concurrent previews (default 1)")
    p.add_argument("--heartbeat-s", type=float, default=leases.HEARTBEAT_S,
                   help=f"lease renewal and dead-worker check period, s (default {leases.HEARTBEAT_S:g})")
    p.add_argument("--lease-s", type=float, default=leases.LEASE_S,
                   help=f"a worker silent this long is dead for other hosts, s (default {leases.LEASE_S:g})")
    p.add_argument("--max-attempts", type=int, default=leases.MAX_ATTEMPTS,
                   help=f"starts of a job whose workers keep dying before it fails (default {leases.MAX_ATTEMPTS})")


def run(args: argparse.Namespace) -> int:
    from server.config import Settings
    from server.db.session import make_engine, make_sessionmaker

    overrides = {k: v for k, v in {"database_url": args.database_url, "data_dir": args.data_dir,
                                   "job_queue_url": args.queue_url}.items() if v is not None}
    settings = Settings(**overrides)
    lanes = [x.strip() for x in args.lanes.split(",") if x.strip()]
    bad = [x for x in lanes if x not in LANES]
    if bad or not lanes:
        raise SystemExit(f"slinger worker: unknown lane(s) {bad or lanes}; use {','.join(LANES)}")
    url = queue_url(settings)
    if url == "immediate":
        raise SystemExit("slinger worker: 'immediate' is not a queue a worker can consume")
    engine = make_engine(settings.database_url, settings.database_busy_timeout_s)
    storage = StorageMonitor(settings.database_url, settings.storage_min_free_bytes)
    storage.guard(engine)  # an unwritable SQLite -shm: jobs fail with the reason, no SIGBUS (server.site.storage)
    ctx = tasks.WorkerContext(make_sessionmaker(engine, before_use=storage.before_use), settings.data_dir, settings,
                              lease_s=args.lease_s)
    tasks.bind(ctx)
    queue = ctx.jobs = JobQueue(url, ctx.store, tasks.execute)
    try:
        lease = leases.Leases(ctx.sessions, ctx.identity, queue.enqueue, lease_s=args.lease_s,
                              heartbeat_s=args.heartbeat_s, max_attempts=args.max_attempts)
    except ValueError as e:
        raise SystemExit(f"slinger worker: {e}") from None
    lease.reap()  # jobs of workers that died while none ran
    if "fast" in lanes:
        import sim_twin.preview.preview  # noqa: F401  warm: the first preview must not pay MuJoCo's import

        ctx.start_preview_pool()
        ctx.warmed.clear()  # previews wait for the warm-up below (WorkerContext.warm_previews)
    consumers = []
    for lane in lanes:
        workers = args.fast_workers if lane == "fast" else args.heavy_workers
        consumers.append(queue.hueys[lane].create_consumer(
            workers=workers, worker_type="thread", periodic=False, initial_delay=0.02, backoff=1.5,
            max_delay=FAST_POLL_S if lane == "fast" else 1.0, check_worker_health=True))
    log.info("worker %s (id %s) consuming %s on %s", ctx.name, ctx.identity.id, ",".join(lanes), _redact(url))
    lease.start()
    try:
        for c in consumers[:-1]:
            c.start()
        if "fast" in lanes:
            # nor should the first preview pay for its policy's loading and first rollouts, or the
            # first ellipse for scipy's import: in the background once the consumers are up
            # (previews wait for it; other fast jobs do not)
            threading.Thread(target=ctx.warm_previews, name="warm-previews", daemon=True).start()
        consumers[-1].run()  # until SIGINT (graceful) or SIGTERM
        for c in consumers[:-1]:
            c.stop(graceful=True)
    finally:
        lease.stop()
        ctx.close()
        try:
            lease.release_own("stopped while running it")
        finally:
            storage.release(engine)
    return 0


def worker_argv(settings) -> list[str]:
    """``slinger worker`` for the database, data dir and queue of ``settings`` (``slinger up``)."""
    from server.site.stack import slinger_command

    return slinger_command("worker", "--database-url", settings.database_url, "--data-dir", str(settings.data_dir),
                           "--queue-url", queue_url(settings))


def _redact(url: str) -> str:
    if "@" in url and "://" in url:
        scheme, rest = url.split("://", 1)
        return f"{scheme}://***@{rest.split('@', 1)[1]}"
    return url
