"""The server side of the control chain against a FAKE runtime over real Zenoh: the preview gate,
signed commands, E-STOP latch and reset, reconciliation of open throws (``lost``).

The fake runtime checks signatures with the machine's command key like the real one, so an
accepted throw here proves the server signed it for the right epoch."""

from __future__ import annotations

import time
from datetime import timedelta

import pytest

from server.db.types import utcnow
from server.throws.gate import GateLimits
from tests.conftest import add_user, login, wait_for, wait_online

TARGET = [8.0, -0.292, 0.0]
Q = [0.0, -0.5, 1.5, 0.2, -1.0, 0.0]  # the fake runtime's joint state


def _preview(client, **changes) -> str:
    """Store a finished preview job (as POST /api/previews and a worker would) and return its id;
    ``id`` "gone" is returned without storing anything (an unknown preview)."""
    from datetime import datetime

    from server.db.models import Job

    summary = {"status": "ok", "reason": None, "machine_id": "m1", "mode": "2d", "target_m": list(TARGET),
               "policy_version": "fake-2d", "policy_sha256": "ab" * 32, "created_at": utcnow().isoformat(),
               "start_q": list(Q), **changes}
    if summary.pop("id", None) == "gone":
        return "gone"
    created = datetime.fromisoformat(summary.pop("created_at"))
    with client.app.state.sessions.begin() as db:
        job = Job(kind="preview", status="done", params={"meta": {}}, result=summary, progress=1.0,
                  cancel_requested=False, created_at=created)
        db.add(job)
        db.flush()
        return job.id


@pytest.fixture
def gated(client, fake_runtime_factory):
    client.app.state.throws.gate = GateLimits()
    rt = fake_runtime_factory()
    wait_online(client)
    return rt


def _throw(client, preview_id=None, target=TARGET):
    body = {"machine_id": "m1", "mode": "2d", "target": target}
    if preview_id is not None:
        body["preview_id"] = preview_id
    return client.post("/api/throws", json=body)


GATE_CASES = [  # (preview changes or None for no preview, target, status, condition, words in the detail)
    (None, TARGET, 422, "preview_missing", "preview_id"),
    ({"id": "gone"}, TARGET, 422, "preview_unknown", "preview again"),
    ({"status": "failed", "reason": "clearance violation: ground"}, TARGET, 422, "preview_failed", "ground"),
    ({"mode": "3d"}, TARGET, 422, "preview_other", "another machine or mode"),
    ({}, [8.2, -0.292, 0.0], 422, "preview_target", "0.20 m away"),
    ({"created_at": "old"}, TARGET, 409, "preview_stale", "s old (at most 60 s)"),
    ({"policy_sha256": "cd" * 32}, TARGET, 409, "policy_changed", "policy changed"),
    ({"start_q": [0.0, -0.43, 1.5, 0.2, -1.0, 0.0]}, TARGET, 409, "machine_moved", "boom by 0.070 rad"),
    ({"start_q": [0.0, -0.5, 1.5, 0.2, -1.5, 0.0]}, TARGET, 409, "machine_moved", "gripper pitch by 0.500 rad"),
]


def test_gate_names_the_failed_condition(client, gated, throw_count):
    for changes, target, status, condition, words in GATE_CASES:
        pid = None
        if changes is not None:
            if changes.get("created_at") == "old":
                changes = {"created_at": (utcnow() - timedelta(seconds=90)).isoformat()}
            pid = _preview(client, **changes)
        r = _throw(client, pid, target)
        assert r.status_code == status, (condition, r.text)
        assert r.headers["x-refused-condition"] == condition and words in r.json()["detail"], r.text
    assert gated.requests == [] and throw_count() == 0


def test_gated_throw_is_signed_for_the_user_and_epoch(client, gated):
    r = _throw(client, _preview(client, target_m=[8.03, -0.292, 0.0]))  # within the 5 cm tolerance
    assert r.status_code == 202, r.text
    auth = gated.requests[0].auth
    assert auth.user == "admin" and auth.epoch == gated.epoch
    row = wait_for(lambda: (t := client.get(f"/api/throws/{r.json()['id']}").json())["status"] == "landed" and t, 10)
    assert row["preview"]["policy_sha256"] == "ab" * 32


def test_estop_latches_until_an_operator_resets_it(client, gated):
    r = client.post("/api/machines/m1/estop", json={"reason": "person in the zone"})
    assert r.status_code == 200, r.text
    assert gated.estop_reason == "person in the zone (admin)"
    m = wait_for(lambda: (m := client.get("/api/machines").json()[0])["estop_latched"] and m, 5, "latched")
    assert m["ready"] is False and m["not_ready_reason"] == "E-STOP latched"
    r = _throw(client, _preview(client))
    assert r.status_code == 409 and "E-STOP latched" in r.json()["detail"], r.text
    assert r.headers["X-Refused-Condition"] == "estop_latched"

    add_user(client.app.state.sessions, "vic", "viewer-pass-1", "viewer")
    client.cookies.clear()
    login(client, "vic", "viewer-pass-1")
    assert client.post("/api/machines/m1/estop/reset").status_code == 403
    assert client.post("/api/machines/m1/estop").status_code == 403
    client.cookies.clear()
    assert client.post("/api/machines/m1/estop").status_code == 401
    login(client, "admin", "admin-pass-1")
    r = client.post("/api/machines/m1/estop/reset")
    assert r.status_code == 200 and r.json()["reset"] is True, r.text
    assert gated.estop_reason is None
    assert _throw(client, _preview(client)).status_code == 202
    actions = [(e["username"], e["action"]) for e in client.get("/api/audit").json()]
    assert ("admin", "abort") in actions and ("admin", "estop_reset") in actions


def test_reset_with_a_wrong_key_is_refused_with_the_runtime_reason(client, gated):
    client.post("/api/machines/m1/estop")
    client.app.state.fleet.signer._keys["m1"] = b"\x00" * 32  # the server's key no longer matches
    r = client.post("/api/machines/m1/estop/reset")
    assert r.status_code == 409 and "bad signature" in r.json()["detail"]
    assert gated.estop_reason is not None


def test_restarted_runtime_without_the_throw_makes_it_lost(client, fake_runtime_factory):
    first = fake_runtime_factory(hold=True)
    wait_online(client)
    tid = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET}).json()["id"]
    reconciler = client.app.state.reconciler
    reconciler.stop()  # passes by hand only: the running one acts on fleet events (server.fleet.reconcile)
    reconciler.handshake_s, reconciler.result_grace_s = 0.0, 0.0
    assert reconciler.run_once() == []  # the runtime is running it
    first.close()
    wait_online(client, online=False)
    second = fake_runtime_factory()
    wait_online(client)
    wait_for(lambda: client.app.state.fleet.epoch_of("m1", fresh=True) == second.epoch, 5, "new epoch")
    lost = reconciler.run_once()
    assert [t for t, _ in lost] == [tid]
    row = client.get(f"/api/throws/{tid}").json()
    assert row["status"] == "lost" and f"epoch {first.epoch} -> {second.epoch}" in row["failure_reason"]
    # no ThrowResult comes for it, yet the operator is told as for a failed throw (docs/operator-guide.md: alarms)
    (alarm,) = [a for a in client.get("/api/alarms").json() if a["key"] == f"throw:{tid}"]
    assert alarm["priority"] == "high" and alarm["cause"] == "runtime_not_answering" and "lost" in alarm["title"]


def test_running_reconciler_acts_on_the_restart_event_not_on_its_sweep(client, fake_runtime_factory):
    """The reconciler's own thread marks the throw lost when the restarted runtime comes online
    (a fleet event), long before its backstop sweep (60 s here) would have."""
    first = fake_runtime_factory(hold=True)
    wait_online(client)
    tid = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET}).json()["id"]
    reconciler = client.app.state.reconciler
    reconciler.handshake_s, reconciler.result_grace_s, reconciler.period_s = 0.0, 0.0, 60.0
    reconciler.wake()  # a pass now, which sets its next sweep 60 s away
    time.sleep(0.5)
    assert client.get(f"/api/throws/{tid}").json()["status"] != "lost"  # the runtime is running it
    first.close()
    wait_online(client, online=False)
    fake_runtime_factory()
    t0 = time.monotonic()
    wait_for(lambda: client.get(f"/api/throws/{tid}").json()["status"] == "lost", 8, "throw lost")
    assert time.monotonic() - t0 < 8 and "restarted" in client.get(f"/api/throws/{tid}").json()["failure_reason"]


def test_runtime_gone_past_the_bound_then_a_late_result_replaces_lost(client, fake_runtime_factory):
    from runtime.protocol.messages import ThrowRequest

    rt = fake_runtime_factory(hold=True)
    wait_online(client)
    tid = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET}).json()["id"]
    req = rt.requests[0]
    rt.close()
    wait_online(client, online=False)
    reconciler = client.app.state.reconciler
    reconciler.stop()  # passes by hand only: the running one acts on fleet events (server.fleet.reconcile)
    reconciler.handshake_s = 0.0
    assert reconciler.run_once() == []  # offline for less than the bound
    reconciler.runtime_gone_s = 0.0
    assert [t for t, _ in reconciler.run_once()] == [tid]
    assert "offline for" in client.get(f"/api/throws/{tid}").json()["failure_reason"]
    # the runtime was only cut off: it comes back with the result in its outbox
    back = fake_runtime_factory(deliver=False)
    back.epoch = rt.epoch
    assert back.send_result(back.make_result(ThrowRequest(**req.model_dump(exclude={"auth"})))).stored
    assert client.get(f"/api/throws/{tid}").json()["status"] == "landed"
