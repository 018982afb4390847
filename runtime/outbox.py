"""Durable outbox: no throw result is lost while the server is away.

Each finished ThrowResult is written as one JSON file in a directory (atomically: temporary
file, fsync, rename) before any delivery is tried. A deliverer sends it to the server (Zenoh
query to keys.THROW_RESULT; the server's queryable replies a ResultAck); the file is deleted only
on ``ResultAck(throw_id=<same>, stored=True)``. Undelivered files are retried every
``retry_interval_s`` and survive a runtime restart. Files that no longer parse as a ThrowResult
are renamed ``*.bad`` and skipped.

The deliverer is injectable (``Callable[[bytes], ResultAck | None]``) so the outbox is tested
without Zenoh; :func:`zenoh_deliverer` is the production one.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

from runtime.protocol import keys
from runtime.protocol.messages import ResultAck, ThrowResult, ValidationError, decode, encode

log = logging.getLogger(__name__)

Deliverer = Callable[[bytes], "ResultAck | None"]
_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def zenoh_deliverer(session, timeout_s: float = 5.0) -> Deliverer:
    """A deliverer that queries keys.THROW_RESULT on ``session`` with the result as payload.

    Returns the first valid ResultAck among the replies, or None (no server, timeout, error or
    malformed reply).
    """

    def deliver(payload: bytes) -> ResultAck | None:
        for reply in session.get(keys.THROW_RESULT, payload=payload, timeout=timeout_s):
            if reply.ok is None:
                log.warning("server rejected a throw result: %s", reply.err.payload.to_bytes()[:200])
                continue
            try:
                return decode(ResultAck, reply.ok.payload.to_bytes())
            except ValidationError as e:
                log.warning("malformed ResultAck dropped: %s", e)
        return None

    return deliver


class Outbox:
    """Directory-backed queue of ThrowResults.

    Args:
        directory: where result files live (created if missing).
        deliver: sends one encoded ThrowResult, returns the server's ResultAck or None.
        retry_interval_s: pause between delivery rounds of the background thread.
    """

    def __init__(self, directory: str | Path, deliver: Deliverer, retry_interval_s: float = 2.0):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.deliver = deliver
        self.retry_interval_s = float(retry_interval_s)
        self._lock = threading.Lock()  # one delivery round at a time
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def put(self, result: ThrowResult) -> Path:
        """Store a result durably and wake the delivery thread; returns the file path."""
        name = f"{result.stamp_s:017.6f}-{_SAFE.sub('_', result.throw_id)}.json"
        path = self.directory / name
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=".json")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(encode(result))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        log.info("throw %s (%s) queued in outbox", result.throw_id, result.status)
        self._wake.set()
        return path

    def pending(self) -> list[Path]:
        """Undelivered result files, oldest first."""
        return sorted(p for p in self.directory.glob("*.json") if not p.name.startswith(".tmp-"))

    def deliver_pending(self) -> int:
        """Try every pending file once; returns how many were acknowledged and removed."""
        delivered = 0
        with self._lock:
            for path in self.pending():
                try:
                    data = path.read_bytes()
                    throw_id = decode(ThrowResult, data).throw_id
                except (OSError, ValidationError) as e:
                    log.error("outbox file %s unusable (%s); renamed to .bad", path.name, e)
                    path.replace(path.with_suffix(".bad"))
                    continue
                try:
                    ack = self.deliver(data)
                except Exception as e:  # noqa: BLE001  a failing transport must not kill the outbox
                    log.warning("delivering throw %s failed: %s", throw_id, e)
                    ack = None
                if ack is not None and ack.stored and ack.throw_id == throw_id:
                    path.unlink(missing_ok=True)
                    delivered += 1
                    log.info("throw %s delivered", throw_id)
                elif ack is not None:
                    log.warning("server did not store throw %s (ack %s); will retry", throw_id, ack)
        return delivered

    def start(self) -> None:
        """Start the background delivery thread (idempotent)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="outbox", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the background thread (files stay on disk)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.pending():
                self.deliver_pending()
            self._wake.wait(self.retry_interval_s)
            self._wake.clear()
