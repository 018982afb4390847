"""Storage faults with clear answers (issue 24 finding 5): a held write lock, a full disk (a small
tmpfs), a damaged database file and an immutable ``-shm`` file each give 503 with the condition
and the reason, /api/health names them, the server keeps running (no SIGBUS), and what was stored
before is still there when the fault is gone.

Needs root for ``mount -t tmpfs`` and ``chattr +i`` (skipped without).
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from server.db.migrate import upgrade
from tests.conftest import ADMIN, add_user

LOGIN = {"username": ADMIN[0], "password": ADMIN[1]}


def _client(settings, **overrides):
    from fastapi.testclient import TestClient

    from server.app import create_app

    return TestClient(create_app(settings.model_copy(update=overrides)))


def _assert_fault(r, condition: str, words: str) -> None:
    assert r.status_code == 503, r.text
    body = r.json()
    assert body["condition"] == condition and r.headers["x-refused-condition"] == condition, body
    assert words in body["detail"], body


def test_held_write_lock_is_503_database_locked_then_recovers(settings):
    with _client(settings, database_busy_timeout_s=0.5) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        holder = sqlite3.connect(settings.data_dir / "slinger.db", isolation_level=None)
        holder.execute("BEGIN IMMEDIATE")  # another process holds the write lock
        try:
            _assert_fault(c.post("/api/auth/login", json=LOGIN), "database_locked", "locked by another process")
            _assert_fault(c.get("/api/health"), "database_locked", "locked")
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        assert c.get("/api/health").status_code == 200
        assert c.post("/api/auth/login", json=LOGIN).status_code == 200


@pytest.fixture
def small_disk(tmp_path):
    """A 24 MiB tmpfs (root only); unmounted afterwards."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mnt)]).returncode:
        pytest.skip("needs root to mount a tmpfs")
    try:
        yield mnt
    finally:
        if subprocess.run(["umount", str(mnt)]).returncode:
            subprocess.run(["umount", "-l", str(mnt)])


def _fill(folder: Path) -> Path:
    """Write a file until the disk is full; returns it. Unbuffered: a buffered file would try to write
    its rest again at close and raise ENOSPC there, outside the loop that expects it."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * (1 << 16))
        except OSError:
            pass
    return filler


def test_full_disk_is_503_disk_full_and_nothing_is_lost(settings, small_disk):
    data_dir = small_disk / "var"
    settings = settings.model_copy(update={"data_dir": data_dir, "database_url": f"sqlite:///{data_dir / 'slinger.db'}",
                                           "storage_min_free_bytes": 1 << 20})
    with _client(settings) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        assert c.post("/api/auth/login", json=LOGIN).status_code == 200
        filler = _fill(small_disk)
        try:
            _assert_fault(c.get("/api/health"), "disk_full", "full")
            codes = set()
            for _ in range(60):  # log-ins write rows; SQLite fails once its WAL must grow
                r = c.post("/api/auth/login", json=LOGIN)
                codes.add(r.status_code)
                if r.status_code == 503:
                    _assert_fault(r, "disk_full", "full")
                    break
            assert 503 in codes and codes <= {200, 503}, codes
        finally:
            filler.unlink()
        assert c.get("/api/health").status_code == 200
        assert c.post("/api/auth/login", json=LOGIN).status_code == 200
        assert c.get("/api/auth/me").json()["username"] == ADMIN[0]  # the account written before is intact


def test_damaged_database_file_starts_in_a_fault_state(settings):
    settings.data_dir.mkdir(parents=True)
    (settings.data_dir / "slinger.db").write_bytes(b"this is not a database" * 100)
    with _client(settings) as c:  # before: the start-up migration raised and the server did not start
        _assert_fault(c.get("/api/health"), "database_unreadable", "not a SQLite database")
        _assert_fault(c.post("/api/auth/login", json=LOGIN), "database_unreadable", "not a SQLite database")


CHILD = r"""
import json, sys
from argon2 import PasswordHasher
import server.accounts.auth
server.accounts.auth._hasher = PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1)
from fastapi.testclient import TestClient
from server.app import create_app
from server.config import Settings
args = json.loads(sys.argv[1])
settings = Settings(data_dir=args["data_dir"], zenoh_listen=[args["zenoh"]], viser_enabled=False, auto_migrate=True,
                    require_preview=False, job_queue_url="immediate", query_timeout_s=2.0)
out = []
with TestClient(create_app(settings)) as c:
    def call(method, path, **kw):
        r = c.request(method, path, **kw)
        out.append([path, r.status_code, r.json().get("condition"), r.json().get("detail")])
    call("GET", "/api/health")
    call("POST", "/api/auth/login", json={"username": "admin", "password": "admin-pass-1"})
    if args.get("freeze_shm"):
        import subprocess
        subprocess.run(["chattr", "+i", args["freeze_shm"]], check=True)  # while the server runs
        call("POST", "/api/auth/login", json={"username": "admin", "password": "admin-pass-1"})
        call("GET", "/api/health")
print("RESULT " + json.dumps(out), flush=True)
"""


def _serve_once(settings, zenoh_endpoint, **extra) -> tuple[int, list]:
    """Start the app in a child process, make a few requests, stop it: (exit status, answers)."""
    args = {"data_dir": str(settings.data_dir), "zenoh": zenoh_endpoint, **extra}
    p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    line = next((ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")), None)
    return p.returncode, json.loads(line[7:]) if line else p.stderr[-3000:]


def _chattr(flag: str, path: Path) -> None:
    if os.geteuid() != 0 or not shutil.which("chattr"):
        pytest.skip("needs root and chattr")
    if subprocess.run(["chattr", flag, str(path)]).returncode:
        pytest.skip(f"chattr {flag} not supported here")


def test_immutable_shm_file_gives_a_fault_state_not_a_sigbus(settings, zenoh_endpoint):
    db = settings.data_dir / "slinger.db"
    upgrade(f"sqlite:///{db}")
    with sqlite3.connect(db) as con:
        con.execute("PRAGMA journal_mode=WAL")
    add_user_direct(db)
    shm = db.with_name("slinger.db-shm")
    shm.write_bytes(b"\0" * 32768)  # what a crashed process leaves; then made immutable
    _chattr("+i", shm)
    try:
        rc, out = _serve_once(settings, zenoh_endpoint)
    finally:
        _chattr("-i", shm)
    assert rc == 0, out  # before: the server died (SIGBUS, exit 135) or did not start
    assert [o[:3] for o in out] == [["/api/health", 503, "database_read_only"],
                                    ["/api/auth/login", 503, "database_read_only"]], out
    assert "slinger.db-shm is immutable" in out[0][3]
    rc, out = _serve_once(settings, zenoh_endpoint)  # the fault removed: all is as before
    assert rc == 0 and [o[1] for o in out] == [200, 200], out


def test_database_made_immutable_while_serving_is_503_not_a_sigbus(settings, zenoh_endpoint):
    """The database file made immutable between requests: the next write is refused with the
    condition. There is no memory-mapped ``-shm`` to die through (a rollback journal, not WAL:
    server.db.session.SQLITE_JOURNAL_MODE)."""
    db = settings.data_dir / "slinger.db"
    upgrade(f"sqlite:///{db}")
    add_user_direct(db)
    if os.geteuid() != 0 or not shutil.which("chattr"):
        pytest.skip("needs root and chattr")
    try:
        rc, out = _serve_once(settings, zenoh_endpoint, freeze_shm=str(db))
    finally:
        subprocess.run(["chattr", "-i", str(db)])
    assert rc == 0, out  # before: SIGBUS at the next write (exit 135)
    assert [o[:3] for o in out] == [["/api/health", 200, None], ["/api/auth/login", 200, None],
                                    ["/api/auth/login", 503, "database_read_only"],
                                    ["/api/health", 503, "database_read_only"]], out
    assert not db.with_name("slinger.db-shm").exists()


def add_user_direct(db: Path) -> None:
    """The fixtures' admin, written with the server's own code into the database file ``db``."""
    from server.db.session import make_engine, make_sessionmaker

    engine = make_engine(f"sqlite:///{db}")
    try:
        add_user(make_sessionmaker(engine), *ADMIN, "admin")
    finally:
        engine.dispose()


def test_storage_checks_keep_sqlite_locks(tmp_path):
    """Checking the files must not release SQLite's locks: closing any descriptor of a file drops
    every POSIX lock the process holds on it. While this process holds the write lock, another
    process must still find the database locked after a check."""
    import sqlite3
    import subprocess
    import sys

    from server.site.storage import StorageMonitor

    db = tmp_path / "x.db"
    conn = sqlite3.connect(db, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("CREATE TABLE t (x)")
    conn.execute("BEGIN IMMEDIATE")
    conn.execute("INSERT INTO t VALUES (1)")
    try:
        monitor = StorageMonitor(f"sqlite:///{db}", 0)
        monitor._open[id(conn)] = conn  # noqa: SLF001  as the engine's connect event records it
        assert monitor.check_files() is None
        other = subprocess.run([sys.executable, "-c", "import sqlite3, sys; c = sqlite3.connect(sys.argv[1], timeout=0.2); "
                                "c.execute('BEGIN IMMEDIATE')", str(db)], capture_output=True, text=True, timeout=60)
        assert other.returncode != 0 and "locked" in other.stderr, other
    finally:
        conn.execute("ROLLBACK")
        conn.close()


MID_WRITE = r"""
import json, os, subprocess, sys
from argon2 import PasswordHasher
import server.accounts.auth
server.accounts.auth._hasher = PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1)
from fastapi.testclient import TestClient
from server.app import create_app
from server.accounts.auth import audit
from server.config import Settings
args = json.loads(sys.argv[1])
settings = Settings(data_dir=args["data_dir"], zenoh_listen=[args["zenoh"]], viser_enabled=False, auto_migrate=True,
                    require_preview=False, job_queue_url="immediate", query_timeout_s=2.0)
db = os.path.join(args["data_dir"], "slinger.db")
files = lambda: [db + s for s in ("", "-wal", "-shm", "-journal") if os.path.exists(db + s)]
out = []
with TestClient(create_app(settings)) as c:
    for i in range(3):
        try:
            with c.app.state.sessions.begin() as s:
                for k in range(200):
                    audit(s, "system", "probe", f"row{i}-{k}", pad="x" * 2000)
                s.flush()  # the write is under way, past every check before it
                subprocess.run(["chattr", "+i", *files()], check=True)
            out.append("committed")
        except Exception as e:
            out.append(type(e).__name__)
        finally:
            subprocess.run(["chattr", "-i", *files()])
        out.append(c.get("/api/health").status_code)
print("RESULT " + json.dumps(out), flush=True)
"""


def test_database_files_made_immutable_mid_write_give_an_error_not_a_sigbus(settings, zenoh_endpoint):
    """The database's files made immutable while a write transaction is under way (its rows
    flushed, the commit next): the commit fails with an error and the server answers on; before,
    the WAL index's memory-mapped ``-shm`` killed the process with SIGBUS (exit 135) at the commit
    (server.db.session.SQLITE_JOURNAL_MODE)."""
    if os.geteuid() != 0 or not shutil.which("chattr"):
        pytest.skip("needs root and chattr")
    settings.data_dir.mkdir(parents=True)
    args = {"data_dir": str(settings.data_dir), "zenoh": zenoh_endpoint}
    try:
        p = subprocess.run([sys.executable, "-c", MID_WRITE, json.dumps(args)], capture_output=True, text=True,
                           timeout=180, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    finally:
        for f in settings.data_dir.glob("slinger.db*"):
            subprocess.run(["chattr", "-i", str(f)])
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])  # before: -7 / 135, a bus error
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT "))
    out = json.loads(line[7:])
    assert out[1::2] == [200, 200, 200], out  # storage healthy again after each fault
    assert all(o != "committed" for o in out[0::2]), out  # the write failed with an error instead
