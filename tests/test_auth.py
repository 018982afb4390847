"""Accounts: log-in, roles on routes, expiring sessions, bearer tokens, users API, audit log."""

from __future__ import annotations

from datetime import timedelta

import pytest

from server.accounts.auth import hash_password, verify_password
from server.db.models import AuthSession
from tests.conftest import ADMIN, add_user, login, wait_online

TARGET_2D = [8.0, -0.292, 0.0]


def test_password_hash_is_argon2_and_verifies():
    h = hash_password("correct horse")
    assert h.startswith("$argon2id$") and "correct horse" not in h
    assert verify_password(h, "correct horse") and not verify_password(h, "wrong")
    assert not verify_password("not-a-hash", "x")


def test_routes_need_a_session(client):
    client.cookies.clear()
    assert client.get("/api/health").status_code == 200  # public
    for path in ("/api/machines", "/api/throws", "/api/scene", "/api/auth/me", "/api/users"):
        assert client.get(path).status_code == 401, path
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 401


def test_bad_credentials_are_401_with_one_message(client):
    client.cookies.clear()
    for user, pw in ((ADMIN[0], "wrong-pass"), ("nobody", "whatever1")):
        r = client.post("/api/auth/login", json={"username": user, "password": pw})
        assert r.status_code == 401 and r.json()["detail"] == "invalid user name or password"
    assert client.post("/api/auth/login", json={"username": "", "password": ""}).status_code == 422


def test_login_cookie_bearer_and_logout(client):
    client.cookies.clear()
    r = client.post("/api/auth/login", json={"username": ADMIN[0], "password": ADMIN[1]})
    assert r.status_code == 200
    body = r.json()
    assert body["user"] == {**body["user"], "username": "admin", "role": "admin"}
    assert "slinger_session" in r.headers["set-cookie"] and "HttpOnly" in r.headers["set-cookie"]
    token = body["token"]
    assert client.get("/api/auth/me").json()["username"] == "admin"
    client.cookies.clear()
    assert client.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).status_code == 200
    assert client.post("/api/auth/logout", headers={"Authorization": f"Bearer {token}"}).status_code == 204
    assert client.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401


def test_session_expires(client):
    token = client.post("/api/auth/login", json={"username": ADMIN[0], "password": ADMIN[1]}).json()["token"]
    with client.app.state.sessions.begin() as db:
        for row in db.query(AuthSession).all():
            row.expires_at = row.expires_at - timedelta(days=2)
    client.cookies.clear()
    assert client.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401


def test_roles_viewer_operator_admin(client, fake_runtime_factory):
    sessions = client.app.state.sessions
    add_user(sessions, "vera", "viewer-pass-1", "viewer")
    add_user(sessions, "otto", "operator-pass", "operator")
    rt = fake_runtime_factory()
    wait_online(client)

    client.cookies.clear()
    login(client, "vera", "viewer-pass-1")
    assert client.get("/api/machines").status_code == 200
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 403 and "operator" in r.json()["detail"]
    assert client.get("/api/users").status_code == 403
    assert rt.requests == []

    client.cookies.clear()
    login(client, "otto", "operator-pass")
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 202, r.text
    assert client.post("/api/users", json={"username": "x", "password": "123456789012"}).status_code == 403

    client.cookies.clear()
    login(client, *ADMIN)
    audit = client.get("/api/audit", params={"action": "throw"}).json()
    assert audit[0]["username"] == "otto" and audit[0]["subject"] == r.json()["id"]
    assert client.get(f"/api/throws/{r.json()['id']}").status_code == 200


def test_users_api(client):
    r = client.post("/api/users", json={"username": "nina", "password": "nina-pass-123", "role": "operator"})
    assert r.status_code == 201 and r.json()["role"] == "operator"
    assert client.post("/api/users", json={"username": "nina", "password": "nina-pass-123"}).status_code == 409
    assert client.post("/api/users", json={"username": "short", "password": "123"}).status_code == 422
    assert client.post("/api/users", json={"username": "r", "password": "123456789012", "role": "god"}).status_code == 422
    assert [u["username"] for u in client.get("/api/users").json()] == ["admin", "nina"]
    # deactivating ends the user's sessions
    token = client.post("/api/auth/login", json={"username": "nina", "password": "nina-pass-123"}).json()["token"]
    client.cookies.clear()
    login(client, *ADMIN)
    assert client.patch("/api/users/nina", json={"active": False}).json()["active"] is False
    assert client.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401
    assert client.patch("/api/users/admin", json={"role": "viewer"}).status_code == 422  # not yourself
    assert client.patch("/api/users/ghost", json={"role": "viewer"}).status_code == 404
    actions = [a["action"] for a in client.get("/api/audit").json()]
    assert "user_add" in actions and "user_update" in actions and "login" in actions


@pytest.mark.parametrize("argv_extra", [["--role", "operator"], ["--admin"]])
def test_cli_user_add(tmp_path, argv_extra, capsys):
    from server.cli import main

    data = str(tmp_path / "v")
    rc = main(["user", "add", "someone", *argv_extra, "--data-dir", data])
    out = capsys.readouterr().out
    assert rc == 0 and "password:" in out  # generated (stdin is not a terminal) and shown once
    assert main(["user", "add", "someone", "--data-dir", data, "--password", "abcdefgh1234"]) == 1  # exists
    main(["user", "list", "--data-dir", data])
    assert "someone" in capsys.readouterr().out


def _sqlite_cli(db_file, sql: str) -> None:
    """Run ``sql`` with the sqlite3 command-line shell (foreign keys off, its default)."""
    import shutil
    import sqlite3
    import subprocess

    if shutil.which("sqlite3"):
        subprocess.run(["sqlite3", str(db_file), "PRAGMA foreign_keys=OFF; " + sql], check=True, timeout=30)
    else:  # the same semantics from Python's sqlite3 (foreign keys are off by default there too)
        con = sqlite3.connect(db_file)
        con.executescript("PRAGMA foreign_keys=OFF; " + sql)
        con.close()


@pytest.mark.parametrize("drop_trigger", [False, True], ids=["as-migrated", "without-cascade-trigger"])
def test_deleted_users_session_never_authenticates_a_new_user_with_the_same_id(client, settings, drop_trigger):
    """An admin's row deleted by raw SQL with foreign keys off; SQLite gives the next account the
    same id; the deleted admin's token must not answer as the new account (issue 24 finding 3).
    Without the cascade trigger (a tool that drops it, or a restore) the per-user key still holds."""
    from sqlalchemy import select

    from server.db.models import User

    sessions = client.app.state.sessions
    add_user(sessions, "dora", "dora-admin-pass", "admin")
    r = client.post("/api/auth/login", json={"username": "dora", "password": "dora-admin-pass"})
    token = r.json()["token"]
    client.cookies.clear()
    bearer = {"Authorization": f"Bearer {token}"}
    assert client.get("/api/auth/me", headers=bearer).json()["username"] == "dora"
    with sessions() as db:
        dora_id = db.scalar(select(User.id).where(User.username == "dora"))
    db_file = settings.data_dir / "slinger.db"
    if drop_trigger:
        _sqlite_cli(db_file, "DROP TRIGGER trg_users_delete_auth_sessions;")
    _sqlite_cli(db_file, "DELETE FROM users WHERE username = 'dora';")
    add_user(sessions, "eve", "eve-viewer-pass", "viewer")
    with sessions() as db:
        assert db.scalar(select(User.id).where(User.username == "eve")) == dora_id  # the id was reused
        left = db.query(AuthSession).filter(AuthSession.user_id == dora_id).count()
    assert left == (1 if drop_trigger else 0)  # the trigger cascades what foreign keys did not
    r = client.get("/api/auth/me", headers=bearer)
    assert r.status_code == 401, r.text
    login(client, "eve", "eve-viewer-pass")
    assert client.get("/api/auth/me").json() == {**client.get("/api/auth/me").json(), "username": "eve",
                                                 "role": "viewer"}
