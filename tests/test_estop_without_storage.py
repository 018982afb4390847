"""An E-STOP that needs nothing but the link, and one that could not be delivered stays pressed
(docs/safety.md, hazard table):

* with the data directory's disk full (a small tmpfs) the E-STOP is authorised from memory
  (server.accounts.auth.SessionMirror), sent and confirmed; ``GET /api/machines`` answers from memory; the
  audit entry is written once the disk has room again (server.accounts.auth.AuditBacklog);
* with PostgreSQL unreachable (a TCP relay to it cut) the same holds;
* a deactivated account's session is refused at once, a deleted one's (deleted outside the
  server) within the mirror's refresh;
* a stop the runtime does not confirm (frozen, offline) stays latched on the server: the machine
  shows E-STOPPED in the API and the live state, throws and moves are refused, the stop reaches the
  runtime when it answers again or comes back online, and only a reset clears it; the latch
  survives a restart of the server.

Runs the app in the test process against FakeRuntime (tests/conftest.py) over loopback Zenoh.
"""

from __future__ import annotations

import socket
import sqlite3
import threading
import time

from server.db.models import AuditEntry
from tests.conftest import ADMIN, add_user, login, machine_key, wait_for
from tests.test_storage_faults import _fill, small_disk  # noqa: F401  (a fixture)

OPERATOR = ("op1", "operator-pass-1")
THROW = {"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]}


def _app(settings):
    from fastapi.testclient import TestClient

    from server.app import create_app

    return TestClient(create_app(settings))


def _machine(c, machine_id: str = "m1") -> dict | None:
    r = c.get("/api/machines")
    assert r.status_code == 200, r.text
    return next((m for m in r.json() if m["id"] == machine_id), None)


def _audited_aborts(sessions) -> list[dict]:
    from sqlalchemy import select

    with sessions() as db:
        return [e.detail | {"user": e.username} for e in db.scalars(select(AuditEntry).where(AuditEntry.action == "abort"))]


def test_estop_is_authorised_sent_and_listed_while_the_disk_is_full(settings, small_disk, fake_runtime_factory):  # noqa: F811
    data_dir = small_disk / "var"
    settings = settings.model_copy(update={"data_dir": data_dir, "database_url": f"sqlite:///{data_dir / 'slinger.db'}",
                                           "storage_min_free_bytes": 1 << 20})
    with _app(settings) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        rt = fake_runtime_factory(site_dir=settings.resolved_site_dir)
        wait_for(lambda: (m := _machine(c)) and m["online"] and m["ready"], 20, "m1 ready")
        filler = _fill(small_disk)
        try:
            assert c.get("/api/health").json()["condition"] == "disk_full"  # the fault is there
            r = c.post("/api/machines/m1/estop", json={"reason": "disk full drill"})
            assert r.status_code == 200, r.text  # before: 503 disk_full, the stop never sent
            assert rt.estop_reason is not None and "disk full drill" in rt.estop_reason
            m = _machine(c)  # before: 503
            assert m is not None and m["online"] and m["estop_latched"] is True, m
            wait_for(lambda: c.app.state.audit_backlog.pending() >= 1, 10, "the audit entry queued in memory")
        finally:
            filler.unlink()
        wait_for(lambda: c.app.state.audit_backlog.pending() == 0, 20, "audit backlog written")
        aborts = _audited_aborts(c.app.state.sessions)
        assert any(a["delivered"] and "disk full drill" in a["reason"] and a["user"] == ADMIN[0] for a in aborts), aborts


def _small_disk_settings(settings, small_disk):  # noqa: F811
    data_dir = small_disk / "var"
    return settings.model_copy(update={"data_dir": data_dir, "database_url": f"sqlite:///{data_dir / 'slinger.db'}",
                                       "storage_min_free_bytes": 1 << 20})


def _audited(sessions, action: str) -> list[dict]:
    from sqlalchemy import select

    with sessions() as db:
        return [e.detail | {"user": e.username} for e in db.scalars(select(AuditEntry).where(AuditEntry.action == action))]


def test_reset_return_to_ready_and_takeover_work_and_are_audited_while_the_disk_is_full(
        settings, small_disk, fake_runtime_factory):  # noqa: F811
    """A reset is a deliberate act that works during a storage fault as the stop does: the session
    from memory, the signed command sent, the audit entries in memory until the disk has room."""
    settings = _small_disk_settings(settings, small_disk)
    with _app(settings) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        rt = fake_runtime_factory(site_dir=settings.resolved_site_dir, lease_holder="srv-other")
        wait_for(lambda: (m := _machine(c)) and m["online"] and m["ready"], 20, "m1 ready")
        backlog = c.app.state.audit_backlog
        filler = _fill(small_disk)
        try:
            assert c.get("/api/health").json()["condition"] == "disk_full"  # the fault is there
            assert c.post("/api/machines/m1/estop", json={"reason": "reset drill"}).status_code == 200
            assert rt.estop_reason is not None
            r = c.post("/api/machines/m1/estop/reset")
            assert r.status_code == 200 and r.json()["reset"] is True, r.text  # before: 503 disk_full, latch kept
            assert rt.estop_reason is None
            r = c.post("/api/machines/m1/return-to-ready")
            assert r.status_code == 200 and r.json()["accepted"] is True, r.text  # before: 503
            assert len(rt.returns) == 1 and rt.returns[0].auth is not None and rt.returns[0].auth.user == ADMIN[0]
            r = c.post("/api/machines/m1/lease/takeover")
            assert r.status_code == 200 and r.json()["holder"] == c.app.state.fleet.signer.server_id, r.text
            wait_for(lambda: backlog.pending() >= 4, 10, "the four audit entries queued in memory")
        finally:
            filler.unlink()
        wait_for(lambda: backlog.pending() == 0, 20, "audit backlog written")
        sessions = c.app.state.sessions
        assert [(a["user"], a["delivered"], a["reset"]) for a in _audited(sessions, "estop_reset")] == [(ADMIN[0], True, True)]
        assert [(a["delivered"], a["accepted"]) for a in _audited(sessions, "return_to_ready")] == [(True, True)]
        assert [(a["delivered"], a["granted"]) for a in _audited(sessions, "lease_takeover")] == [(True, True)]


def test_a_session_from_before_a_restart_stops_and_resets_when_storage_fails_at_start(
        settings, small_disk, fake_runtime_factory):  # noqa: F811
    """The session mirror is on disk (server.accounts.session_file): a server restarted while its
    data disk is full (its first read of the sessions fails) authorises the sessions issued before
    the restart from the file; a token it never held still needs storage (503)."""
    from fastapi.testclient import TestClient

    from server.accounts.auth import COOKIE_NAME

    settings = _small_disk_settings(settings, small_disk)
    with _app(settings) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        token = c.cookies.get(COOKIE_NAME)
        assert token
    assert (settings.data_dir / "session_mirror.json").stat().st_mode & 0o077 == 0  # only the server reads it
    machine_key(settings.resolved_site_dir, "m1")  # the machine's command key, made before the disk fills
    filler = _fill(small_disk)
    try:
        with _app(settings) as c:  # restarted with the disk full: the sessions cannot be read
            assert c.app.state.session_mirror.from_file and not c.app.state.session_mirror.loaded
            c.headers["Authorization"] = f"Bearer {token}"
            rt = fake_runtime_factory(site_dir=settings.resolved_site_dir)
            wait_for(lambda: (m := _machine(c)) and m["online"] and m["ready"], 20, "m1 ready")  # before: 503
            r = c.post("/api/machines/m1/estop", json={"reason": "restart drill"})
            assert r.status_code == 200, r.text  # before: 503, the stop never sent
            assert rt.estop_reason is not None and "restart drill" in rt.estop_reason
            assert c.post("/api/machines/m1/estop/reset").status_code == 200
            assert rt.estop_reason is None
            stranger = TestClient(c.app, headers={"Authorization": "Bearer not-a-session-of-this-site"})
            assert stranger.post("/api/machines/m1/estop").status_code == 503  # unknown: storage must say
            assert rt.estop_reason is None
    finally:
        filler.unlink()


class _Relay:
    """A TCP relay from a local port to ``target`` that can be cut (every connection closed and
    new ones refused) and restored: PostgreSQL becoming unreachable."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.cut = False
        self._conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            if self.cut:
                client.close()
                continue
            upstream = socket.create_connection(self.target)
            self._conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            for s in (a, b):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def set_cut(self, cut: bool) -> None:
        self.cut = cut
        if cut:
            for s in self._conns:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            self._conns = []

    def close(self) -> None:
        self.set_cut(True)
        self.listener.close()


def test_estop_is_authorised_and_sent_while_postgresql_is_unreachable(settings, pg_url, fake_runtime_factory):
    relay = _Relay(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{relay.port}") + "?connect_timeout=2"
    settings = settings.model_copy(update={"database_url": url})
    try:
        with _app(settings) as c:
            add_user(c.app.state.sessions, *ADMIN, "admin")
            login(c, *ADMIN)
            rt = fake_runtime_factory()
            wait_for(lambda: (m := _machine(c)) and m["online"] and m["ready"], 20, "m1 ready")
            relay.set_cut(True)
            r = c.post("/api/machines/m1/estop", json={"reason": "database gone"})
            assert r.status_code == 200, r.text  # before: 503 database_unavailable, never sent
            assert rt.estop_reason is not None and "database gone" in rt.estop_reason
            m = _machine(c)
            assert m is not None and m["estop_latched"] is True, m
            relay.set_cut(False)
            wait_for(lambda: c.app.state.audit_backlog.pending() == 0, 30, "audit backlog written")
            assert any("database gone" in a["reason"] for a in _audited_aborts(c.app.state.sessions))
    finally:
        relay.close()


def test_a_disabled_or_deleted_accounts_session_cannot_stop(client, fake_runtime_factory, settings):
    from server.accounts.auth import create_user

    with client.app.state.sessions.begin() as db:
        create_user(db, *OPERATOR, "operator")
        create_user(db, "op2", "operator-pass-2", "operator")
    fake_runtime_factory()
    wait_for(lambda: (m := _machine(client)) and m["online"], 20, "m1 online")
    from fastapi.testclient import TestClient

    op1, op2 = TestClient(client.app), TestClient(client.app)
    login(op1, *OPERATOR)
    login(op2, "op2", "operator-pass-2")
    assert op1.post("/api/machines/m1/estop").status_code == 200
    assert client.post("/api/machines/m1/estop/reset").status_code == 200
    assert client.patch(f"/api/users/{OPERATOR[0]}", json={"active": False}).status_code == 200
    assert op1.post("/api/machines/m1/estop").status_code == 401  # refused at once, from memory
    con = sqlite3.connect(settings.data_dir / "slinger.db")  # another process deletes the account
    with con:
        con.execute("PRAGMA foreign_keys=ON")
        con.execute("DELETE FROM users WHERE username = 'op2'")
    con.close()
    # refused within the session mirror's refresh (server.accounts.auth.MIRROR_REFRESH_S)
    wait_for(lambda: op2.post("/api/machines/m1/estop").status_code == 401, 10, "the deleted account's stop refused")


def test_an_unconfirmed_estop_stays_latched_until_a_reset(client, fake_runtime_factory):
    rt = fake_runtime_factory()
    wait_for(lambda: (m := _machine(client)) and m["online"] and m["ready"], 20, "m1 ready")
    rt.frozen = True  # a stopped runtime: the stop is neither executed nor answered
    r = client.post("/api/machines/m1/estop", json={"reason": "frozen drill"})
    assert r.status_code == 503 and "latched" in r.json()["detail"], r.text
    m = _machine(client)
    assert m["estop_latched"] is True and m["ready"] is False and "NOT confirmed" in m["not_ready_reason"], m
    live = client.app.state.live.status("m1")
    assert live["state"] == "estopped" and "frozen drill" in live["estop_reason"], live  # before: "ready"
    refused = client.post("/api/throws", json=THROW)
    assert refused.status_code == 409 and "E-STOP" in refused.json()["detail"], refused.text
    assert client.post("/api/machines/m1/return-to-ready").status_code == 409
    assert rt.requests == []
    rt.frozen = False  # it wakes: the held stop reaches it
    wait_for(lambda: rt.estop_reason is not None, 10, "the held stop delivered")
    assert "frozen drill" in rt.estop_reason
    time.sleep(0.5)
    m = _machine(client)
    assert m["estop_latched"] is True and m["ready"] is False, m  # still pressed: only a reset clears it
    assert client.post("/api/machines/m1/estop/reset").status_code == 200
    sent = len(rt.aborts)
    m = wait_for(lambda: (m := _machine(client)) and m["ready"] and m, 10, "ready after the reset")
    assert m["estop_latched"] is False, m
    time.sleep(0.6)
    assert len(rt.aborts) == sent and rt.estop_reason is None  # no stop sent after the reset
    assert client.post("/api/throws", json=THROW).status_code == 202


def test_a_stop_pressed_while_offline_latches_the_runtime_that_comes_back_and_survives_a_server_restart(
        settings, fake_runtime_factory):
    with _app(settings) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        rt = fake_runtime_factory()
        wait_for(lambda: (m := _machine(c)) and m["online"] and m["ready"], 20, "m1 ready")
        rt.close()  # the runtime is gone
        wait_for(lambda: not _machine(c)["online"], 20, "m1 offline")
        r = c.post("/api/machines/m1/estop", json={"reason": "offline drill"})
        assert r.status_code == 503, r.text
        m = _machine(c)
        assert m["estop_latched"] is True and m["ready"] is False, m
        assert c.app.state.live.status("m1")["state"] == "estopped"
    with _app(settings) as c:  # the server restarted: the latch is read back
        login(c, *ADMIN)
        m = _machine(c)
        assert m is not None and m["estop_latched"] is True and "offline drill" in m["estop_reason"], m
        back = fake_runtime_factory()  # the runtime restarts (unlatched): the held stop reaches it
        wait_for(lambda: back.estop_reason is not None, 10, "the restarted runtime latched")
        wait_for(lambda: (m := _machine(c)) and m["online"], 20, "m1 online")
        for _ in range(5):  # never shown ready while the server holds the stop
            m = _machine(c)
            assert m["ready"] is False and m["estop_latched"] is True, m
            time.sleep(0.2)
        assert c.post("/api/machines/m1/estop/reset").status_code == 200
        wait_for(lambda: (m := _machine(c)) and m["ready"], 10, "ready after the reset")
    with _app(settings) as c:
        login(c, *ADMIN)
        assert c.app.state.fleet.estop_latch("m1") is None  # the reset is persisted too


def test_the_audit_backlog_keeps_order_and_time_until_storage_is_back(client):
    from server.site.storage import StorageFault

    backlog = client.app.state.audit_backlog
    storage = client.app.state.storage
    real = storage.before_use

    def failing() -> None:
        raise StorageFault("disk_full", "the disk is full")

    sessions = client.app.state.sessions
    sessions.kw["info"]["before_use"] = failing
    count = 3
    try:
        stamps = [time.time()]
        for i in range(count):
            assert backlog.record("op", "abort", f"m{i}", delivered=False) is False
            stamps.append(time.time())
            time.sleep(0.05)
        assert backlog.pending() == count and backlog.flush() is False
    finally:
        sessions.kw["info"]["before_use"] = real
    assert backlog.flush() is True and backlog.pending() == 0
    from sqlalchemy import select

    with sessions() as db:
        rows = list(db.scalars(select(AuditEntry).where(AuditEntry.action == "abort").order_by(AuditEntry.id)))
    assert [r.subject for r in rows] == [f"m{i}" for i in range(count)]
    for row, before, after in zip(rows, stamps, stamps[1:]):
        assert before <= row.at.timestamp() <= after  # the time of the event, not of the flush


def test_an_unwritable_latch_file_keeps_the_latch_in_memory(tmp_path):
    """The server's latch file cannot be written (its folder is a file): the latch holds in memory,
    the stop is still put, and the file is written once it can be; a new line reads it back."""
    from concurrent.futures import TimeoutError as FutureTimeout

    from server.fleet.estop import EstopLine, EstopUnconfirmed

    class Session:
        def __init__(self):
            self.puts: list[str] = []

        def put(self, key, payload, **_kw):
            self.puts.append(str(key))

    blocker = tmp_path / "var"
    blocker.write_text("not a folder")  # the data dir's place is taken: every write fails
    latch_file = blocker / "estop_latches.json"
    session = Session()
    line = EstopLine(session, lambda request, *_a: request, resend_s=0.02, deadline_s=0.1, relatch_s=0.05,
                     latch_file=latch_file)
    try:
        future = line.press("m1", "drill (op)", "op")
        try:
            future.result(timeout=5)
            raise AssertionError("an unanswered stop was confirmed")
        except EstopUnconfirmed:
            pass
        except FutureTimeout:
            raise AssertionError("the press never failed") from None
        assert line.latch("m1") is not None and line.latch("m1").reason == "drill (op)"
        wait_for(lambda: not line.latches_persisted, 5, "the failed write noticed")
        sent = len(session.puts)
        wait_for(lambda: len(session.puts) > sent + 3, 5, "the latched stop put again")
        blocker.unlink()
        wait_for(lambda: line.latches_persisted and latch_file.exists(), 10, "the latch file written once it can be")
    finally:
        line.close()
    again = EstopLine(Session(), lambda request, *_a: request, latch_file=latch_file)
    try:
        assert again.latch("m1") is not None and "drill" in again.latch("m1").reason
    finally:
        again.close()


def test_the_session_file_holds_unexpired_sessions_for_a_start_without_storage_and_fails_closed(tmp_path):
    """server.accounts.session_file with the mirror alone: the file's unexpired sessions are held when
    the first read fails, an expired one is not; a damaged file authorises nobody; space is reserved."""
    from datetime import timedelta

    from server.accounts.auth import SessionMirror, _digest
    from server.accounts.session_file import RESERVE_NAME, SessionFile
    from server.db.types import utcnow
    from server.site.storage import StorageFault

    def down():
        raise StorageFault("disk_full", "the disk is full")

    file = SessionFile(tmp_path / "session_mirror.json")
    now = utcnow()
    file.save({_digest("tok-ann"): (1, "ann", "operator", True, now, now + timedelta(hours=1)),
               _digest("tok-old"): (2, "old", "operator", True, now, now - timedelta(seconds=1))})
    assert (tmp_path / RESERVE_NAME).stat().st_size > 0
    mirror = SessionMirror(down, refresh_s=60.0, file=file)
    mirror.start()
    try:
        assert mirror.from_file and mirror.user("tok-ann").username == "ann"
        assert mirror.user("tok-old") is None and mirror.user("tok-bob") is None
    finally:
        mirror.stop()
    (tmp_path / "session_mirror.json").write_text("{damaged")
    mirror = SessionMirror(down, refresh_s=60.0, file=file)
    mirror.start()
    try:
        assert mirror.user("tok-ann") is None  # nothing authorised from a file that cannot be read
    finally:
        mirror.stop()
