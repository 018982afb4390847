"""Durable outbox: no throw result is lost while the server is away or the disk is full.

Each finished ThrowResult is written as one JSON file in a directory (atomically: temporary
file, fsync, rename) before any delivery is tried. A deliverer sends it to the servers (Zenoh
query to keys.THROW_RESULT, to every server's queryable: the one that issued the throw stores it
and replies a ResultAck, another refuses it); the file is deleted only on
``ResultAck(throw_id=<same>, stored=True)``. Undelivered files survive a runtime restart. Files
that no longer parse as a ThrowResult are renamed ``*.bad`` and skipped.

Full disk: at start the outbox reserves RESERVE_BYTES in a file ``.reserve``; a result that
cannot be written (ENOSPC, EDQUOT, EIO, a read-only file system: any OSError) gives the reserve
back and is written again, and if that fails too it is kept in memory, delivered from there all
the same, and written to disk as soon as writes succeed again (each delivery round tries; the
reserve is made again then). A landed throw is therefore delivered, never lost, whatever the
disk; only a runtime that dies while the disk is full and the server away loses what it held in
memory (logged as an error when the result went to memory).

Retries are bounded where they can be: a result that no server answers, or whose server could
not store it now (``stored=False``: its database or disk failing), is tried again every
AWAY_RETRY_S (the outbox's purpose is to outlast a server that is away or faulted, and a
restarted server must have its results before its reconciler gives the throw up; a query that no
queryable matches costs the link nothing); a result that servers only refuse (error replies such
as "not a throw this server issued" or a bad MAC) backs off (``retry_interval_s`` doubling up to
MAX_BACKOFF_S) and is tried MAX_REFUSALS times, then moved to
``undeliverable/`` in the outbox directory, kept there and counted (:attr:`Outbox.undeliverable`,
RuntimeInfo.undeliverable_results), never retried without end; moving a file back into the
outbox directory queues it again.

The deliverer is injectable (``Callable[[bytes], ResultAck | None]``, raising
:class:`DeliveryRefused` for refusals) so the outbox is tested without Zenoh;
:func:`zenoh_deliverer` is the production one.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

from runtime.protocol import keys
from runtime.protocol.messages import ResultAck, ThrowResult, ValidationError, decode, encode

log = logging.getLogger(__name__)

Deliverer = Callable[[bytes], "ResultAck | None"]
_SAFE = re.compile(r"[^A-Za-z0-9_.-]")

RESERVE_BYTES = 8 * 1024 * 1024
"""Space the outbox holds at start for results written while the disk is full, bytes. CHOSEN
8 MiB: a 10 s throw's result (100 Hz telemetry as MCAP, base64) is about 0.3 MB, so some 25 of
them; far below any disk the runtime runs from."""
MAX_BACKOFF_S = 60.0
"""Longest pause between delivery tries of a result that servers refuse, s."""
AWAY_RETRY_S = 2.0
"""Pause between delivery tries of a result no server answered (or stored), s. CHOSEN 2 s: a
restarted server has its results within 2 s, well inside its result grace (15 s by default)."""
MAX_REFUSALS = 10
"""Tries of a result that servers only refuse before it is moved to ``undeliverable/``. CHOSEN 10:
with the back-off some 5 minutes, so the issuing server's restart beside a refusing second
server does not set its results aside."""
UNDELIVERABLE = "undeliverable"


class DeliveryRefused(Exception):
    """Servers answered a delivery and none stored it (their error replies, in ``args[0]``)."""


def zenoh_deliverer(session, timeout_s: float = 5.0) -> Deliverer:
    """A deliverer that queries keys.THROW_RESULT on ``session`` with the result as payload, at
    every server's queryable (``QueryTarget.ALL``, replies not consolidated): the server that
    issued the throw stores it, others refuse it.

    Returns the ResultAck that says stored (else the last valid one), or None when no server
    answered (none there, timeout, malformed replies).

    Raises:
        DeliveryRefused: servers answered with error replies only.
    """
    import zenoh

    def deliver(payload: bytes) -> ResultAck | None:
        acks, refusals = [], []
        for reply in session.get(keys.THROW_RESULT, payload=payload, timeout=timeout_s,
                                 target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is None:
                refusals.append(reply.err.payload.to_bytes()[:200].decode(errors="replace"))
                continue
            try:
                acks.append(decode(ResultAck, reply.ok.payload.to_bytes()))
            except ValidationError as e:
                log.warning("malformed ResultAck dropped: %s", e)
        stored = [a for a in acks if a.stored]
        if stored or acks:
            return (stored or acks)[-1]
        if refusals:
            raise DeliveryRefused("; ".join(refusals))
        return None

    return deliver


class Outbox:
    """Directory-backed queue of ThrowResults (module docstring: full disk, bounded retries).

    Args:
        directory: where result files live (created if missing).
        deliver: sends one encoded ThrowResult, returns the server's ResultAck or None (no
            answer), raises DeliveryRefused when servers refused it.
        retry_interval_s: first pause between tries of one result, doubling per try up to
            ``max_backoff_s``; also the delivery thread's idle wake-up.
        reserve_bytes: space reserved at start (RESERVE_BYTES; 0: none).
        max_refusals: see MAX_REFUSALS.
        max_backoff_s: see MAX_BACKOFF_S.
        clock: monotonic seconds (back-off timing; tests inject one).
    """

    def __init__(self, directory: str | Path, deliver: Deliverer, retry_interval_s: float = 2.0,
                 reserve_bytes: int = RESERVE_BYTES, max_refusals: int = MAX_REFUSALS,
                 max_backoff_s: float = MAX_BACKOFF_S, clock: Callable[[], float] = time.monotonic):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.deliver = deliver
        self.retry_interval_s = float(retry_interval_s)
        self.max_refusals, self.max_backoff_s = int(max_refusals), float(max_backoff_s)
        self.clock = clock
        self.reserve_path = self.directory / ".reserve"
        self.reserve_bytes = int(reserve_bytes)
        self._lock = threading.Lock()  # one delivery round at a time
        self._mem_lock = threading.Lock()  # the results held in memory
        self._memory: dict[str, bytes] = {}  # file name -> encoded result not yet on disk
        self._tries: dict[str, tuple[int, int, float]] = {}  # name -> (tries, refusals, next try at)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.undeliverable = len(list((self.directory / UNDELIVERABLE).glob("*.json")))
        """Results moved to ``undeliverable/`` (kept, never retried without end)."""
        self._reserve()

    # --- storage ------------------------------------------------------------------------------
    def _reserve(self) -> bool:
        """Make the reserve file if it is missing; True if it is there."""
        if self.reserve_bytes <= 0 or self.reserve_path.exists():
            return True
        tmp = self.directory / ".reserve.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                os.posix_fallocate(fd, 0, self.reserve_bytes)
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.reserve_path)
            return True
        except OSError as e:
            tmp.unlink(missing_ok=True)
            log.warning("outbox: could not reserve %d bytes in %s (%s)", self.reserve_bytes, self.directory, e.strerror or e)
            return False

    def write(self, name: str, data: bytes) -> Path:
        """Write ``data`` to the file ``name`` in the outbox directory atomically and durably
        (temporary file, fsync, rename).

        Raises:
            OSError: the write failed (nothing is left behind).
        """
        path = self.directory / name
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=".json")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    def put(self, result: ThrowResult) -> Path:
        """Store a result (on disk; with a full disk from the reserve, else in memory) and wake
        the delivery thread; returns the file path (where it is or will be written)."""
        name = f"{result.stamp_s:017.6f}-{_SAFE.sub('_', result.throw_id)}.json"
        data = encode(result)
        try:
            path = self.write(name, data)
        except OSError as first:
            released = self.reserve_path.exists()
            self.reserve_path.unlink(missing_ok=True)
            try:
                if not released:
                    raise first
                path = self.write(name, data)
                log.error("outbox: disk full (%s): throw %s written from the reserve", first.strerror or first, result.throw_id)
            except OSError as e:
                with self._mem_lock:
                    self._memory[name] = data
                log.error("outbox: throw %s (%s) could not be written (%s): held in memory, delivered from there, "
                          "written when the disk takes it", result.throw_id, result.status, e.strerror or e)
                self._wake.set()
                return self.directory / name
        log.info("throw %s (%s) queued in outbox", result.throw_id, result.status)
        self._wake.set()
        return path

    def _catch_up(self) -> None:
        """Write results held in memory to disk, then the reserve, while writes succeed."""
        with self._mem_lock:
            held = list(self._memory.items())
        for name, data in held:
            try:
                self.write(name, data)
            except OSError:
                return
            with self._mem_lock:
                self._memory.pop(name, None)
            log.info("outbox: %s written to disk (held in memory while the disk was full)", name)
        if not self._memory:
            self._reserve()

    def in_memory(self) -> list[str]:
        """Names of the results held in memory (not yet on disk), oldest first."""
        with self._mem_lock:
            return sorted(self._memory)

    def pending(self) -> list[Path]:
        """Undelivered result files on disk, oldest first."""
        return sorted(p for p in self.directory.glob("*.json") if not p.name.startswith(".tmp-"))

    # --- delivery -----------------------------------------------------------------------------
    def deliver_pending(self, due_only: bool = False) -> int:
        """Try every pending result once (``due_only``: those whose back-off has passed), from
        disk and from memory, oldest first; returns how many were acknowledged and removed."""
        delivered = 0
        with self._lock:
            self._catch_up()
            with self._mem_lock:
                held = dict(self._memory)
            entries: list[tuple[str, Path | None]] = [(p.name, p) for p in self.pending()]
            entries += [(n, None) for n in held if n not in {e[0] for e in entries}]
            now = self.clock()
            for name, path in sorted(entries, key=lambda e: e[0]):
                if due_only and self._tries.get(name, (0, 0, -float("inf")))[2] > now:
                    continue
                try:
                    data = path.read_bytes() if path is not None else held[name]
                    throw_id = decode(ThrowResult, data).throw_id
                except (OSError, ValidationError) as e:
                    if path is not None:
                        log.error("outbox file %s unusable (%s); renamed to .bad", path.name, e)
                        path.replace(path.with_suffix(".bad"))
                    continue
                refused: str | None = None
                try:
                    ack = self.deliver(data)
                except DeliveryRefused as e:
                    ack, refused = None, str(e)
                except Exception as e:  # noqa: BLE001  a failing transport must not kill the outbox
                    log.warning("delivering throw %s failed: %s", throw_id, e)
                    ack = None
                if ack is not None and ack.stored and ack.throw_id == throw_id:
                    if path is not None:
                        path.unlink(missing_ok=True)
                    with self._mem_lock:
                        self._memory.pop(name, None)
                    self._tries.pop(name, None)
                    delivered += 1
                    log.info("throw %s delivered", throw_id)
                    continue
                if ack is not None:
                    log.warning("server did not store throw %s (ack %s); will retry", throw_id, ack)
                self._retry_later(name, path, throw_id, refused)
        return delivered

    def _retry_later(self, name: str, path: Path | None, throw_id: str, refused: str | None) -> None:
        """Back off the next try of ``name``; a result refused ``max_refusals`` times goes to
        ``undeliverable/`` (kept, counted, logged)."""
        tries, refusals, _ = self._tries.get(name, (0, 0, 0.0))
        tries, refusals = tries + 1, refusals + (refused is not None)
        if refused is not None:
            log.warning("server did not store throw %s (%s); try %d of %d", throw_id, refused, refusals, self.max_refusals)
        if refusals >= self.max_refusals and path is not None:
            target = self.directory / UNDELIVERABLE
            try:
                target.mkdir(exist_ok=True)
                path.replace(target / path.name)
            except OSError as e:
                log.error("outbox: could not set aside undeliverable %s (%s)", path.name, e)
            else:
                self._tries.pop(name, None)
                self.undeliverable += 1
                log.error("throw %s undeliverable: refused %d times (%s); kept in %s", throw_id, refusals, refused, target)
                return
        if refusals:
            delay = min(self.retry_interval_s * 2 ** (refusals - 1), self.max_backoff_s)
        else:
            delay = min(self.retry_interval_s, AWAY_RETRY_S)
        self._tries[name] = (tries, refusals, self.clock() + delay)

    def start(self) -> None:
        """Start the background delivery thread (idempotent)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="outbox", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the background thread (files stay on disk; results held in memory are written if
        the disk takes them, else logged as lost with the process)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        with self._lock:
            self._catch_up()
        for name in self.in_memory():
            log.error("outbox: %s was never written (disk full) and ends with this process", name)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.pending() or self.in_memory():
                self.deliver_pending(due_only=True)
            with self._lock:
                waits = [t for _, _, t in self._tries.values()]
            pause = self.retry_interval_s if not waits else max(min(min(waits) - self.clock(), self.max_backoff_s), 0.01)
            self._wake.wait(pause)
            self._wake.clear()
