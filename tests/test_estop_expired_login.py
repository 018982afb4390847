"""A console left open past the end of its log-in keeps its E-STOP, and nothing else
(docs/safety.md, row S13; server.accounts.auth.STOP_GRACE_S).

A log-in lasts ``session_ttl_s`` (12 h). Before, the session cookie ended with it and the server
refused the E-STOP of an expired session with 401, on which the console left for the log-in page:
the stop was neither sent nor reported. Now a session whose log-in expired less than 24 h ago
still stops (the answer and the audit entry say the log-in had expired), every other request is
refused as before, and a session that was ended (log-out, disabled account) or expired longer ago
stops nothing.

Runs the app in the test process against FakeRuntime (tests/conftest.py) over loopback Zenoh.
"""

from __future__ import annotations

import hashlib
from datetime import timedelta

from sqlalchemy import select, update

from server.accounts.auth import COOKIE_NAME, STOP_GRACE_S, create_session
from server.db.models import AuditEntry, AuthSession, User
from server.db.types import utcnow
from tests.conftest import add_user, login, wait_for

OPERATOR = ("op1", "operator-pass-1")
THROW = {"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]}


def _app(settings):
    from fastapi.testclient import TestClient

    from server.app import create_app

    return TestClient(create_app(settings))


def _expire(sessions, token: str, ago_s: float) -> None:
    """Make the session of ``token`` expire ``ago_s`` seconds ago (a commit: the mirror re-reads)."""
    digest = hashlib.sha256(token.encode()).hexdigest()
    with sessions.begin() as db:
        db.execute(update(AuthSession).where(AuthSession.token_sha256 == digest)
                   .values(expires_at=utcnow() - timedelta(seconds=ago_s)))


def _log_in(c, user=OPERATOR) -> str:
    r = c.post("/api/auth/login", json={"username": user[0], "password": user[1]})
    assert r.status_code == 200, r.text
    return r.json()["token"]


def _ready(c, rt) -> None:
    wait_for(lambda: (m := next((x for x in c.get("/api/machines").json() if x["id"] == "m1"), None))
             and m["online"] and m["ready"], 20, "m1 ready")


def test_an_expired_log_in_still_stops_and_nothing_else(settings, fake_runtime_factory):
    with _app(settings) as c:
        add_user(c.app.state.sessions, *OPERATOR, "operator")
        r = c.post("/api/auth/login", json={"username": OPERATOR[0], "password": OPERATOR[1]})
        assert r.status_code == 200, r.text
        token = r.json()["token"]
        cookie = r.headers["set-cookie"]
        assert f"Max-Age={int(settings.session_ttl_s + STOP_GRACE_S)}" in cookie, cookie  # the cookie outlives the log-in
        rt = fake_runtime_factory(site_dir=settings.resolved_site_dir)
        _ready(c, rt)
        me = c.get("/api/auth/me").json()  # the console announces the end of the log-in from this
        assert me["username"] == OPERATOR[0] and me["session_expires_at"] == r.json()["expires_at"], me

        _expire(c.app.state.sessions, token, 60.0)
        assert c.get("/api/auth/me").status_code == 401  # the log-in is over ...
        assert c.get("/api/machines").status_code == 401
        assert c.post("/api/throws", json=THROW).status_code == 401
        assert rt.requests == []
        r = c.post("/api/machines/m1/estop", json={"reason": "late shift"})  # ... but the stop is taken
        assert r.status_code == 200, r.text
        expired_at = r.json()["login_expired_at"]
        assert expired_at is not None
        assert rt.estop_reason is not None and "late shift" in rt.estop_reason and "log-in expired" in rt.estop_reason
        assert c.post("/api/machines/m1/estop/reset").status_code == 401  # a reset needs a log-in
        assert rt.estop_reason is not None

        def audited():
            with c.app.state.sessions() as db:
                return [e.detail for e in db.scalars(select(AuditEntry).where(AuditEntry.action == "abort"))]

        entry = wait_for(lambda: audited(), 10, "the E-STOP's audit entry")[0]
        assert entry["delivered"] is True and entry["login_expired_at"] and entry["login_expired_at"][:16] == expired_at[:16], entry

        # logged in again: the answer names no expiry
        c.cookies.clear()
        _log_in(c)
        r = c.post("/api/machines/m1/estop", json={"reason": "again"})
        assert r.status_code == 200 and r.json()["login_expired_at"] is None, r.text


def test_an_ended_or_long_expired_log_in_stops_nothing(settings, fake_runtime_factory):
    with _app(settings) as c:
        add_user(c.app.state.sessions, *OPERATOR, "operator")
        add_user(c.app.state.sessions, "vic", "viewer-pass-1", "viewer")
        rt = fake_runtime_factory(site_dir=settings.resolved_site_dir)
        token = _log_in(c)
        _ready(c, rt)

        def press() -> int:
            return c.post("/api/machines/m1/estop", json={"reason": "x"}).status_code

        _expire(c.app.state.sessions, token, STOP_GRACE_S + 60.0)
        assert press() == 401  # expired more than a day ago
        _expire(c.app.state.sessions, token, 60.0)
        with c.app.state.sessions.begin() as db:  # the account disabled by an admin
            db.scalars(select(User).where(User.username == OPERATOR[0])).one().active = False
        assert press() == 401
        with c.app.state.sessions.begin() as db:
            db.scalars(select(User).where(User.username == OPERATOR[0])).one().active = True
        assert press() == 200  # the same expired session once the account is active again
        rt.estop_reason = None
        assert c.post("/api/auth/logout").status_code == 204
        c.cookies.set(COOKIE_NAME, token)  # the console still holds the ended session's token
        assert press() == 401  # logged out: ended, not expired
        c.cookies.clear()
        viewer = _log_in(c, ("vic", "viewer-pass-1"))
        _expire(c.app.state.sessions, viewer, 60.0)
        assert press() == 403  # a viewer's expired session is still a viewer's
        assert rt.estop_reason is None


def test_expired_sessions_are_kept_for_the_grace_then_purged_and_the_mirror_holds_them(settings):
    with _app(settings) as c:
        sessions, mirror = c.app.state.sessions, c.app.state.session_mirror
        add_user(sessions, *OPERATOR, "operator")
        recent, old = _log_in(c), _log_in(c)
        _expire(sessions, recent, 3600.0)
        _expire(sessions, old, STOP_GRACE_S + 3600.0)
        assert mirror.user(recent) is None and mirror.session(recent) is None  # expired for everything ...
        held = mirror.session(recent, STOP_GRACE_S)  # ... but the stop
        assert held is not None and held[0].username == OPERATOR[0] and held[1] < utcnow()
        assert mirror.session(old, STOP_GRACE_S) is None
        with sessions.begin() as db:  # the next log-in purges what is past the grace
            create_session(db, db.scalars(select(User).where(User.username == OPERATOR[0])).one(), 60.0)
        with sessions() as db:
            kept = {row.token_sha256 for row in db.scalars(select(AuthSession))}
        assert hashlib.sha256(recent.encode()).hexdigest() in kept
        assert hashlib.sha256(old.encode()).hexdigest() not in kept
