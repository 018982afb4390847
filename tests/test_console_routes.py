"""Routes the console pages need: the API reference served without a CDN, the preview check
(is a preview still valid for a throw now?) for a preview the server does not know, and the
audit entries of security-relevant actions (failed log-ins, rollbacks, diagnosis runs,
password changes) that the Users page shows, and the drift alert's acknowledgement."""

from __future__ import annotations

import json
import threading

from tests.conftest import ADMIN, add_user, login, wait_for
from tests.fixtures import raise_drift_alert


def _audit(client, action: str) -> list[dict]:
    """The audit log's entries of ``action``, newest first (read as the admin)."""
    r = client.get("/api/audit", params={"action": action, "limit": 1000})
    assert r.status_code == 200, r.text
    return r.json()


def test_api_docs_work_offline(client):
    for path in ("/docs", "/redoc"):
        html = client.get(path).text
        assert "/docs-static/" in html, path
        assert "cdn." not in html and "https://" not in html.split("<body")[1], path  # nothing fetched from outside
    for f in ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js"):
        r = client.get(f"/docs-static/{f}")
        assert r.status_code == 200 and len(r.content) > 10_000, f


def test_preview_check_of_an_unknown_preview_is_invalid_with_a_reason(client):
    r = client.post("/api/previews/nope/check", json={"machine_id": "m1", "mode": "2d", "target": [8.0, 0.0, 0.0]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["valid"] is False and body["reason"], body


def test_preview_check_refuses_bad_input(client):
    r = client.post("/api/previews/nope/check", json={"machine_id": "m1", "mode": "2d", "target": [8.0, 0.0]})
    assert r.status_code == 422


def test_a_user_changes_their_own_password_audited(client):
    from tests.conftest import ADMIN

    r = client.post("/api/account/password", json={"current_password": "not-it", "new_password": "a-new-password-1"})
    assert r.status_code == 403 and "current password" in r.json()["detail"]
    r = client.post("/api/account/password", json={"current_password": ADMIN[1], "new_password": "a-new-password-1"})
    assert r.status_code == 204, r.text
    assert client.get("/api/auth/me").status_code == 401  # every session ended: log in again
    r = client.post("/api/auth/login", json={"username": ADMIN[0], "password": "a-new-password-1"})
    assert r.status_code == 200
    entries = [a for a in client.get("/api/audit").json() if a["action"] == "password_change"]
    assert [e["detail"]["changed"] for e in entries] == [True, False], entries


def test_a_failed_log_in_writes_exactly_one_entry_and_no_password(client):
    secret = "Wrong-Secret-4711"
    before = len(_audit(client, "login_failed"))
    r = client.post("/api/auth/login", json={"username": ADMIN[0], "password": secret})
    assert r.status_code == 401 and r.json()["detail"] == "invalid user name or password"
    login(client, *ADMIN)  # the failure logged the client out of nothing: log in again to read
    entries = _audit(client, "login_failed")
    assert len(entries) == before + 1, entries
    e = entries[0]
    assert (e["username"], e["subject"]) == (ADMIN[0], ADMIN[0])
    assert e["detail"] == {"address": "testclient", "reason": "wrong password"}, e
    log = client.get("/api/audit", params={"limit": 1000}).text
    assert secret not in log and ADMIN[1] not in log  # neither the wrong nor the right password


def test_failed_log_ins_of_unknown_and_disabled_users_are_audited_with_the_name_as_typed(client):
    add_user(client.app.state.sessions, "dora", "dora-pass-123", "viewer")
    assert client.patch("/api/users/dora", json={"active": False}).status_code == 200
    typed = "nobody\x1b[31m"
    assert client.post("/api/auth/login", json={"username": typed, "password": "whatever-1"}).status_code == 401
    assert client.post("/api/auth/login", json={"username": "dora", "password": "dora-pass-123"}).status_code == 401
    login(client, *ADMIN)
    by_subject = {e["subject"]: e["detail"]["reason"] for e in _audit(client, "login_failed")}
    assert by_subject["dora"] == "account disabled"
    assert by_subject["nobody\\x1b[31m"] == "unknown user"  # as typed, the control character escaped


def test_held_log_ins_are_audited_one_entry_each(client):
    for _ in range(5):  # Settings.login_failures_per_user_address: 5 per 5 minutes
        assert client.post("/api/auth/login", json={"username": "otto", "password": "guess-123"}).status_code == 401
    r = client.post("/api/auth/login", json={"username": "otto", "password": "guess-123"})
    assert r.status_code == 429 and int(r.headers["Retry-After"]) > 0
    held = lambda: [e for e in _audit(client, "login_failed") if e["detail"]["reason"].startswith("held")]  # noqa: E731
    wait_for(held, 5.0, "the held attempt's audit entry")  # written on the guard's audit thread
    entries = _audit(client, "login_failed")
    assert len(entries) == 6 and len(held()) == 1, entries
    assert all(e["subject"] == "otto" and e["detail"]["address"] == "testclient" for e in entries)
    assert "guess-123" not in json.dumps(entries)


def test_the_login_guard_drops_audit_entries_past_its_backlog_and_counts_them():
    from server.accounts.login_guard import LoginGuard

    guard = LoginGuard(max_audit_backlog=1)
    started, gate, written = threading.Event(), threading.Event(), []
    guard.record_later(lambda n: (started.set(), gate.wait(5), written.append(("first", n))))
    assert started.wait(5)  # the first write runs (it left the backlog)
    guard.record_later(lambda n: written.append(("second", n)))  # waits: the backlog is full now
    guard.record_later(lambda n: written.append(("dropped", n)))
    guard.record_later(lambda n: written.append(("dropped too", n)))
    gate.set()
    guard.close()
    assert written == [("first", 0), ("second", 2)]  # the second entry carries the count of the dropped


def test_rollback_attempts_are_audited_refused_ones_too(client):
    r = client.post("/api/policies/rollback", json={"machine_id": "m1", "mode": "2d"})
    assert r.status_code == 409 and "no previous" in r.json()["detail"]
    add_user(client.app.state.sessions, "otto", "operator-pass", "operator")
    login(client, "otto", "operator-pass")
    r = client.post("/api/policies/rollback", json={"machine_id": "m1", "mode": "3d"})
    assert r.status_code == 403 and "admin role" in r.json()["detail"]
    login(client, *ADMIN)
    entries = _audit(client, "rollback_refused")
    assert [(e["username"], e["subject"], e["detail"]["mode"]) for e in entries] == [("otto", "m1", "3d"), ("admin", "m1", "2d")]
    assert "no previous 2d policy version" in entries[1]["detail"]["reason"]
    assert "admin role" in entries[0]["detail"]["reason"]


def test_refused_diagnosis_runs_are_audited(client):
    r = client.post("/api/diagnosis/runs", json={"machine_id": "m1", "limit": 10})
    assert r.status_code == 422
    (e,) = _audit(client, "diagnosis_run")
    assert (e["username"], e["subject"], e["detail"]["started"]) == (ADMIN[0], "m1", False)
    assert e["detail"]["reason"], e


def test_rollback_targets_and_evaluate_an_unknown_version(client):
    r = client.get("/api/policies/rollback-targets", params={"machine_id": "m1"})
    assert r.status_code == 200 and r.json() == {"2d": None, "3d": None}, r.text  # nothing to roll back to
    r = client.post("/api/policies/999/evaluate")
    assert r.status_code == 404 and "no policy version" in r.json()["detail"]


def test_a_drift_alert_is_acknowledged_by_an_operator_published_and_audited(client):
    published = []
    hub = client.app.state.live
    watch = client.app.state.drift
    watch.publish = lambda event, data: (published.append((event, data)), hub.publish(event, data))
    assert client.post("/api/machines/m1/drift/ack").status_code == 404  # no alert yet
    alert = raise_drift_alert(watch, "m1")
    assert alert["status"] == "open" and published[-1] == ("drift", alert)
    add_user(client.app.state.sessions, "vera", "viewer-pass-1", "viewer")
    login(client, "vera", "viewer-pass-1")
    r = client.post("/api/machines/m1/drift/ack")
    assert r.status_code == 403 and r.json()["detail"] == "acknowledging a drift alert needs the operator role (you are viewer)"
    assert watch.alert("m1")["status"] == "open"  # the refusal changed nothing
    add_user(client.app.state.sessions, "otto", "operator-pass", "operator")
    login(client, "otto", "operator-pass")
    r = client.post("/api/machines/m1/drift/ack")
    assert r.status_code == 200, r.text
    body = r.json()
    assert (body["status"], body["acknowledged_by"], body["raised_at"]) == ("acknowledged", "otto", alert["raised_at"])
    assert published[-1][0] == "drift" and published[-1][1]["status"] == "acknowledged"  # every console clears its alarm
    assert watch.alerts() == [body] and hub.status("m1")["drift_alert"]["status"] == "acknowledged"
    again = client.post("/api/machines/m1/drift/ack").json()
    assert again["acknowledged_by"] == "otto" and again["acknowledged_at"] == body["acknowledged_at"]  # the first one stays
    login(client, *ADMIN)
    entries = _audit(client, "drift_ack")
    assert [(e["username"], e["subject"], e["detail"]["acknowledged"]) for e in entries] == [
        ("otto", "m1", True), ("otto", "m1", True), ("vera", "m1", False)]
    assert entries[0]["detail"]["raised_at"] == alert["raised_at"] and entries[0]["detail"]["alert"] == alert["text"]
