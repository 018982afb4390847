"""API tests against a FAKE runtime speaking the real protocol over real Zenoh on loopback."""

from __future__ import annotations

import math

import pytest

from runtime.telemetry import read_telemetry
from runtime.throw_geometry import impact_errors
from tests.conftest import wait_for, wait_online

TARGET_2D = [8.0, -0.292, 0.0]  # on the arm plane when cabin_turn = 0 (lateral offset -0.292 m)


def test_health(client):
    r = client.get("/api/health")
    assert r.status_code == 200
    assert r.json() == {"status": "ok", "zenoh": True, "database": True}


def test_machines_lists_online_simulated_machine_with_policy(client, fake_runtime_factory):
    assert client.get("/api/machines").json() == []
    fake_runtime_factory(machine_id="m1", cabin_turn_rad=0.25)
    m = wait_online(client, "m1")
    assert m["simulated"] is True
    assert m["policies"] == {"2d": "fake-2d"}
    assert m["cabin_turn_rad"] == pytest.approx(0.25)


def test_throw_happy_path_stores_result_and_telemetry(client, fake_runtime_factory, settings, throw_count):
    rt = fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 202, r.text
    throw_id = r.json()["id"]
    assert rt.requests[0].throw_id == throw_id and rt.requests[0].target_m == TARGET_2D

    row = wait_for(lambda: (t := client.get(f"/api/throws/{throw_id}").json())["status"] == "landed" and t,
                   10, "landed row")
    assert rt.acks and rt.acks[-1].stored is True and rt.acks[-1].throw_id == throw_id
    assert row["impact"] == pytest.approx([8.3, -0.1, 0.0])
    down, cross = impact_errors(TARGET_2D, [8.3, -0.1, 0.0])
    assert (row["downrange_error_m"], row["crossrange_error_m"]) == pytest.approx((down, cross))
    assert 0.25 < down < 0.35 and 0.15 < cross < 0.25  # long and left of the line
    assert row["policy_version"] == "fake-2d"
    assert row["target"] == TARGET_2D
    for key in ("requested_at", "started_at", "released_at", "completed_at"):
        assert row[key] is not None and row[key].endswith(("Z", "+00:00")), (key, row[key])
    assert row["duration_s"] == pytest.approx(3.2)
    assert row["telemetry_url"] == f"/api/throws/{throw_id}/telemetry"

    path = settings.data_dir / "telemetry" / f"{throw_id}.mcap"
    assert path.is_file()
    download = client.get(row["telemetry_url"])
    assert download.status_code == 200 and download.headers["content-type"] == "application/x-mcap"
    assert download.content == path.read_bytes()
    tel = read_telemetry(download.content)
    assert tel["q"].shape == (10, 6) and tel["payload_pos_m"].shape == (10, 3)

    # history: newest first, filter by machine
    listed = client.get("/api/throws", params={"machine_id": "m1"}).json()
    assert [t["id"] for t in listed] == [throw_id]
    assert client.get("/api/throws", params={"machine_id": "other"}).json() == []

    # the outbox re-delivers after a lost ack: idempotent, still one row, same values
    ack = rt.send_result(rt.results[-1])
    assert ack is not None and ack.stored is True
    assert throw_count() == 1
    assert client.get(f"/api/throws/{throw_id}").json()["impact"] == row["impact"]


def test_results_the_server_did_not_issue_are_refused(client, fake_runtime_factory, throw_count):
    """A result for an id the server never issued, an unsigned one and one with a bad MAC are
    refused with the reason and never reach the history."""
    from runtime.protocol.messages import ThrowRequest

    rt = fake_runtime_factory(deliver=False)
    wait_online(client)
    req = ThrowRequest(throw_id="orphan-1", machine_id="m1", mode="2d", target_m=TARGET_2D)
    assert rt.send_result(rt.make_result(req)) is None  # signed, but never issued
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    issued = ThrowRequest(throw_id=r.json()["id"], machine_id="m1", mode="2d", target_m=TARGET_2D)
    unsigned = rt.make_result(issued).model_copy(update={"auth": None})
    assert rt.send_result(unsigned) is None
    good = rt.make_result(issued)
    forged = good.model_copy(update={"impact_m": [1.0, 1.0, 0.0]})  # MAC no longer matches
    assert rt.send_result(forged) is None
    reasons = [reason for _tid, reason in client.app.state.fleet.refused_results]
    assert "never issued" in reasons[0] and "unsigned" in reasons[1] and "bad signature" in reasons[2]
    assert client.get("/api/throws/orphan-1").status_code == 404
    assert client.get(f"/api/throws/{issued.throw_id}").json()["status"] == "requested"
    assert rt.send_result(good).stored  # the genuine one is stored
    assert client.get(f"/api/throws/{issued.throw_id}").json()["status"] == "landed"
    assert throw_count() == 1


@pytest.mark.parametrize(
    "body",
    [
        {"machine_id": "m1", "mode": "2d"},  # no target
        {"machine_id": "m1", "mode": "2d", "target": [8.0, 0.0]},  # two numbers
        {"machine_id": "m1", "mode": "4d", "target": TARGET_2D},  # unknown mode
        {"machine_id": "m1", "mode": "2d", "target": ["a", 0, 0]},
        {"machine_id": "m1/*", "mode": "2d", "target": TARGET_2D},  # key-expression injection
        {"machine_id": "m1", "mode": "2d", "target": TARGET_2D, "speed": 3},  # unknown field
    ],
)
def test_malformed_request_is_422_and_leaves_no_row(client, fake_runtime_factory, throw_count, body):
    rt = fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", json=body)
    assert r.status_code == 422, r.text
    assert throw_count() == 0 and rt.requests == []


def test_non_finite_target_is_422(client, fake_runtime_factory, throw_count):
    fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", content=b'{"machine_id": "m1", "mode": "3d", "target": [NaN, 0, 0]}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert throw_count() == 0


@pytest.mark.parametrize(
    ("mode", "target", "reason"),
    [
        ("2d", [20.0, -0.292, 0.0], "beyond"),
        ("3d", [2.0, 1.0, 0.0], "too close"),
        ("2d", [0.0, 8.0, 0.0], "2D throwing plane"),
        ("3d", [8.0, 0.0, 3.0], "on the ground"),
    ],
)
def test_target_the_mode_cannot_serve_is_422_with_reason(client, fake_runtime_factory, throw_count, mode, target, reason):
    rt = fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": mode, "target": target})
    assert r.status_code == 422
    assert reason in r.json()["detail"]
    assert throw_count() == 0 and rt.requests == []


def test_2d_plane_follows_the_cabin_angle(client, fake_runtime_factory, throw_count):
    """The same target is off-plane or on-plane depending on the machine's current cabin angle."""
    yaw = math.pi / 2
    rt = fake_runtime_factory(cabin_turn_rad=yaw)
    wait_online(client)
    assert client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D}).status_code == 422
    rotated = [0.292, 8.0, 0.0]  # TARGET_2D turned by +90 degrees about z
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": rotated})
    assert r.status_code == 202, r.text
    assert len(rt.requests) == 1


def test_unknown_machine_is_404(client, fake_runtime_factory, throw_count):
    fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "nope", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 404 and "nope" in r.json()["detail"]
    assert throw_count() == 0
    assert client.get("/api/throws/does-not-exist").status_code == 404
    assert client.get("/api/throws/does-not-exist/telemetry").status_code == 404


def test_offline_runtime_is_503(client, fake_runtime_factory, throw_count):
    rt = fake_runtime_factory()
    wait_online(client)
    rt.close()
    wait_online(client, online=False)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 503 and "offline" in r.json()["detail"]
    assert throw_count() == 0


def test_runtime_refusal_is_422_with_its_reason_and_no_row(client, fake_runtime_factory, throw_count):
    rt = fake_runtime_factory(refuse="no 2d policy loaded")
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 422 and r.json()["detail"] == "no 2d policy loaded"
    assert len(rt.requests) == 1
    assert throw_count() == 0


def test_runtime_not_answering_is_503_and_the_throw_is_reconciled(client, fake_runtime_factory, throw_count, monkeypatch):
    """No answer: the runtime may have taken the throw, so the row stays until the runtime
    reports it or the reconciliation finds it is not running it (then ``lost``, with the reason,
    and a live ``result`` event: no result will come, and pages showing the throw read it again)."""
    rt = fake_runtime_factory(silent=True)
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 503 and "did not confirm" in r.json()["detail"], r.text
    assert len(rt.requests) == 1 and throw_count() == 1
    reconciler = client.app.state.reconciler
    reconciler.stop()  # passes by hand only: the running one acts on fleet events (server.fleet.reconcile)
    reconciler.handshake_s, reconciler.result_grace_s = 0.0, 0.0
    published = []
    monkeypatch.setattr(client.app.state.live, "publish", lambda event, data, console_id=None: published.append((event, data)))
    lost = reconciler.run_once()
    assert [tid for tid, _ in lost] == [rt.requests[0].throw_id]
    assert ("result", {"throw_id": rt.requests[0].throw_id}) in published
    row = client.get(f"/api/throws/{rt.requests[0].throw_id}").json()
    assert row["status"] == "lost" and "not running the throw" in row["failure_reason"]


def test_a_confirmed_promotion_is_announced_as_a_deployment_event(client, fake_runtime_factory, monkeypatch):
    """The runtime's PolicyUpdate settles the offered deployment and a live ``deployment`` event
    says so (its RuntimeInfo may have shown the new policy first: a page's rollback target moved)."""
    import time

    from runtime.protocol import keys
    from runtime.protocol.messages import PolicyUpdate, encode
    from server.db.models import Machine, PolicyDeployment, PolicyVersion

    with client.app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        v = PolicyVersion(name="pB", mode="2d", sha256="b" * 64, manifest={})
        db.add(v)
        db.flush()
        db.add(PolicyDeployment(machine_id="m1", mode="2d", policy_version_id=v.id, previous_sha256="a" * 64, status="offered"))
    rt = fake_runtime_factory()
    wait_online(client)
    published = []
    monkeypatch.setattr(client.app.state.live, "publish", lambda event, data, console_id=None: published.append((event, data)))
    update = PolicyUpdate(machine_id="m1", stamp_s=time.monotonic(), mode="2d", version="pB", sha256="b" * 64, status="loaded")
    rt.session.put(keys.policy_status("m1"), encode(update))
    wait_for(lambda: ("deployment", {"machine_id": "m1", "mode": "2d", "status": "active"}) in published, 10, "deployment event")


def test_openapi_documents_the_endpoints(client):
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/api/health", "/api/machines", "/api/throws", "/api/throws/{throw_id}",
              "/api/throws/{throw_id}/telemetry"):
        assert p in paths
    assert {"202", "404", "422", "503"} <= set(paths["/api/throws"]["post"]["responses"])
