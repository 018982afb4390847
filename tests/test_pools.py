"""The twin's process pools never fork their caller (sim_twin.pools): a worker forked from a
process with threads can wait forever on a lock another thread held at the fork (seen as an
evaluation that hung after a test had run a server in the same process)."""

from __future__ import annotations

import os
import threading

from sim_twin.pools import process_pool


def test_pool_workers_start_from_a_fresh_interpreter_while_a_thread_holds_a_lock():
    held, release = threading.Lock(), threading.Event()

    def hold():
        with held:
            release.wait(30)

    t = threading.Thread(target=hold, daemon=True)
    t.start()
    try:
        with process_pool(2) as pool:
            assert pool._mp_context.get_start_method() == "forkserver"  # noqa: SLF001
            pids = set(pool.map(os.getpid, [], chunksize=1)) | {pool.submit(os.getpid).result(timeout=60) for _ in range(4)}
        assert os.getpid() not in pids and len(pids) >= 1
    finally:
        release.set()
        t.join(5)
