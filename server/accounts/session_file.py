"""The session mirror on disk: the valid sessions the server last read, so that an E-STOP (and a
reset) with a session issued before a restart is authorised even when storage fails before the
restarted server's first read (docs/safety.md, row S11).

One small JSON file in the data directory beside the E-STOP latches
(``<data_dir>/session_mirror.json``, mode 0600), a list of::

    {"sha256": "<token SHA-256, hex>", "user_id": 3, "username": "alice", "role": "operator",
     "created_at": "2026-11-26T01:00:00+00:00", "expires_at": "2026-11-26T13:00:00+00:00"}

It holds what the database holds (the tokens' SHA-256, never a token) for the active accounts
only. :class:`server.accounts.auth.SessionMirror` writes it after each read that changed what it
holds and reads it at start only when the database cannot be read; the first successful read
replaces it. Written atomically (a temporary file in the same directory, ``fsync``,
``os.replace``, ``fsync`` of the directory). A full disk does not keep it off the disk:
RESERVE_BYTES are held in ``.session_mirror.reserve`` (best effort, as the runtime's E-STOP latch:
runtime.estop_latch); a write that fails gives the reserve back and is tried again.
"""

from __future__ import annotations

import json
import logging
import os
from datetime import datetime
from pathlib import Path

log = logging.getLogger(__name__)

FILE_NAME = "session_mirror.json"
RESERVE_NAME = ".session_mirror.reserve"
RESERVE_BYTES = 256 * 1024
"""Space held for the file on a full disk, bytes: some 250 bytes per session, so about 1 000
sessions (the file system allocates whole blocks; the temporary file needs its own)."""

Entry = tuple[int, str, str, bool, datetime, datetime]
"""(user id, user name, role, active, account created at, session expires at): one session."""


class SessionFile:
    """The session mirror's file.

    Args:
        path: the file (its folder is made when written).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.reserve = self.path.with_name(RESERVE_NAME)

    def load(self) -> dict[str, Entry]:
        """token SHA-256 -> :data:`Entry` as last written, {} when there is no file. A file that
        cannot be read or parsed gives {} (logged): no session is authorised from it."""
        try:
            rows = json.loads(self.path.read_bytes())
            return {str(r["sha256"]): (int(r["user_id"]), str(r["username"]), str(r["role"]), True,
                                       datetime.fromisoformat(r["created_at"]), datetime.fromisoformat(r["expires_at"]))
                    for r in rows}
        except FileNotFoundError:
            return {}
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("session mirror file %s not read (%s): sessions from before the restart need storage", self.path, e)
            return {}

    def save(self, entries: dict[str, Entry]) -> None:
        """Write ``entries`` (the active accounts' only), replacing the file atomically.

        Raises:
            OSError: it could not be written even from the reserved space; the previous file is
                left as it was.
        """
        rows = [{"sha256": digest, "user_id": uid, "username": name, "role": role,
                 "created_at": created.isoformat(), "expires_at": expires.isoformat()}
                for digest, (uid, name, role, active, created, expires) in sorted(entries.items()) if active]
        data = json.dumps(rows, indent=0).encode()
        try:
            self._write(data)
        except OSError as e:
            if not self.reserve.exists():
                raise
            self.reserve.unlink()
            log.error("session mirror file: write failed (%s): written from the reserved space", e.strerror or e)
            self._write(data)
        self._make_reserve()

    def _write(self, data: bytes) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{FILE_NAME}.{os.getpid()}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
            dfd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise

    def _make_reserve(self) -> None:
        """Hold RESERVE_BYTES in the reserve file if it is missing (best effort, logged)."""
        if self.reserve.exists():
            return
        try:
            fd = os.open(self.reserve, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                os.posix_fallocate(fd, 0, RESERVE_BYTES)
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as e:
            self.reserve.unlink(missing_ok=True)
            log.warning("session mirror file: no space reserved in %s (%s)", self.path.parent, e.strerror or e)
