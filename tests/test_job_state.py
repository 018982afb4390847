"""A job's ``jobs`` row is its only state (server.jobs.specs, server.analysis.diagnosis, server.jobs.watch):

* each kind's parameters are a typed spec, checked when the job is submitted and again when a
  worker runs it (a row with bad parameters fails with the reason instead of half-running);
* a diagnosis whose worker is SIGKILLed on its last attempt ends ``failed`` with the reason, and
  the next diagnosis starts (a run kept in a side file stayed "running" and refused every later
  diagnosis as busy); no status file is written anywhere;
* job progress and completion are ``job`` events (what /api/live carries), and a route awaiting a
  job is woken by them.
"""

from __future__ import annotations

import asyncio
import os
import signal

import pytest

from server.config import Settings
from server.db.migrate import upgrade
from server.db.models import Job, Machine, Throw
from server.db.session import make_engine, make_sessionmaker
from server.analysis.diagnosis import DiagnosisBusy, DiagnosisRuns
from server.jobs import JobQueue, JobStore
from server.jobs.specs import JobSpecError, parse_spec
from server.jobs.tasks import WorkerContext, bind, execute
from server.jobs.watch import JobWatcher
from tests.conftest import wait_for
from tests.fleet_site import Worker

ONE_ATTEMPT = ("--lanes", "heavy", "--heartbeat-s", "0.3", "--lease-s", "30", "--max-attempts", "1")


def _site(tmp_path):
    var = tmp_path / "var"
    var.mkdir()
    db_url, q_url = f"sqlite:///{var / 'slinger.db'}", f"sqlite:///{var / 'jobs.db'}"
    upgrade(db_url)
    engine = make_engine(db_url)
    sessions = make_sessionmaker(engine)
    return engine, sessions, JobQueue(q_url, JobStore(sessions), execute), Settings(data_dir=var, database_url=db_url,
                                                                                   job_queue_url=q_url)


def test_job_specs_are_checked_at_submit_and_at_run(tmp_path):
    engine, sessions, queue, settings = _site(tmp_path)
    try:
        with pytest.raises(JobSpecError, match="limit"):
            queue.submit("diagnosis", {"machine_id": "m1", "limit": 0})
        with pytest.raises(JobSpecError, match="extra|not permitted"):
            queue.submit("probe", {"steps": 1, "rm_rf": True})
        with pytest.raises(JobSpecError, match="unknown job kind"):
            queue.submit("bake", {})
        with sessions() as db:
            assert db.query(Job).count() == 0  # nothing refused left a row
        spec = parse_spec("diagnosis", {"machine_id": "m1"})
        assert spec.limit == 50 and spec.workers is None  # defaults filled in, stored as the spec's JSON
        # a row written by another producer with bad parameters fails at run time, with the reason
        with sessions.begin() as db:
            db.add(Job(id="bad-row", kind="probe", status="queued", params={"steps": "many"}, progress=0.0,
                       cancel_requested=False))
        bind(WorkerContext(sessions, settings.data_dir, settings, queue))
        execute("bad-row")
        job = queue.store.get("bad-row")
        assert job["status"] == "failed" and "bad parameters for a probe job" in job["error"] and "steps" in job["error"]
    finally:
        engine.dispose()


def test_a_diagnosis_killed_on_its_last_attempt_fails_and_the_next_one_starts(tmp_path):
    """The export blocks on FIFOs standing in for telemetry files, so the job is surely running
    when its worker gets SIGKILL; a second worker reaps it at the one-attempt limit."""
    engine, sessions, queue, settings = _site(tmp_path)
    fifo_dir = settings.data_dir / "telemetry"
    fifo_dir.mkdir()
    with sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        for i in range(5):
            os.mkfifo(fifo_dir / f"t{i}.mcap")
            db.add(Throw(id=f"t{i}", machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=0.0, target_z_m=0.0,
                         status="landed", telemetry_path=f"telemetry/t{i}.mcap"))
    runs = DiagnosisRuns(sessions, queue, settings.data_dir, workers=1)
    try:
        first = runs.start("m1", limit=5, requested_by="op")
        with pytest.raises(DiagnosisBusy):
            runs.start("m1")
        with Worker(settings, *ONE_ATTEMPT) as w:
            wait_for(lambda: (j := queue.store.get(first["id"]))["status"] == "running" and j["message"], 60,
                     "the diagnosis exporting")
            os.kill(w.proc.pid, signal.SIGKILL)
            w.proc.wait(10)
        with Worker(settings, *ONE_ATTEMPT):  # reaps the dead worker's job at the limit
            job = wait_for(lambda: (j := queue.store.get(first["id"]))["status"] == "failed" and j, 60,
                           "the killed diagnosis failed")
        assert "limit of 1 attempts" in job["error"] and "died" in job["error"], job["error"]
        view = runs.get(first["id"])
        assert view["status"] == "failed" and view["error"] == job["error"] and view["machine_id"] == "m1"
        second = runs.start("m1", limit=5)  # not refused as busy
        assert second["id"] != first["id"] and second["status"] == "queued"
        assert [r["id"] for r in runs.list("m1")] == [second["id"], first["id"]]
        assert not list(settings.data_dir.rglob("status.json"))
    finally:
        for i in range(5):  # unblock nothing is left reading; remove the FIFOs
            (fifo_dir / f"t{i}.mcap").unlink()
        engine.dispose()


def test_job_events_carry_progress_and_wake_a_waiting_request(tmp_path):
    engine, sessions, queue, settings = _site(tmp_path)
    events: list[tuple[str, dict]] = []
    watcher = JobWatcher(queue.store, lambda name, data: events.append((name, data)), period_s=0.05,
                         busy_period_s=0.01)
    try:
        job_id = queue.store.create("probe", {"steps": 3}, subject="m1")
        watcher.poll()
        assert events[-1] == ("job", {"id": job_id, "kind": "probe", "status": "queued", "subject": "m1",
                                      "progress": 0.0, "message": None, "error": None, "requested_by": None})
        watcher.poll()
        assert len(events) == 1  # no change, no event
        watcher.start()

        async def wait_and_finish():
            waiter = asyncio.create_task(watcher.wait(job_id, 10.0))
            await asyncio.sleep(0.1)
            assert not waiter.done()
            queue.store.progress(job_id, 0.5, "half way", force=True)
            await asyncio.sleep(0.1)
            queue.store.finish(job_id, "done", result={"steps": 3})
            return await asyncio.wait_for(waiter, 5.0)

        job = asyncio.run(wait_and_finish())
        assert job["status"] == "done" and job["result"] == {"steps": 3}
        seen = [(e["status"], e["progress"], e["message"]) for _, e in events]
        assert ("queued", 0.5, "half way") in seen and seen[-1][0] == "done"
    finally:
        watcher.stop()
        engine.dispose()
