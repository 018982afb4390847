"""A small file that reaches the disk even when the disk is full: written atomically (a temporary
file in the same directory, ``fsync``, ``os.replace``, ``fsync`` of the directory), with space held
in a reserve file beside it that a failed write gives back before it writes again.

Used by the runtime's E-STOP latch (runtime.estop_latch) and the server's session mirror
(server.accounts.session_file): both must be on disk when storage is full (docs/safety.md, rows
RT3 and S11).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)


def fsync_dir(directory: Path) -> None:
    """fsync ``directory`` so that a rename or removal in it survives a power cut.

    Raises:
        OSError: the directory cannot be opened or synced.
    """
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class ReservedFile:
    """One file written atomically, with ``reserve_bytes`` held for it in ``reserve``.

    Args:
        path: the file (its directory must exist when it is written).
        reserve: the reserve file, in the same file system (usually the same directory).
        reserve_bytes: space held, bytes (the file, its temporary copy and the directory entry
            must fit; file systems allocate whole blocks).
        what: the file's name in log messages, e.g. "E-STOP latch".
    """

    def __init__(self, path: Path, reserve: Path, reserve_bytes: int, what: str):
        self.path = path
        self.reserve = reserve
        self.reserve_bytes = reserve_bytes
        self.what = what

    def make_reserve(self) -> None:
        """Hold ``reserve_bytes`` in the reserve file if it is missing (best effort, logged)."""
        if self.reserve.exists():
            return
        try:
            fd = os.open(self.reserve, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                os.posix_fallocate(fd, 0, self.reserve_bytes)
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as e:
            self.reserve.unlink(missing_ok=True)
            log.warning("%s: no space reserved in %s (%s)", self.what, self.reserve.parent, e.strerror or e)

    def write(self, data: bytes) -> None:
        """Replace the file's content with ``data`` (mode 0600); a write that fails gives the
        reserve back and is tried once more. The reserve is not made again here
        (:meth:`make_reserve`).

        Raises:
            OSError: it could not be written even from the reserved space; the previous file is
                left as it was.
        """
        try:
            self._replace(data)
        except OSError as e:
            if not self.reserve.exists():
                raise
            self.reserve.unlink()
            log.error("%s: write failed (%s): written from the reserved space", self.what, e.strerror or e)
            self._replace(data)

    def _replace(self, data: bytes) -> None:
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
            fsync_dir(self.path.parent)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise
