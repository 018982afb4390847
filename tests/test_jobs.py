"""Job workers (server.jobs): the API process never imports MuJoCo; jobs queued while no worker
runs survive a restart of the API and are done by a worker started later; progress is stored
and streamed (Server-Sent Events); cancellation; a preview through a real worker; the same
queue on PostgreSQL and Redis (skipped when unreachable); bad input gives clear errors."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from server.db.migrate import upgrade
from server.db.session import make_engine, make_sessionmaker
from server.jobs import JobQueue, JobStore
from server.jobs.queue import lane_of, make_huey
from server.jobs.tasks import execute
from server.site.stack import slinger_command
from tests.conftest import ADMIN, add_user, login, wait_for
from tests.fleet_site import Worker

POLICY = Path(__file__).resolve().parent.parent / "policies" / "throw2d.onnx"


def _settings(tmp_path: Path, **kw) -> Settings:
    return Settings(data_dir=tmp_path / "var", zenoh_listen=[f"tcp/127.0.0.1:{_port()}"], viser_enabled=False,
                    query_timeout_s=2.0, auto_migrate=True, **kw)


def _port() -> int:
    from tests.conftest import free_port

    return free_port()


def _client(settings: Settings) -> TestClient:
    c = TestClient(create_app(settings))
    c.__enter__()
    add_user(c.app.state.sessions, *ADMIN, "admin") if not _has_admin(c) else None
    login(c, *ADMIN)
    return c


def _has_admin(c) -> bool:
    from server.db.models import User

    with c.app.state.sessions() as db:
        return db.query(User).filter_by(username=ADMIN[0]).first() is not None


def test_api_process_never_imports_mujoco(tmp_path):
    code = textwrap.dedent(f"""
        import sys
        from fastapi.testclient import TestClient
        from server.app import create_app
        from server.config import Settings
        s = Settings(data_dir={str(tmp_path / 'var')!r}, viser_enabled=False, auto_migrate=True,
                     zenoh_listen=["tcp/127.0.0.1:{_port()}"])
        with TestClient(create_app(s)) as c:
            assert c.get("/api/health").status_code == 200
            assert c.app.state.jobs.url.startswith("sqlite:///")
        bad = sorted(m for m in sys.modules if m.split(".")[0] in ("mujoco", "sim_twin")
                     or m.split(".")[0] == "scipy")  # not in the server wheel; scipy.stats alone adds ~50 MiB
        print("HEAVY", bad)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "HEAVY []" in out.stdout, out.stdout


def test_jobs_survive_an_api_restart_progress_streams_and_cancel(tmp_path):
    settings = _settings(tmp_path)
    c = _client(settings)
    try:
        queued = c.post("/api/jobs", json={"kind": "probe", "params": {"steps": 4, "step_s": 0.1}})
        assert queued.status_code == 202 and queued.json()["status"] == "queued"
        assert c.post("/api/jobs", json={"kind": "evaluation"}).status_code == 422  # not started by hand
    finally:
        c.__exit__(None, None, None)  # the API stops before any worker ran
    job_id = queued.json()["id"]
    c = _client(settings)  # ... and starts again
    try:
        with Worker(settings, "--lanes", "heavy") as w:
            events = []
            with c.stream("GET", f"/api/jobs/{job_id}/events") as r:
                assert r.headers["content-type"].startswith("text/event-stream")
                for line in r.iter_lines():
                    if line.startswith("data: "):
                        events.append(json.loads(line[6:]))
            assert events[-1]["status"] == "done", w.text()[-2000:]
            assert {e["status"] for e in events} >= {"running", "done"} or events[0]["status"] == "done"
            job = c.get(f"/api/jobs/{job_id}").json()
            assert job["result"]["steps"] == 4 and job["progress"] == 1.0 and job["worker"].endswith(f":{w.proc.pid}")

            long = c.post("/api/jobs", json={"kind": "probe", "params": {"steps": 200, "step_s": 0.05}}).json()
            wait_for(lambda: c.get(f"/api/jobs/{long['id']}").json()["status"] == "running", 30, "probe running")
            assert c.post(f"/api/jobs/{long['id']}/cancel").json()["cancel_requested"] is True
            done = wait_for(lambda: (j := c.get(f"/api/jobs/{long['id']}").json())["status"] != "running" and j, 30)
            assert done["status"] == "cancelled" and done["progress"] < 1.0

            failing = c.post("/api/jobs", json={"kind": "probe", "params": {"fail": "boom"}}).json()
            f = wait_for(lambda: (j := c.get(f"/api/jobs/{failing['id']}").json())["status"] == "failed" and j, 30)
            assert "boom" in f["error"]
        assert [j["id"] for j in c.get("/api/jobs", params={"kind": "probe", "limit": 1}).json()] == [failing["id"]]
        assert c.get("/api/jobs/nope").status_code == 404 and c.post("/api/jobs/nope/cancel").status_code == 404
    finally:
        c.__exit__(None, None, None)


@pytest.mark.skipif(not POLICY.is_file(), reason="no trained 2D policy")
def test_preview_runs_in_a_worker(tmp_path, fake_runtime_factory, zenoh_endpoint):
    from runtime.protocol.messages import PolicyInfo
    from tests.conftest import wait_online

    settings = Settings(data_dir=tmp_path / "var", zenoh_listen=[zenoh_endpoint], viser_enabled=False,
                        query_timeout_s=2.0, auto_migrate=True, preview_timeout_s=2.0)
    c = _client(settings)
    try:
        manifest = json.loads(POLICY.with_suffix(".json").read_text())
        c.app.state.store.register_policy(manifest, onnx_path=POLICY)
        fake_runtime_factory(policies=[PolicyInfo(mode="2d", version=manifest["name"], sha256=manifest["onnx_sha256"])])
        wait_online(c)
        body = {"machine_id": "m1", "mode": "2d", "target": [8.5, -0.292, 0.0], "rollouts": 50}
        r = c.post("/api/previews", json=body)
        assert r.status_code == 503 and "worker" in r.json()["detail"]  # none running
        c.app.state.settings.preview_timeout_s = 60.0  # no timed asserts (bench_preview measures)
        with Worker(settings, "--lanes", "fast") as w:
            wait_for(lambda: "consuming" in w.text(), 60, "worker up")
            # it loads the recorded policy and previews it once at start (its first preview is warm)
            wait_for(lambda: "preview warm-up: 2d policy" in w.text(), 60, "the worker's warm-up")
            assert "warm-up of the" not in w.text(), w.text()[-2000:]
            r = c.post("/api/previews", json=body)
            assert r.status_code == 200, (r.text, w.text()[-2000:])
            p = r.json()
            assert p["mc"]["rollouts"] == 50 and p["policy_version"] == manifest["name"]
            assert c.get(f"/api/previews/{p['id']}").json()["impact_m"] == p["impact_m"]
            assert c.get(f"/api/jobs/{p['id']}").json()["kind"] == "preview"
        assert c.get(f"/api/previews/{p['id']}").status_code == 200  # stored, not in memory
    finally:
        c.__exit__(None, None, None)


def test_bad_queue_and_job_input_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unsupported job queue URL"):
        make_huey("mysql://x", "fast")
    with pytest.raises(ValueError, match="unknown job lane"):
        make_huey("immediate", "slow")
    assert lane_of("preview") == "fast" and lane_of("diagnosis") == "heavy"
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    try:
        store = JobStore(make_sessionmaker(engine))
        with pytest.raises(ValueError, match="unknown job kind"):
            store.create("mine-bitcoin", {})
        with pytest.raises(ValueError, match="not a final job status"):
            store.finish("x", "running")
    finally:
        engine.dispose()
    out = subprocess.run(slinger_command("worker", "--lanes", "slow", "--data-dir", str(tmp_path)),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "unknown lane" in out.stderr


def _redis_url() -> str:
    import redis

    url = "redis://127.0.0.1:6379/15"
    try:
        redis.Redis.from_url(url, socket_connect_timeout=2).ping()
    except redis.exceptions.ConnectionError as e:
        pytest.skip(f"Redis not reachable at 127.0.0.1:6379: {e}")
    return url


@pytest.mark.postgres
def test_site_queues_on_postgres_and_redis(tmp_path, pg_url):
    """Workers on two queues at once (PostgreSQL tables, Redis lists), state in PostgreSQL."""
    urls = {"postgresql": pg_url, "redis": _redis_url()}
    upgrade(pg_url)
    engine = make_engine(pg_url)
    try:
        queues = {k: JobQueue(u, JobStore(make_sessionmaker(engine)), execute) for k, u in urls.items()}
        queues["redis"].hueys["heavy"].flush()
        ids = {k: [q.submit("probe", {"steps": 2, "step_s": 0.05}) for _ in range(3)] for k, q in queues.items()}
        workers = [Worker(Settings(data_dir=tmp_path / "var", database_url=pg_url, job_queue_url=u), "--lanes", "heavy")
                   for u in urls.values()]
        with workers[0], workers[1]:
            for k, q in queues.items():
                jobs = [q.wait(i, 60) for i in ids[k]]
                assert all(j["status"] == "done" for j in jobs), (k, jobs, [w.text()[-1500:] for w in workers])
                assert {j["worker"] for j in jobs} == {f"{_host()}:{workers[list(urls).index(k)].proc.pid}"}
    finally:
        engine.dispose()


def _host() -> str:
    import socket

    return socket.gethostname()


def test_every_job_runner_is_an_allowed_kind():
    """A runner whose kind the jobs table refuses answers 500 (GET /api/diagnosis/effects did)."""
    from server.db.models import JOB_KINDS
    from server.jobs.tasks import RUNNERS

    assert set(RUNNERS) <= set(JOB_KINDS)


def test_one_users_job_flood_is_bounded_per_user(tmp_path):
    """A user past their limit of queued previews is refused; other users' previews and the
    system's own jobs (no user, or an upload's evaluation) still queue; a finished job frees a slot."""
    from server.jobs import JobLimit
    from server.jobs.store import MAX_ACTIVE_PER_USER

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    try:
        store = JobStore(make_sessionmaker(engine))
        preview = {"onnx_path": "policies/p.onnx", "sha256": "0" * 64, "request": {}}
        ids = [store.create("preview", preview, requested_by="vera") for _ in range(MAX_ACTIVE_PER_USER)]
        with pytest.raises(JobLimit, match="vera has 4 previews or probes queued or running"):
            store.create("preview", preview, requested_by="vera")
        with pytest.raises(JobLimit):
            store.create("probe", {}, requested_by="vera")
        assert store.create("preview", preview, requested_by="otto")
        assert store.create("evaluation", {"version_id": 1, "distances_m": [8.0], "throws": 2}, requested_by="vera")
        assert store.create("catalog", {})
        store.cancel(ids[0])
        assert store.create("preview", preview, requested_by="vera")
    finally:
        engine.dispose()
