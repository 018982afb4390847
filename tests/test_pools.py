"""The twin's process pools never fork their caller (sim_twin.twin.pools): a worker forked from a
process with threads can wait forever on a lock another thread held at the fork (seen as an
evaluation that hung after a test had run a server in the same process)."""

from __future__ import annotations

import os
import threading

from sim_twin.twin.pools import process_pool


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


def test_preview_monte_carlo_in_a_pool_gives_the_same_impacts():
    """The preview's full rollouts in pool processes (the worker's Settings.preview_processes)
    land where they land in one process: every release delay is drawn before they run; a pool
    whose processes loaded the policy ahead (warm_policy, as a worker does on a policy's first
    nominal preview) gives the same, and so does an ellipse that reuses the nominal of its
    nominal-only preview (NominalCache)."""
    import dataclasses

    import numpy as np

    from runtime.policy import PolicyRunner
    from sim_twin.preview.preview import NominalCache, PreviewRequest, preview_throw, site_profile, warm_policy, warm_up
    from sim_twin.twin.initial_pose import sample_pose
    from sim_twin.twin.pools import process_pool

    policy = PolicyRunner.load("policies/throw2d.onnx")
    profile = site_profile(None, None)
    q = sample_pose(np.random.default_rng(0), cabin_turn=0.0).tolist()
    req = PreviewRequest("2d", [8.5, -0.292, 0.0], q, [0.0] * 6, rollouts=48)
    alone = preview_throw(policy, req, profile)
    pool = process_pool(2)
    try:
        warm_up(pool, 2)
        for f in warm_policy(pool, 2, policy.path):
            assert f.result() is None  # loaded, first calls made (raises here if they failed)
        pooled = preview_throw(policy, req, profile, pool=pool)
        # the console's two steps: the nominal alone, then its ellipse, which reuses that nominal
        nominals = NominalCache()
        preview_throw(policy, dataclasses.replace(req, rollouts=1), profile, pool=pool, nominals=nominals)
        shared = preview_throw(policy, req, profile, pool=pool, nominals=nominals)
        assert nominals.hits == 1
    finally:
        pool.shutdown()
    assert alone["mc"]["param_rollouts"] == 4 and alone["mc"]["failed_rollouts"] == 0
    assert pooled["mc"]["impacts_m"] == alone["mc"]["impacts_m"]
    assert pooled["mc"]["sigma_downrange_m"] == alone["mc"]["sigma_downrange_m"]
    for s in (shared, alone):
        s.pop("timing_s")
    assert shared == alone


OWNER = r"""
import os, sys, time
from sim_twin.twin.pools import process_pool
pool = process_pool(2)
pids = {pool.submit(os.getpid).result(timeout=120) for _ in range(8)}
print(" ".join(map(str, sorted(pids))), flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie awaiting its reaper counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_no_pool_process_outlives_a_kill_9_of_its_owner():
    """kill -9 of the pool's owner (a job worker, a `slinger up` stack): its forkserver and every
    pool worker end too (before: the workers waited on their task queue for ever)."""
    import signal
    import subprocess
    import sys

    from tests.conftest import wait_for

    owner = subprocess.Popen([sys.executable, "-c", OWNER], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in owner.stdout.readline().split()]
        assert workers and all(_alive(p) for p in workers)
        children = subprocess.run(["ps", "-o", "pid=", "--ppid", str(owner.pid)], capture_output=True,
                                  text=True).stdout.split()
        forkserver = [int(p) for p in children]
    finally:
        owner.send_signal(signal.SIGKILL)
        owner.wait(timeout=10)
    assert forkserver, "the pool's forkserver is the owner's child"
    wait_for(lambda: not any(_alive(p) for p in workers + forkserver), 20, "pool processes gone")
