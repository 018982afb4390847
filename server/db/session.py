"""Engine and session factory, built from settings inside ``create_app`` (never at import)."""

from __future__ import annotations

import math

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

import server.db.aggregates  # noqa: F401  (registers the listener that keeps the accuracy aggregates)


def make_engine(database_url: str) -> Engine:
    """An engine for ``database_url``.

    SQLite: allow use from Zenoh callback threads and FastAPI's threadpool, enable foreign keys
    and WAL, wait up to 10 s on a locked database instead of failing at once, and provide
    ``sqrt`` and ``floor`` where the SQLite build lacks its math functions (server.accuracy
    uses them).
    """
    if database_url.startswith("sqlite"):
        engine = create_engine(
            database_url, connect_args={"check_same_thread": False, "timeout": 10.0}
        )

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA journal_mode=WAL")
            try:
                cur.execute("SELECT sqrt(1.0)")
            except Exception:  # noqa: BLE001  sqlite3.OperationalError: no such function
                dbapi_conn.create_function("sqrt", 1, lambda x: None if x is None else math.sqrt(x), deterministic=True)
                dbapi_conn.create_function("floor", 1, lambda x: None if x is None else math.floor(x),
                                           deterministic=True)
            cur.close()

        return engine
    return create_engine(database_url, pool_pre_ping=True)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (rows are read after commit)."""
    return sessionmaker(engine, expire_on_commit=False)
