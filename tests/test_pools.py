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


def test_preview_monte_carlo_in_a_pool_gives_the_same_impacts():
    """The preview's full rollouts in pool processes (the worker's Settings.preview_processes)
    land where they land in one process: every release delay is drawn before they run."""
    import numpy as np

    from runtime.policy import PolicyRunner
    from sim_twin.initial_pose import sample_pose
    from sim_twin.pools import process_pool
    from sim_twin.preview import PreviewRequest, preview_throw, site_profile, warm_up

    policy = PolicyRunner.load("policies/throw2d.onnx")
    profile = site_profile(None, None)
    q = sample_pose(np.random.default_rng(0), cabin_turn=0.0).tolist()
    req = PreviewRequest("2d", [8.5, -0.292, 0.0], q, [0.0] * 6, rollouts=48)
    alone = preview_throw(policy, req, profile)
    pool = process_pool(2)
    try:
        warm_up(pool, 2)
        pooled = preview_throw(policy, req, profile, pool=pool)
    finally:
        pool.shutdown()
    assert alone["mc"]["param_rollouts"] == 4 and alone["mc"]["failed_rollouts"] == 0
    assert pooled["mc"]["impacts_m"] == alone["mc"]["impacts_m"]
    assert pooled["mc"]["sigma_downrange_m"] == alone["mc"]["sigma_downrange_m"]
