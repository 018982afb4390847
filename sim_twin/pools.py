"""Process pools of the twin's batch work (evaluation, site matrix, dataset generation, benchmark).

The pools start their workers from a fresh interpreter (multiprocessing's ``forkserver``), never
by forking the caller: a caller with threads (a Zenoh session, a job worker's heartbeat, a test
process that ran a server) may hold a lock at the moment of a fork, and a forked worker that needs
that lock waits forever (Python's documentation of ``os.fork``: "forking a multi-threaded process
is problematic"; Python 3.14 makes forkserver the default on Linux for that reason). Workers import
MuJoCo and the policy on their first task, so the cost is about a second per worker per pool.
Everything submitted must be picklable (module-level functions and plain arguments).
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor


def process_pool(workers: int | None = None) -> ProcessPoolExecutor:
    """A ProcessPoolExecutor of ``workers`` processes (default: every core) started by forkserver."""
    return ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1,
                               mp_context=multiprocessing.get_context("forkserver"))
