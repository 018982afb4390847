"""Alembic migrations on SQLite and PostgreSQL: upgrade creates the schema the models describe
(no drift), UTC-aware timestamps round-trip, the sha256 uniqueness holds, downgrade removes all.

The PostgreSQL test (mark ``postgres``) creates a throwaway database on 127.0.0.1:5432, drops it
afterwards, and skips when the server is unreachable (fixture ``pg_url`` in tests/conftest.py).
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest
from alembic import command
from sqlalchemy import create_engine, inspect
from sqlalchemy.exc import IntegrityError, StatementError

from server.db.migrate import alembic_config, downgrade, upgrade
from server.db.models import Machine, PolicyVersion, Throw
from server.db.session import make_engine, make_sessionmaker

TABLES = {"machines", "policy_versions", "throws", "alembic_version"}


def _check_schema(url: str) -> None:
    upgrade(url)
    engine = make_engine(url)
    try:
        assert TABLES <= set(inspect(engine).get_table_names())
        cols = {c["name"] for c in inspect(engine).get_columns("throws")}
        assert {"downrange_error_m", "crossrange_error_m", "telemetry_path", "released_at"} <= cols
        # the migration and the models agree (alembic check raises on any drift)
        command.check(alembic_config(url))

        sessions = make_sessionmaker(engine)
        t0 = datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone(timedelta(hours=2)))
        with sessions.begin() as db:
            db.add(Machine(id="m1", simulated=True))
            db.add(Throw(id="t1", machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=-0.3,
                         target_z_m=0.0, requested_at=t0))
            db.add(PolicyVersion(name="p", mode="2d", sha256="a" * 64, manifest={"target_range_m": [5, 10]}))
        with sessions() as db:
            row = db.get(Throw, "t1")
            assert row.requested_at.tzinfo is not None and row.requested_at.utcoffset() == timedelta(0)
            assert row.requested_at == t0
            assert db.get(Machine, "m1").simulated is True
            assert db.query(PolicyVersion).one().manifest == {"target_range_m": [5, 10]}
        with pytest.raises(IntegrityError), sessions.begin() as db:
            db.add(PolicyVersion(name="q", mode="2d", sha256="a" * 64, manifest={}))
        with pytest.raises(StatementError, match="naive"), sessions.begin() as db:
            db.get(Throw, "t1").completed_at = datetime(2026, 1, 1)
        upgrade(url)  # idempotent at head
    finally:
        engine.dispose()
    downgrade(url, "base")
    engine = create_engine(url)
    try:
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
    finally:
        engine.dispose()


def test_migrations_on_sqlite(tmp_path):
    _check_schema(f"sqlite:///{tmp_path / 'nested' / 'slinger.db'}")


def test_sqlite_foreign_keys_are_enforced(tmp_path):
    url = f"sqlite:///{tmp_path / 's.db'}"
    upgrade(url)
    engine = make_engine(url)
    try:
        with pytest.raises(IntegrityError), make_sessionmaker(engine).begin() as db:
            db.add(Throw(id="t", machine_id="ghost", mode="2d", target_x_m=8, target_y_m=0, target_z_m=0))
    finally:
        engine.dispose()


@pytest.mark.postgres
def test_migrations_on_postgres(pg_url):
    _check_schema(pg_url)


def test_session_user_key_migration_keeps_live_sessions(tmp_path):
    """0008 gives every account a random key and copies it into the account's sessions (they stay
    valid); a session whose account is already gone is deleted."""
    from sqlalchemy import text

    url = f"sqlite:///{tmp_path / 's.db'}"
    upgrade(url, "0007")
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO users (id, username, password_hash, role, active, created_at) "
                          "VALUES (1, 'ann', 'x', 'admin', 1, '2026-01-01 00:00:00'), "
                          "(2, 'bob', 'x', 'viewer', 1, '2026-01-01 00:00:00')"))
        conn.execute(text("INSERT INTO auth_sessions (token_sha256, user_id, created_at, expires_at) VALUES "
                          "('a', 1, '2026-01-01', '2099-01-01'), ('b', 2, '2026-01-01', '2099-01-01'), "
                          "('c', 9, '2026-01-01', '2099-01-01')"))
    engine.dispose()
    upgrade(url)
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            keys = dict(conn.execute(text("SELECT id, session_key FROM users")).all())
            rows = dict(conn.execute(text("SELECT token_sha256, user_key FROM auth_sessions")).all())
    finally:
        engine.dispose()
    assert len(keys[1]) == 64 and keys[1] != keys[2]
    assert rows == {"a": keys[1], "b": keys[2]}
