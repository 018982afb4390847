"""Jobs of dead workers are re-run (server.jobs.leases): two real ``slinger worker`` processes,
the one running a long job is killed with SIGKILL, the other re-runs the job from the start
(attempts = 2). On SQLite both workers share this host (dead pid found at once); on PostgreSQL
each runs under its own host name (``unshare --uts``), so the survivor can only see the death
through the expired lease. A job that kills its worker on every attempt ends failed after the
limit with the reason."""

from __future__ import annotations

import os
import signal
import subprocess
import threading

import pytest

from server.config import Settings
from server.db.migrate import upgrade
from server.db.session import make_engine, make_sessionmaker
from server.jobs import JobQueue, JobStore
from server.jobs.leases import Leases, WorkerIdentity
from server.jobs.tasks import execute
from tests.conftest import wait_for
from tests.fleet_site import Worker

SAME_HOST = ("--lanes", "heavy", "--heartbeat-s", "0.3", "--lease-s", "30")
"""Same host: the dead pid is found at once; a long lease so that a loaded CI host never expires
a live worker's lease."""
OTHER_HOSTS = ("--lanes", "heavy", "--heartbeat-s", "0.5", "--lease-s", "4")
"""Other hosts: only the lease tells; short, so the test waits ~4 s for it."""
FINAL = ("done", "failed", "cancelled")


def _queue(db_url: str, queue_url: str):
    upgrade(db_url)
    engine = make_engine(db_url)
    return engine, JobQueue(queue_url, JobStore(make_sessionmaker(engine)), execute)


def _kill_the_runner_and_watch(queue: JobQueue, job_id: str, workers: list[Worker]) -> tuple[dict, list[dict], dict]:
    """Wait until a worker has made progress on the job, SIGKILL it; return the final job, the
    rows seen after the kill and the row just before it."""
    job = wait_for(lambda: (j := queue.store.get(job_id))["status"] == "running" and j["progress"] > 0.1 and j, 60,
                   "the long job running")
    victim = next(w for w in workers if job["worker"].endswith(f":{w.proc.pid}"))
    os.kill(victim.proc.pid, signal.SIGKILL)
    victim.proc.wait(10)
    seen: list[dict] = []

    def final():
        seen.append(j := queue.store.get(job_id))
        return j["status"] in FINAL and j

    return wait_for(final, 90, "the job re-run by the other worker"), seen, job


def _assert_rerun(done: dict, seen: list[dict], before: dict, survivor: Worker) -> None:
    assert done["status"] == "done" and done["attempts"] == 2, done
    assert done["worker"].endswith(f":{survivor.proc.pid}") and done["result"]["steps"] == 40
    rerun = [j for j in seen if j["attempts"] == 2]
    assert rerun and rerun[0]["progress"] < before["progress"], (before, rerun[:3])  # progress restarted


def test_sqlite_job_of_a_killed_worker_is_rerun_then_a_crashing_job_fails(tmp_path):
    var = tmp_path / "var"
    settings = Settings(data_dir=var)
    db_url, q_url = f"sqlite:///{var / 'slinger.db'}", f"sqlite:///{var / 'jobs.db'}"
    var.mkdir()
    engine, queue = _queue(db_url, q_url)
    s = Settings(data_dir=var, database_url=db_url, job_queue_url=q_url)
    try:
        job_id = queue.submit("probe", {"steps": 40, "step_s": 0.1})
        workers = [Worker(s, *SAME_HOST), Worker(s, *SAME_HOST)]
        with workers[0], workers[1]:
            done, seen, before = _kill_the_runner_and_watch(queue, job_id, workers)
            survivor = next(w for w in workers if w.proc.poll() is None)
            _assert_rerun(done, seen, before, survivor)
            assert any("re-queued: worker" in (j["message"] or "") and "pid" in j["message"] for j in seen) or \
                "re-queued" in survivor.text()

        # a job that kills its worker every time: start workers one after another until it ends
        crash = queue.submit("probe", {"steps": 5, "step_s": 0.05, "kill_worker_at_step": 1})
        started = []
        while (job := queue.store.get(crash))["status"] not in FINAL and len(started) < 6:
            w = Worker(s, *SAME_HOST)
            started.append(w)
            with w:
                wait_for(lambda: w.proc.poll() is not None or queue.store.get(crash)["status"] in FINAL, 60,
                         "the worker killed by the job, or the job failed")
        assert job["status"] == "failed" and job["attempts"] == 3, (job, [w.text()[-1500:] for w in started])
        assert "limit of 3 attempts" in job["error"] and "died" in job["error"], job["error"]
        assert len(started) == 4  # three killed by the job, the fourth found it at the limit
    finally:
        engine.dispose()


@pytest.mark.postgres
def test_postgres_job_of_a_killed_worker_on_another_host_is_rerun(tmp_path, pg_url):
    if os.geteuid() != 0 or subprocess.run(["unshare", "--uts", "true"], capture_output=True).returncode != 0:
        pytest.skip("unshare --uts (a worker under another host name) is not permitted here")
    q_url = "postgresql://" + pg_url.split("://", 1)[1]
    engine, queue = _queue(pg_url, q_url)
    s = Settings(data_dir=tmp_path / "var", database_url=pg_url, job_queue_url=q_url)
    try:
        job_id = queue.submit("probe", {"steps": 40, "step_s": 0.1})
        workers = [Worker(s, *OTHER_HOSTS, hostname="worker-host-a"), Worker(s, *OTHER_HOSTS, hostname="worker-host-b")]
        with workers[0], workers[1]:
            done, seen, before = _kill_the_runner_and_watch(queue, job_id, workers)
            survivor = next(w for w in workers if w.proc.poll() is None)
            _assert_rerun(done, seen, before, survivor)
            assert "lease expired" in survivor.text(), survivor.text()[-2000:]
            assert done["worker"].startswith("worker-host-")
    finally:
        engine.dispose()


def test_lease_settings_and_claims_are_checked(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    try:
        sessions = make_sessionmaker(engine)
        with pytest.raises(ValueError, match="heartbeat_s < lease_s"):
            Leases(sessions, WorkerIdentity(), print, lease_s=1.0, heartbeat_s=1.0)
        with pytest.raises(ValueError, match="max_attempts"):
            Leases(sessions, WorkerIdentity(), print, max_attempts=0)
        store = JobStore(sessions)
        job_id = store.create("probe", {})
        a, b = WorkerIdentity(), WorkerIdentity()
        assert store.start(job_id, a, lease_s=0.2)["attempts"] == 1
        assert store.start(job_id, b) is None  # a stale queue message never runs a job twice
        requeued = []
        lease = Leases(sessions, b, lambda j, k: requeued.append(j), lease_s=0.2, heartbeat_s=0.1)
        assert lease.reap() == []  # a's lease still runs and its pid (ours) lives
        threading.Event().wait(0.3)
        assert lease.reap() == [(job_id, "queued")] and requeued == [job_id]
        assert not store.finish(job_id, "done", worker_id=a.id)  # a lost it: its late result is not written
        assert store.get(job_id)["status"] == "queued" and "lease expired" in store.get(job_id)["message"]
    finally:
        engine.dispose()
