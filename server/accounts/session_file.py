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
from datetime import datetime
from pathlib import Path

from runtime.reserved_file import ReservedFile

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
        self._file = ReservedFile(self.path, self.reserve, RESERVE_BYTES, "session mirror file")

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
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file.write(data)
        self._file.make_reserve()
