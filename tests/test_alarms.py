"""Alarms kept on the server (server.console.alarms, after ISA-18.2): raised by a condition, cleared when
it is gone, acknowledged by whom and when, acknowledge-all, shelving with a time limit, history,
audit entries; failed throws name their cause; the operator's own E-STOP is no alarm. Through
the API of a real app (SQLite, migrated)."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from server.console.alarms import MAX_SHELVE_MIN, failure_cause
from server.db.models import Machine, Throw
from server.fleet.events import ResultStored, RuntimeOffline, RuntimeOnline
from tests.conftest import ADMIN, add_user, login
from tests.fixtures import raise_drift_alert


def _throw(sessions, throw_id: str, status: str, reason: str | None) -> None:
    with sessions.begin() as db:
        if db.get(Machine, "m1") is None:
            db.add(Machine(id="m1", simulated=True))
        db.add(Throw(id=throw_id, machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=0.0, target_z_m=0.0,
                     requested_at=datetime.now(UTC), status=status, failure_reason=reason))


def _audit(client, action: str) -> list[dict]:
    r = client.get("/api/audit", params={"action": action, "limit": 1000})
    assert r.status_code == 200, r.text
    return r.json()


def test_failure_causes_are_named_and_an_operator_stop_is_no_alarm():
    assert failure_cause("m1", "behind real time by 150 ms")[0] == "host_behind_real_time"
    assert "not the network" in failure_cause("m1", "behind real time by 150 ms")[2]
    assert failure_cause("m1", "runtime not answering for 5 s")[0] == "runtime_not_answering"
    assert failure_cause("m1", "machine link lost (no joint states for 0.3 s)")[0] == "link_lost"
    assert failure_cause("m1", "joint at end stop")[0] == "machine_fault"
    assert failure_cause("m1", "E-STOP in the console (button)") is None
    loaded = failure_cause("m1", "machine link lost", load=(9.0, 2))[2]
    assert "load 9.0 on 2 cores" in loaded and "before the network" in loaded
    assert "load" not in failure_cause("m1", "machine link lost", load=(0.5, 2))[2]


def test_offline_alarm_is_raised_once_cleared_when_back_and_kept_until_acknowledged(client):
    alarms = client.app.state.alarms
    alarms.on_event(RuntimeOffline("m1"))
    alarms.on_event(RuntimeOffline("m1"))  # one alarm per standing condition
    active = client.get("/api/alarms").json()
    assert [(a["title"], a["state"], a["priority"]) for a in active] == [("m1: runtime offline", "unacked", "high")]
    alarms.on_event(RuntimeOnline("m1"))
    (a,) = client.get("/api/alarms").json()
    assert a["state"] == "rtn_unacked" and a["cleared_at"]  # cleared, still waits for its acknowledgement
    r = client.post(f"/api/alarms/{a['id']}/ack")
    assert r.status_code == 200 and r.json()["acked_by"] == ADMIN[0] and r.json()["state"] == "normal"
    assert client.get("/api/alarms").json() == []  # gone from the active list
    (h,) = client.get("/api/alarms", params={"active": "false"}).json()  # kept in the history
    assert h["id"] == a["id"] and h["acked_at"] and h["cleared_at"]
    assert [e["subject"] for e in _audit(client, "alarm_ack")] == ["m1"]
    assert {e["action"] for e in client.get("/api/audit", params={"limit": 1000}).json()} >= {"alarm_raise", "alarm_clear"}


def test_failed_throws_raise_alarms_with_their_cause_the_operators_stop_does_not(client):
    sessions, alarms = client.app.state.sessions, client.app.state.alarms
    _throw(sessions, "t-rt", "failed", "behind real time by 150 ms")
    _throw(sessions, "t-stop", "aborted", "E-STOP in the console (button)")
    _throw(sessions, "t-ok", "landed", None)
    for t in ("t-rt", "t-stop", "t-ok"):
        alarms.on_event(ResultStored(t))
    (a,) = client.get("/api/alarms").json()
    assert a["cause"] == "host_behind_real_time" and a["subject"] == "t-rt" and "control computer" in a["title"]


def test_acknowledge_all_shelve_with_a_limit_and_roles(client):
    alarms = client.app.state.alarms
    for mid in ("m1", "m2", "m3"):
        alarms.on_event(RuntimeOffline(mid))
    ids = [a["id"] for a in client.get("/api/alarms").json()]
    assert client.post(f"/api/alarms/{ids[0]}/shelve", json={"minutes": MAX_SHELVE_MIN + 1}).status_code == 422
    r = client.post(f"/api/alarms/{ids[0]}/shelve", json={"minutes": 30})
    assert r.status_code == 200 and r.json()["shelved"] and r.json()["shelved_by"] == ADMIN[0]
    add_user(client.app.state.sessions, "vera", "viewer-pass-1", "viewer")
    client.cookies.clear()
    login(client, "vera", "viewer-pass-1")
    assert len(client.get("/api/alarms").json()) == 3  # viewers read
    assert client.post("/api/alarms/ack-all", json={}).status_code == 403  # but do not acknowledge
    client.cookies.clear()
    login(client, *ADMIN)
    done = client.post("/api/alarms/ack-all", json={}).json()
    assert len(done) == 3 and all(a["state"] == "acked" for a in done)  # active (not cleared), acknowledged
    assert client.post("/api/alarms/ack-all", json={}).json() == []
    r = client.delete(f"/api/alarms/{ids[0]}/shelve")
    assert r.status_code == 200 and not r.json()["shelved"]
    assert {e["action"] for e in client.get("/api/audit", params={"limit": 1000}).json()} >= {"alarm_shelve", "alarm_unshelve"}
    assert client.post("/api/alarms/nope/ack").status_code == 404


def test_a_drift_alert_is_an_alarm_and_its_acknowledgement_acknowledges_the_alert(client):
    alert = raise_drift_alert(client.app.state.drift, "m1")
    (a,) = client.get("/api/alarms").json()
    assert a["cause"] == "drift" and a["priority"] == "medium" and a["text"] == alert["text"]
    assert client.post(f"/api/alarms/{a['id']}/ack").status_code == 200
    assert client.app.state.drift.alert("m1")["acknowledged_by"] == ADMIN[0]
    assert client.get("/api/alarms").json() == []  # the drift alert's acknowledgement cleared it
    assert _audit(client, "drift_ack")


@pytest.mark.parametrize("minutes", [0, -1])
def test_shelving_needs_a_positive_time(client, minutes):
    client.app.state.alarms.on_event(RuntimeOffline("m1"))
    (a,) = client.get("/api/alarms").json()
    assert client.post(f"/api/alarms/{a['id']}/shelve", json={"minutes": minutes}).status_code == 422


def test_every_change_of_an_alarm_raises_its_revision_and_a_no_op_does_not(client):
    """``revision`` orders one alarm's records for the consoles (web/js/strip.js): 1 when raised, one
    more with each change, the same after an act that changes nothing; its live events carry it."""
    alarms = client.app.state.alarms
    heard = []
    alarms.publish = lambda event, data: heard.append(data["revision"])
    a = alarms.raise_alarm("k:rev", "m1", "high", "machine_fault", "m1: revisions", "text", "todo")
    assert a["revision"] == 1
    revisions = [client.post(f"/api/alarms/{a['id']}/shelve", json={"minutes": 5}).json()["revision"],
                 client.delete(f"/api/alarms/{a['id']}/shelve").json()["revision"],
                 client.delete(f"/api/alarms/{a['id']}/shelve").json()["revision"],  # not shelved: no change
                 client.post(f"/api/alarms/{a['id']}/ack").json()["revision"],
                 client.post(f"/api/alarms/{a['id']}/ack").json()["revision"]]  # acknowledged already
    assert revisions == [2, 3, 3, 4, 4]
    (cleared,) = alarms.clear("k:rev")
    assert cleared["revision"] == 5 and not cleared["active"]
    assert heard == [1, 2, 3, 3, 4, 5]  # the unchanged unshelve is published too; the second ack is not
