"""The server's link to the fleet over Zenoh.

:class:`Fleet` owns the server's one :class:`server.fleet.events.FleetListener` (one subscriber
per machine stream, each message decoded once) and is its first consumer: it tracks which
runtimes are alive (liveliness of ``keys.ALL_RUNTIME_ALIVE``), keeps the latest
:class:`MachineState` per machine (``keys.ALL_STATES``) and the one RuntimeInfo cache of the
server, follows ThrowStatus (``keys.ALL_STATUS``) into the throws table; the other consumers
(the live stream, the drift watch, the 3D scene) register with :meth:`Fleet.add_consumer` and
see the same events after the fleet's state is updated. It queries runtimes (ThrowRequest ->
ThrowAck, RuntimeInfo) and is the queryable of ``keys.THROW_RESULT``: it stores each result (row + MCAP file, see
:mod:`server.fleet.results`) and replies ``ResultAck(stored=True)`` only after the commit. Results are
stored only with a valid MAC of their machine's command key and only for throws the server issued;
anything else is refused with the reason, logged and never shown in the history.

Commands (ThrowRequest, AbortRequest, EstopReset, PolicyOffer) are signed with the machine's
command key (:class:`server.fleet.command_signer.CommandSigner`) for the requesting user and the epoch
of the runtime's claim (from its RuntimeInfo, which the runtime also publishes on
``keys.ALL_RUNTIME_STATES``; the cache follows it). E-STOPs are per-machine fire-and-forget
puts confirmed by the runtime's AbortAck on ``keys.ALL_ESTOP_ACKS`` (:mod:`server.fleet.estop`,
:meth:`Fleet.estop`), so one machine's stop never waits for another's, a query or a pool. The
queries and commands live in :mod:`server.fleet.commands` (re-exported here: ``Fleet`` has them,
``RuntimeUnavailable`` is importable from this module as before).

Threads: Zenoh calls the callbacks on its own threads; everything that touches the database is
handed to one worker thread (:class:`server.fleet.results.ResultStore` runs there) so writes are
serialised and Zenoh threads never block on SQL. A result's telemetry file is written and
fsynced first on a small pool of staging threads (``STAGE_THREADS``), so file I/O overlaps the
database work; the row, the file's rename into place and the accuracy aggregates are committed
together on the worker thread before the ack.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import zenoh
from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import MachineState, ResultAck, RuntimeInfo, ThrowResult, decode, encode
from runtime.zenoh_session import undeclare_all
from server.fleet.command_signer import CommandSigner
from server.fleet.commands import FleetCommands, RuntimeUnavailable
from server.fleet.estop import EstopLine
from server.fleet.events import (
    Consumer,
    FleetEvent,
    FleetListener,
    MachineStateEvent,
    ResultStored,
    RuntimeInfoEvent,
    RuntimeOffline,
    RuntimeOnline,
    ThrowStatusEvent,
)
from server.fleet.results import ResultStore, UnknownThrow

log = logging.getLogger(__name__)


RESULT_BATCH = 200
"""At most this many throw results are stored in one commit (the DB thread drains what arrived)."""
RUNTIME_SILENT_S = 3.0
"""A runtime that published its RuntimeInfo (>= 2 Hz) and is silent this long is shown offline
("runtime not answering"): frozen or cut off, well within the Zenoh link lease (10 s)."""
STAGE_THREADS = 8
"""Threads that write and fsync the results' telemetry files before the DB thread commits them
(file I/O overlaps the database's; the GIL is released while writing)."""

CLOCK_WARN_S = 1.0
"""A runtime whose wall clock differs from the server's by more than this (seconds) gets a clock
warning (signed commands are compensated by the measured offset; the warning names the cause)."""


def clock_warning(offset_s: float | None) -> str | None:
    """The clock warning of a runtime whose wall clock is ``offset_s`` seconds off the server's,
    or None within :data:`CLOCK_WARN_S` (or unknown)."""
    if offset_s is None or abs(offset_s) <= CLOCK_WARN_S:
        return None
    return (f"clock differs from the server by {offset_s:+.1f} s (signed commands are compensated; "
            "fix the time sync of the runtime's host)")


class Fleet(FleetCommands):
    """Zenoh side of the server. Call :meth:`start` once, :meth:`stop` at shutdown. The queries
    and signed commands to runtimes (:meth:`query_info`, :meth:`request_throw`, :meth:`abort`, ...)
    come from :class:`server.fleet.commands.FleetCommands`.

    Args:
        session: an open Zenoh session (the caller closes it).
        store: writes statuses and results to the database and telemetry folder.
        query_timeout_s: timeout of queries to runtimes, s.
        signer: the site's command keys (default: none, so no command can be signed).
        estop_latch_file: where the server keeps its E-STOP latches across restarts
            (:class:`server.fleet.estop.EstopLine`; None: in memory only).
    """

    def __init__(self, session: zenoh.Session, store: ResultStore, query_timeout_s: float = 5.0,
                 signer: CommandSigner | None = None, estop_latch_file: Path | None = None):
        self.session = session
        self.store = store
        self.query_timeout_s = query_timeout_s
        self.signer = signer or CommandSigner(None)
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._started_s = time.monotonic()
        self._offline_since: dict[str, float] = {}
        self._estop = EstopLine(session, self._sign_abort, latch_file=estop_latch_file)
        self.refused_results: list[tuple[str, str]] = []
        """(throw id, reason) of the last refused results (bounded), for tests and diagnostics."""
        self._states: dict[str, MachineState] = {}
        self._infos: dict[str, tuple[float, RuntimeInfo]] = {}
        """machine id -> (monotonic s received, RuntimeInfo): the server's one RuntimeInfo cache."""
        self._forgotten: set[str] = set()
        """machines whose cached RuntimeInfo is forgotten (:meth:`forget_info`): reads ask again,
        the console still shows it (:meth:`last_info`) until a newer one arrives."""
        self._published_s: dict[str, float] = {}
        """machine id -> monotonic s of its runtime's last RuntimeInfo on keys.runtime_state."""
        self._clock_offsets: dict[str, float] = {}
        """machine id -> its runtime's wall clock minus the server's, s (latest RuntimeInfo)."""
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._results: list[tuple[zenoh.Query, ThrowResult, Path | Exception | None]] = []
        """Results with their staged telemetry waiting for the DB thread; one job stores all that
        arrived meanwhile."""
        self._stage = ThreadPoolExecutor(max_workers=STAGE_THREADS, thread_name_prefix="telemetry")
        self._worker: threading.Thread | None = None
        self._decls: list = []
        self.listener = FleetListener()
        """The one subscriber of the machine streams; the fleet is its first consumer."""
        self.listener.add_consumer(self._on_event)

    # --- lifecycle -----------------------------------------------------------------------------
    def add_consumer(self, consumer: Consumer) -> None:
        """Register ``consumer`` for every fleet event (:mod:`server.fleet.events`), after the
        fleet's own handling of it. Zenoh events come on Zenoh threads, :class:`ResultStored` on
        the fleet's database thread; a consumer must not block."""
        self.listener.add_consumer(consumer)

    def remove_consumer(self, consumer: Consumer) -> None:
        self.listener.remove_consumer(consumer)

    def start(self) -> None:
        """Start the worker, then declare the listener's subscribers, the E-STOP acks' and the
        result queryable."""
        self._worker = threading.Thread(target=self._work, name="fleet-db", daemon=True)
        self._worker.start()
        s = self.session
        self.listener.start(s)
        self._decls = [
            s.declare_subscriber(keys.ALL_ESTOP_ACKS, self._estop.on_ack),
            s.declare_queryable(keys.THROW_RESULT, self._on_result, complete=True),
        ]

    def stop(self) -> None:
        """Undeclare everything and drain the worker (pending results are still stored)."""
        self.listener.stop()
        undeclare_all(self._decls)
        self._estop.close()
        self._stage.shutdown(wait=True)  # staged results still reach the DB thread
        if self._worker is not None:
            self._jobs.put(None)
            self._worker.join(timeout=10.0)
            self._worker = None

    # --- read side -----------------------------------------------------------------------------
    def is_online(self, machine_id: str) -> bool:
        """True while the runtime of ``machine_id`` holds its liveliness token."""
        with self._lock:
            return machine_id in self._alive

    def offline_for_s(self, machine_id: str) -> float:
        """Seconds since the runtime of ``machine_id`` went offline (since the fleet link started
        if it was never seen); 0 while online."""
        with self._lock:
            if machine_id in self._alive:
                return 0.0
            return time.monotonic() - self._offline_since.get(machine_id, self._started_s)

    def online_ids(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def latest_state(self, machine_id: str) -> MachineState | None:
        """The most recent MachineState of ``machine_id`` (None if never seen)."""
        with self._lock:
            return self._states.get(machine_id)

    def latest_states(self) -> dict[str, MachineState]:
        with self._lock:
            return dict(self._states)

    def cached_info(self, machine_id: str) -> RuntimeInfo | None:
        """The last RuntimeInfo of ``machine_id`` (None if none since it came online or since
        :meth:`forget_info`)."""
        with self._lock:
            entry = None if machine_id in self._forgotten else self._infos.get(machine_id)
        return entry[1] if entry else None

    def last_info(self, machine_id: str) -> RuntimeInfo | None:
        """The last RuntimeInfo heard from ``machine_id``'s runtime since it came online, even
        one :meth:`forget_info` dropped for reads (what the console shows until a newer one comes)."""
        with self._lock:
            entry = self._infos.get(machine_id)
        return entry[1] if entry else None

    def published_info(self, machine_id: str, max_age_s: float) -> RuntimeInfo | None:
        """The cached RuntimeInfo of ``machine_id`` if its runtime published one (keys.runtime_state)
        within ``max_age_s`` (s), else None; never queries."""
        with self._lock:
            published = self._published_s.get(machine_id)
            entry = None if machine_id in self._forgotten else self._infos.get(machine_id)
        if published is None or entry is None or time.monotonic() - published > max_age_s:
            return None
        return entry[1]

    def fresh_info(self, machine_id: str, max_age_s: float = 2.0, timeout_s: float = 1.0) -> RuntimeInfo | None:
        """RuntimeInfo at most ``max_age_s`` old: the cache, else a query (``timeout_s``);
        the stale cached one if the runtime does not answer or has gone silent (no query then);
        None for an offline runtime."""
        if not self.is_online(machine_id):
            return None
        with self._lock:
            entry = None if machine_id in self._forgotten else self._infos.get(machine_id)
        if entry is not None and time.monotonic() - entry[0] <= max_age_s:
            return entry[1]
        if not self.is_answering(machine_id):  # silent: a query would only wait for its timeout
            return entry[1] if entry else None
        try:
            return self.query_info(machine_id, timeout_s=timeout_s)
        except (RuntimeUnavailable, ValidationError) as e:
            log.debug("RuntimeInfo of %s: %s", machine_id, e)
            return entry[1] if entry else None

    def silent_for_s(self, machine_id: str) -> float:
        """Seconds since the runtime of ``machine_id`` last published its RuntimeInfo (it does
        at >= 2 Hz); 0 while it is offline or has not published since it came online."""
        with self._lock:
            if machine_id not in self._alive or machine_id not in self._published_s:
                return 0.0
            return time.monotonic() - self._published_s[machine_id]

    def is_answering(self, machine_id: str) -> bool:
        """Online (liveliness) and not silent for more than RUNTIME_SILENT_S: a frozen runtime
        keeps its liveliness token until the Zenoh link's lease expires, but stops publishing."""
        return self.is_online(machine_id) and self.silent_for_s(machine_id) <= RUNTIME_SILENT_S

    def clock_offset_s(self, machine_id: str) -> float | None:
        """The runtime's wall clock minus the server's, s, from its latest RuntimeInfo (transit
        time, milliseconds, neglected); None if it never reported its clock."""
        with self._lock:
            return self._clock_offsets.get(machine_id)

    def _note_info(self, info: RuntimeInfo, published: bool) -> None:
        """Cache ``info`` (received now; ``published`` on keys.runtime_state, else a query reply)
        and measure the runtime's clock offset from it."""
        now = time.monotonic()
        with self._lock:
            if info.machine_id not in self._alive and published:
                return
            self._infos[info.machine_id] = (now, info)
            self._forgotten.discard(info.machine_id)
            if published:
                self._published_s[info.machine_id] = now
            if info.clock_unix_s is not None:
                self._clock_offsets[info.machine_id] = info.clock_unix_s - time.time()

    def forget_info(self, machine_id: str) -> None:
        """Drop the cached RuntimeInfo (e.g. after its policies changed) so the next read asks."""
        with self._lock:
            if machine_id in self._infos:
                self._forgotten.add(machine_id)

    def submit_db_job(self, job: Callable[[], object]) -> Future:
        """Run ``job`` on the fleet's database thread; its Future completes when it ran."""
        done: Future = Future()

        def run() -> None:
            try:
                done.set_result(job())
            except BaseException as e:
                done.set_exception(e)
                raise

        self._jobs.put(run)
        return done

    # --- events (Zenoh threads) ----------------------------------------------------------------
    def _on_event(self, event: FleetEvent) -> None:
        """The fleet's own handling of a listener event, before any other consumer sees it."""
        if isinstance(event, MachineStateEvent):
            with self._lock:
                self._states[event.machine_id] = event.state
        elif isinstance(event, RuntimeInfoEvent):
            self._note_info(event.info, published=True)
        elif isinstance(event, ThrowStatusEvent):
            status = event.status
            self._jobs.put(lambda: self.store.apply_status(status))
        elif isinstance(event, RuntimeOnline):
            log.info("runtime %s online", event.machine_id)
            self._set_alive(event.machine_id, True)
            self._estop.runtime_online(event.machine_id)  # a held stop reaches it before anything else
            self._jobs.put(lambda: self._register(event.machine_id))
        elif isinstance(event, RuntimeOffline):
            log.info("runtime %s offline", event.machine_id)
            self._set_alive(event.machine_id, False)

    def _set_alive(self, machine_id: str, alive: bool) -> None:
        """Presence changed: a new claim (or none) -- its RuntimeInfo and epoch are asked again."""
        with self._lock:
            if alive:
                self._alive.add(machine_id)
                self._offline_since.pop(machine_id, None)
            else:
                self._alive.discard(machine_id)
                self._offline_since[machine_id] = time.monotonic()
            self._infos.pop(machine_id, None)
            self._forgotten.discard(machine_id)
            self._published_s.pop(machine_id, None)

    def _on_result(self, query: zenoh.Query) -> None:
        raw = query.payload.to_bytes() if query.payload is not None else b""
        try:
            result = decode(ThrowResult, raw)
        except ValidationError as e:
            log.warning("malformed ThrowResult refused: %s", e)
            query.reply_err(f"malformed ThrowResult: {e}".encode())
            return
        refusal = self.signer.check_result(result)
        if refusal is not None:
            self._refuse_result(query, result.throw_id, f"result of throw {result.throw_id!r} refused: {refusal}")
            return
        # The query stays open until replied (or dropped); its telemetry is written and fsynced
        # on the staging threads, then the DB thread stores and acks it after the commit.
        try:
            self._stage.submit(self._staged, query, result)
        except RuntimeError:  # stopping
            query.drop()

    def _staged(self, query: zenoh.Query, result: ThrowResult) -> None:
        staged: Path | Exception | None
        try:
            staged = self.store.stage_telemetry(result)
        except (ValueError, OSError) as e:
            staged = e
        with self._lock:
            self._results.append((query, result, staged))
            first = len(self._results) == 1
        if first:
            self._jobs.put(self._store_and_ack)

    def _refuse_result(self, query: zenoh.Query, throw_id: str, reason: str) -> None:
        log.warning("%s", reason)
        with self._lock:
            self.refused_results = [*self.refused_results[-99:], (throw_id, reason)]
        try:
            query.reply_err(reason.encode())
        finally:
            query.drop()

    # --- worker thread -------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except Exception:
                log.exception("fleet job failed")

    def _register(self, machine_id: str) -> None:
        try:
            info = self.query_info(machine_id)
        except (RuntimeUnavailable, ValidationError) as e:
            log.warning("runtime %s: no RuntimeInfo (%s)", machine_id, e)
            state = self.latest_state(machine_id)
            self.store.upsert_machine(machine_id, simulated=bool(state and state.simulated))
            return
        self.store.upsert_machine(machine_id, simulated=info.simulated, policies=info.policies)

    def _store_and_ack(self) -> None:
        """Store every result that arrived since the last call in one batch, then ack each."""
        with self._lock:
            batch, self._results = self._results[:RESULT_BATCH], self._results[RESULT_BATCH:]
            if self._results:
                self._jobs.put(self._store_and_ack)
        if not batch:
            return
        t0 = time.monotonic()
        try:
            outcomes = self.store.store_results([r for _, r, _ in batch], [s for _, _, s in batch])
            log.debug("stored %d results in %.0f ms", len(batch), (time.monotonic() - t0) * 1e3)
        except Exception:
            log.exception("storing a batch of %d results failed", len(batch))
            outcomes = [RuntimeError("commit failed")] * len(batch)
        for (query, result, _), outcome in zip(batch, outcomes):
            self._ack(query, result, outcome)

    def _ack(self, query: zenoh.Query, result: ThrowResult, outcome) -> None:
        if isinstance(outcome, UnknownThrow):
            self._refuse_result(query, result.throw_id, str(outcome))
            return
        stored = not isinstance(outcome, Exception)
        if not stored:
            log.error("result of throw %s not stored: %s", result.throw_id, outcome)
        try:
            query.reply(keys.THROW_RESULT, encode(ResultAck(throw_id=result.throw_id, stored=stored)))
        finally:
            query.drop()
        if stored:
            self.listener.emit(ResultStored(result.throw_id))
