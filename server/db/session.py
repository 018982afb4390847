"""Engine and session factory, built from settings by ``server.services.build_services`` (never at
import), and the typed row count of an executed UPDATE or DELETE."""

from __future__ import annotations

import logging
import math
from typing import cast

from sqlalchemy import CursorResult, Engine, Result, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

import server.db.aggregates  # noqa: F401  (registers the listener that keeps the accuracy aggregates)

log = logging.getLogger(__name__)

SQLITE_JOURNAL_MODE = "TRUNCATE"
"""SQLite's journal: a rollback journal (https://sqlite.org/pragma.html#pragma_journal_mode), not
WAL. WAL keeps its index in ``<db>-shm``, a file every connection maps into memory: if that file
becomes unwritable (immutable, its disk gone) while a write is under way, the next store through
the mapping kills the process with SIGBUS, whatever checks ran before. A rollback journal is
written and read with plain system calls, so every storage fault is an error the server can
answer (server.site.storage), and it keeps the locking of several processes on one file (the server,
its job workers and ``slinger user``; unlike WAL with ``locking_mode=EXCLUSIVE``, which would
leave one process alone). Its cost: a write waits for running reads to end (the busy timeout)."""

SQLITE_CACHE_KIB = 512
"""Bound of each SQLite connection's page cache, KiB (``PRAGMA cache_size`` negative: KiB, not
pages; SQLite's default is 2000 KiB, https://sqlite.org/pragma.html#pragma_cache_size). The pool
keeps up to 5 connections open (SQLAlchemy's QueuePool for a file database; up to 10 more are
opened under load and closed when returned), and a rollback journal empties a connection's cache
whenever another connection has written, so a large cache buys little: in a 43-minute soak the
server's SQLite memory grew 2.2 -> 5.3 MiB as its pooled connections filled their 2 MiB caches
(reports/soak_43min, archived: reports/ARCHIVE.md). With 512 KiB the page caches of the pooled
connections stay under 2.5 MiB together; the server's SQLite memory stayed at 1.5-3.2 MiB over a
66-minute soak (reports/soak_60min)."""


def rowcount(result: Result) -> int:
    """Rows an UPDATE or DELETE matched (``Session.execute`` types its result as a plain
    ``Result``; for those statements it is a ``CursorResult``)."""
    return cast(CursorResult, result).rowcount


def make_engine(database_url: str, busy_timeout_s: float = 10.0) -> Engine:
    """An engine for ``database_url``.

    SQLite: allow use from Zenoh callback threads and FastAPI's threadpool, enable foreign keys,
    use the rollback journal of :data:`SQLITE_JOURNAL_MODE` and no memory-mapped I/O
    (``mmap_size=0``: no file of the database is mapped, so a storage fault is an error, never a
    SIGBUS), bound each connection's page cache to :data:`SQLITE_CACHE_KIB`, wait up to ``busy_timeout_s`` on a locked database instead of failing at once (then
    "database is locked": server.site.storage answers 503), and provide
    ``sqrt`` and ``floor`` where the SQLite build lacks its math functions (server.analysis.accuracy
    uses them).
    """
    if database_url.startswith("sqlite"):
        engine = create_engine(
            database_url, connect_args={"check_same_thread": False, "timeout": busy_timeout_s}
        )

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA mmap_size=0")
            cur.execute(f"PRAGMA cache_size=-{SQLITE_CACHE_KIB}")
            mode = cur.execute(f"PRAGMA journal_mode={SQLITE_JOURNAL_MODE}").fetchone()
            if mode is None or str(mode[0]).upper() != SQLITE_JOURNAL_MODE:  # WAL left by another process still open
                log.warning("SQLite journal mode is %s, not %s (another connection holds the database)",
                            mode[0] if mode else "unknown", SQLITE_JOURNAL_MODE)
            try:
                cur.execute("SELECT sqrt(1.0)")
            except Exception:  # noqa: BLE001  sqlite3.OperationalError: no such function
                dbapi_conn.create_function("sqrt", 1, lambda x: None if x is None else math.sqrt(x), deterministic=True)
                dbapi_conn.create_function("floor", 1, lambda x: None if x is None else math.floor(x),
                                           deterministic=True)
            cur.close()

        return engine
    return create_engine(database_url, pool_pre_ping=True)


class CheckedSession(Session):
    """A session that calls ``info["before_use"]()`` (if set) each time it is about to use a
    connection (SQLAlchemy asks :meth:`get_bind` before every statement and flush), i.e. before a
    pooled connection is checked out: server.site.storage refuses there while the database's files
    are unusable, so no connection is touched (a pool checkout that fails closes its connection,
    which is what must not happen with an unwritable ``-shm``)."""

    def get_bind(self, *args, **kwargs):
        before_use = self.info.get("before_use")
        if before_use is not None:
            before_use()
        return super().get_bind(*args, **kwargs)


def make_sessionmaker(engine: Engine, before_use=None) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (rows are read after commit).

    Args:
        before_use: called before each use of a connection; may raise to refuse it
            (:class:`CheckedSession`).
    """
    return sessionmaker(engine, class_=CheckedSession, expire_on_commit=False,
                        info={"before_use": before_use} if before_use is not None else None)
