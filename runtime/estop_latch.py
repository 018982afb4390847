"""The E-STOP latch on disk: it survives kill -9, a restart of the runtime and a power cycle of
its host until a deliberate signed reset (ISO 13850: the stop command is maintained until reset).

One small JSON file in the runtime's state directory (``<state-dir>/estop_latch.json``)::

    {"machine_id": "m1", "reason": "operator abort (alice)", "latched_unix_s": 1795000000.0}

Written atomically (a temporary file in the same directory, ``fsync``, ``os.replace``, ``fsync``
of the directory) before the runtime acknowledges the stop; removed (and the directory fsynced)
by a signed EstopReset. At start the runtime reads it: a latch file means E-STOP latched. A
file that cannot be read or parsed also means latched (fail safe), with the reason saying so.

A full disk does not keep the latch off it: RESERVE_BYTES are held in ``.estop_latch.reserve``
(made at start and after each reset, best effort); a latch write that fails gives the reserve
back and is written again.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from runtime.reserved_file import ReservedFile, fsync_dir

log = logging.getLogger(__name__)

FILE_NAME = "estop_latch.json"
RESERVE_NAME = ".estop_latch.reserve"
RESERVE_BYTES = 64 * 1024
"""Space held for the latch file on a full disk, bytes (a latch file is some 100 bytes; a file
system allocates whole blocks, and the temporary file and the directory entry need theirs)."""


class EstopLatchFile:
    """The durable E-STOP latch of one machine.

    Args:
        state_dir: the runtime's state directory (made if missing).
        machine_id: the machine (recorded in the file; a file of another machine counts as latched).

    Raises:
        OSError: the directory cannot be made.
    """

    def __init__(self, state_dir: str | Path, machine_id: str):
        self.dir = Path(state_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / FILE_NAME
        self.reserve = self.dir / RESERVE_NAME
        self.machine_id = machine_id
        self._file = ReservedFile(self.path, self.reserve, RESERVE_BYTES, "E-STOP latch")
        self._file.make_reserve()

    def load(self) -> str | None:
        """The latched reason at start, or None when no latch is on disk. An unreadable or
        malformed file, or one of another machine, is a latch too (its reason says why)."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as e:
            return f"E-STOP latch file unreadable ({e.strerror}): reset to release"
        try:
            data = json.loads(raw)
            reason, machine_id = str(data["reason"]), str(data["machine_id"])
        except (ValueError, KeyError, TypeError):
            return "E-STOP latch file malformed: reset to release"
        if machine_id != self.machine_id:
            return f"E-STOP latch file of machine {machine_id!r}: reset to release"
        return reason

    def write(self, reason: str, now_unix_s: float | None = None) -> None:
        """Persist the latch with ``reason`` (atomic replace, fsynced file and directory).

        Raises:
            OSError: it could not be written (disk full, read-only, ...); the previous file, if
                any, is left as it was.
        """
        data = {"machine_id": self.machine_id, "reason": reason,
                "latched_unix_s": time.time() if now_unix_s is None else now_unix_s}
        self._file.write(json.dumps(data).encode())

    def clear(self) -> None:
        """Remove the latch (after a signed reset); the directory is fsynced.

        Raises:
            OSError: it could not be removed (the latch then holds after a restart).
        """
        try:
            self.path.unlink()
        except FileNotFoundError:
            return
        fsync_dir(self.dir)
        self._file.make_reserve()
