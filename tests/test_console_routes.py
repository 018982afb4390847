"""Routes the console pages need: the API reference served without a CDN, and the preview
check (is a preview still valid for a throw now?) for a preview the server does not know."""

from __future__ import annotations


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


def test_refused_rollback_and_diagnosis_runs_are_audited(client):
    r = client.post("/api/policies/rollback", json={"machine_id": "m1", "mode": "2d"})
    assert r.status_code >= 400
    r = client.post("/api/diagnosis/runs", json={"machine_id": "m1", "limit": 10})
    assert r.status_code >= 400
    actions = {a["action"] for a in client.get("/api/audit").json()}
    assert {"rollback_refused", "diagnosis_run"} <= actions, actions


def test_rollback_targets_and_evaluate_an_unknown_version(client):
    r = client.get("/api/policies/rollback-targets", params={"machine_id": "m1"})
    assert r.status_code == 200 and r.json() == {"2d": None, "3d": None}, r.text  # nothing to roll back to
    r = client.post("/api/policies/999/evaluate")
    assert r.status_code == 404 and "no policy version" in r.json()["detail"]
