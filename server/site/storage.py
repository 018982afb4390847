"""Storage faults with clear answers: disk full, database locked, database unreadable or read-only.

The server keeps running through a storage fault: a request that meets one answers 503 with the
reason (``{"detail": sentence, "condition": name}`` and the ``X-Refused-Condition`` header) and
``GET /api/health`` names the fault until it is gone; nothing already stored is touched, and a
throw result that cannot be stored stays in the runtime's outbox (it is acknowledged only once
stored) until storage is back.

SQLite's shared-memory file (``<db>-shm``) is memory-mapped by every connection: if it becomes
immutable (``chattr +i``) or otherwise unwritable, SQLite's next write through the mapping, or the
close of the last connection, kills the process with SIGBUS (measured on Linux 6.18, SQLite
3.x: exit 135, no log line). So the files of a SQLite database are checked (:func:`check_files`)
before the engine opens a connection and before a session uses one; when they are not usable, no
connection is made or used (:class:`StorageFault` instead) and the pooled connections are left
alone (not even closed at shutdown), so that the process never writes through a mapping it
cannot write.

Conditions (``StorageFault.condition``):

- ``disk_full``: SQLite/PostgreSQL "disk is full", ENOSPC/EDQUOT, or less than
  ``min_free_bytes`` free in the database's folder;
- ``database_locked``: another process holds SQLite's write lock past the busy timeout;
- ``database_read_only``: a database file, its folder or its file system cannot be written
  (immutable, read-only mount);
- ``database_unreadable``: the file is not a SQLite database, is damaged, or cannot be opened;
- ``database_unavailable``: the database server cannot be reached (PostgreSQL).
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import Engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import DBAPIError, SQLAlchemyError

from server.errors import Unavailable

log = logging.getLogger(__name__)

SQLITE_HEADER = b"SQLite format 3\x00"
"""The first 16 bytes of every SQLite database file (https://sqlite.org/fileformat.html 1.3)."""
DEFAULT_MIN_FREE_BYTES = 8 << 20
RECENT_FAULT_S = 30.0
"""A fault met by a request is reported by /api/health for this long unless a check clears it."""


class StorageFault(Unavailable):
    """A storage fault; ``condition`` names it (module docstring), the message says what and why."""

    condition: str  # always set (DomainError's is optional)

    def __init__(self, condition: str, reason: str):
        super().__init__(reason, condition)
        self.reason = reason


@dataclass
class FaultState:
    condition: str
    reason: str
    since: float


def sqlite_file(database_url: str) -> Path | None:
    """The database file of a SQLite URL, None for other databases or in-memory SQLite."""
    url = make_url(database_url)
    if not url.drivername.startswith("sqlite") or not url.database or url.database == ":memory:":
        return None
    return Path(url.database)


def _writable(path: Path) -> str | None:
    """Why ``path`` (an existing file) cannot be written, else None, WITHOUT opening it: closing
    any descriptor of a file releases every POSIX lock this process holds on it, SQLite's included
    (sqlite.org "How To Corrupt An SQLite Database File", 2.2), so a check that opened the database,
    its ``-wal`` or ``-shm`` while SQLite has them open would break SQLite's locking. ``access``
    (Linux ``inode_permission``) refuses writing an immutable or append-only file even for root."""
    if os.access(path, os.W_OK):
        return None
    if os.geteuid() == 0:  # root passes the permission bits: only the file's flags refuse it
        return f"{path.name} is immutable or append-only (chattr +i/+a): {os.strerror(errno.EPERM)}"
    return f"{path.name} cannot be written: {os.strerror(errno.EACCES)}"


def check_files(db_file: Path, min_free_bytes: int = DEFAULT_MIN_FREE_BYTES, read_header: bool = True) -> StorageFault | None:
    """Check a SQLite database's folder, file, ``-wal`` and ``-shm`` without opening it with SQLite.

    Args:
        db_file: the database file (it may not exist yet: then only its folder is checked).
        min_free_bytes: less free space than this in the folder is ``disk_full``.
        read_header: also read the file's first bytes (the SQLite header). Only while this process
            has no SQLite connection to the file: closing the descriptor of that read would release
            SQLite's POSIX locks (see :func:`_writable`).

    Returns:
        The fault found, or None when the files are usable.
    """
    folder = db_file.parent
    if folder.exists():
        if not os.access(folder, os.W_OK | os.X_OK):
            return StorageFault("database_read_only", f"the database folder {folder} cannot be written")
        try:
            free = shutil.disk_usage(folder).free
        except OSError as e:
            return StorageFault("database_unreadable", f"the database folder {folder} cannot be read: {e.strerror}")
        if free < min_free_bytes:
            return StorageFault("disk_full", f"the disk of {folder} is full ({free / 2**20:.1f} MiB free, "
                                             f"{min_free_bytes / 2**20:.0f} MiB needed)")
    if read_header and db_file.exists():
        try:
            with open(db_file, "rb") as f:
                header = f.read(len(SQLITE_HEADER))
        except OSError as e:
            return StorageFault("database_unreadable", f"the database file {db_file} cannot be read: {e.strerror}")
        if header and header != SQLITE_HEADER:
            return StorageFault("database_unreadable", f"{db_file} is not a SQLite database (damaged or replaced)")
    for suffix in ("", "-wal", "-shm"):
        path = db_file.with_name(db_file.name + suffix)
        if path.exists():
            if not path.is_file():
                return StorageFault("database_unreadable", f"{path} is not a regular file")
            why = _writable(path)
            if why is not None:
                return StorageFault("database_read_only", f"database file {why}")
    return None


def classify(exc: BaseException) -> StorageFault | None:
    """The storage fault behind an exception, or None if it is not one.

    SQLAlchemy errors are judged by the driver's message (SQLite result codes SQLITE_BUSY,
    SQLITE_FULL, SQLITE_READONLY, SQLITE_NOTADB, SQLITE_CORRUPT, SQLITE_CANTOPEN, SQLITE_IOERR;
    PostgreSQL's "could not extend file ... No space left on device"); OSError by errno.
    """
    if isinstance(exc, StorageFault):
        return exc
    if isinstance(exc, OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return StorageFault("disk_full", f"the disk is full: {exc.strerror}")
        if exc.errno == errno.EROFS:
            return StorageFault("database_read_only", f"the file system is read-only: {exc.strerror}")
        return None
    if not isinstance(exc, (SQLAlchemyError, sqlite3.Error)):
        return None
    orig = exc.orig if isinstance(exc, DBAPIError) else exc
    text = str(orig).lower()
    if "locked" in text or "database is busy" in text:
        return StorageFault("database_locked", "the database is locked by another process (its write lock was held "
                                               "past the wait); try again shortly")
    if "disk is full" in text or "no space left" in text or "disk full" in text:
        return StorageFault("disk_full", "the disk of the database is full: free space, then try again")
    if "readonly" in text or "read-only" in text:
        return StorageFault("database_read_only", "the database cannot be written (read-only file, folder or mount)")
    if any(s in text for s in ("not a database", "malformed", "unable to open", "disk i/o error", "corrupt")):
        return StorageFault("database_unreadable", f"the database cannot be read: {orig}")
    if isinstance(exc, DBAPIError) and exc.connection_invalidated or "connection" in text and "refused" in text:
        return StorageFault("database_unavailable", f"the database server cannot be reached: {orig}")
    return None


class StorageMonitor:
    """The storage state of one server process: checks the SQLite files, guards the engine, and
    remembers the last fault a request met.

    Args:
        database_url: the server's database URL.
        min_free_bytes: see :func:`check_files`.
        probe_timeout_s: how long :meth:`check` waits for SQLite's write lock, s.
    """

    def __init__(self, database_url: str, min_free_bytes: int = DEFAULT_MIN_FREE_BYTES, probe_timeout_s: float = 0.5):
        self.db_file = sqlite_file(database_url)
        self.min_free_bytes = min_free_bytes
        self.probe_timeout_s = probe_timeout_s
        self._recent: FaultState | None = None
        self._files: FaultState | None = None
        self._lock = threading.Lock()
        self._open: dict[int, object] = {}

    def check_files(self) -> StorageFault | None:
        """:func:`check_files` for a SQLite database (None for others); remembers the result."""
        with self._lock:
            connected = bool(self._open)
        fault = (check_files(self.db_file, self.min_free_bytes, read_header=not connected)
                 if self.db_file is not None else None)
        with self._lock:
            if fault is None:
                if self._files is not None:
                    log.warning("storage fault cleared: %s", self._files.reason)
                self._files = None
            elif self._files is None or self._files.reason != fault.reason:
                log.error("storage fault (%s): %s", fault.condition, fault.reason)
                self._files = FaultState(fault.condition, fault.reason, time.time())
        return fault

    def report(self, fault: StorageFault) -> None:
        """Remember a fault a request met (shown by :meth:`fault` for RECENT_FAULT_S)."""
        with self._lock:
            self._recent = FaultState(fault.condition, fault.reason, time.time())
        log.error("storage fault (%s): %s", fault.condition, fault.reason)

    def check(self) -> StorageFault | None:
        """The current fault, checking now: the files, then (SQLite, files fine) a connection of
        its own that reads the schema and takes the write lock for a moment (waiting at most
        ``probe_timeout_s``). A passing check clears a remembered request fault."""
        fault = self.check_files()
        if fault is None and self.db_file is not None and self.db_file.exists():
            try:
                con = sqlite3.connect(self.db_file, timeout=self.probe_timeout_s)
                try:
                    con.execute("SELECT count(*) FROM sqlite_master").fetchone()
                    con.execute("BEGIN IMMEDIATE")
                    con.execute("ROLLBACK")
                finally:
                    con.close()
            except sqlite3.Error as e:
                fault = classify(e) or StorageFault("database_unreadable", f"the database cannot be used: {e}")
        with self._lock:
            if fault is None:
                self._recent = None
            elif self._files is None:
                self._recent = FaultState(fault.condition, fault.reason, time.time())
        return fault

    def fault(self) -> FaultState | None:
        """The fault to report now: the files' (checked last), else one a request met recently."""
        with self._lock:
            if self._files is not None:
                return self._files
            if self._recent is not None and time.time() - self._recent.since < RECENT_FAULT_S:
                return self._recent
            return None

    def before_use(self) -> None:
        """Check the SQLite files (nothing for other databases).

        Raises:
            StorageFault: they are not usable.
        """
        if self.db_file is not None:
            fault = self.check_files()
            if fault is not None:
                raise fault

    def guard(self, engine: Engine) -> None:
        """Check the SQLite files before the engine opens a new connection (a fault raises
        :class:`StorageFault` before SQLite touches them). Pass :meth:`before_use` to
        server.db.session.make_sessionmaker to check before each use of a pooled connection as
        well; a check inside the pool's checkout would close the connection on failure, and
        closing is what crashes with an unwritable ``-shm``."""
        if self.db_file is not None:
            event.listen(engine, "do_connect", lambda *_args: self.before_use())
            event.listen(engine, "connect", lambda conn, _rec: self._open.__setitem__(id(conn), conn))
            event.listen(engine, "close", lambda conn, _rec: self._open.pop(id(conn), None))

    def release(self, engine: Engine) -> None:
        """At shutdown: dispose the engine if the SQLite files are usable; else never close its
        connections (closing checkpoints through the unwritable ``-shm`` mapping: SIGBUS) and keep
        them from being closed when the interpreter exits. Committed data is in the database or
        its WAL either way; SQLite recovers the WAL at the next open."""
        if self.db_file is None or self.check_files() is None:
            engine.dispose()
            return
        import ctypes

        for conn in list(self._open.values()):
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(conn))  # never deallocated: never closed
        fault = self.fault()
        log.error("database connections left open at exit: %s", fault.reason if fault is not None else "")

    @property
    def files_ok(self) -> bool:
        """False while the last file check found a fault (then the engine must not be disposed:
        closing a connection whose ``-shm`` cannot be written is what kills the process)."""
        with self._lock:
            return self._files is None


def storage_response(condition: str, reason: str, **extra):
    """The 503 answer of a storage fault: ``{"detail": reason, "condition": condition, **extra}``
    with ``X-Refused-Condition: <condition>`` and ``Retry-After: 5``."""
    from fastapi.responses import JSONResponse

    return JSONResponse(status_code=503, content={"detail": reason, "condition": condition, **extra},
                        headers={"X-Refused-Condition": condition, "Retry-After": "5"})
