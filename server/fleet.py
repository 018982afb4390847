"""The server's link to the fleet over Zenoh.

:class:`Fleet` tracks which runtimes are alive (liveliness of ``keys.ALL_RUNTIME_ALIVE``), keeps the
latest :class:`MachineState` per machine (``keys.ALL_STATES``), queries runtimes (ThrowRequest ->
ThrowAck, RuntimeInfo), follows ThrowStatus (``keys.ALL_STATUS``) into the throws table and is
the queryable of ``keys.THROW_RESULT``: it stores each result (row + MCAP file, see
:mod:`server.results`) and replies ``ResultAck(stored=True)`` only after the commit.

Threads: Zenoh calls the callbacks on its own threads; everything that touches the database is
handed to one worker thread (:class:`server.results.ResultStore` runs there) so writes are
serialised and Zenoh threads never block on SQL.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import zenoh
from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    AbortRequest,
    MachineState,
    ResultAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    ThrowStatus,
    decode,
    encode,
)
from server.results import ResultStore

log = logging.getLogger(__name__)


class RuntimeUnavailable(RuntimeError):
    """The runtime did not answer (offline, or no reply within the timeout)."""


class Fleet:
    """Zenoh side of the server. Call :meth:`start` once, :meth:`stop` at shutdown.

    Args:
        session: an open Zenoh session (the caller closes it).
        store: writes statuses and results to the database and telemetry folder.
        query_timeout_s: timeout of queries to runtimes, s.
    """

    def __init__(self, session: zenoh.Session, store: ResultStore, query_timeout_s: float = 5.0):
        self.session = session
        self.store = store
        self.query_timeout_s = query_timeout_s
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._states: dict[str, MachineState] = {}
        self._infos: dict[str, tuple[float, RuntimeInfo]] = {}
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._decls: list = []
        self.result_listeners: list[Callable[[str], None]] = []
        """Called (on the worker thread) with the throw id after a result is stored."""

    # --- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker, then declare subscribers and the result queryable."""
        self._worker = threading.Thread(target=self._work, name="fleet-db", daemon=True)
        self._worker.start()
        s = self.session
        self._decls = [
            s.liveliness().declare_subscriber(keys.ALL_RUNTIME_ALIVE, self._on_alive, history=True),
            s.declare_subscriber(keys.ALL_STATES, self._on_state),
            s.declare_subscriber(keys.ALL_STATUS, self._on_status),
            s.declare_queryable(keys.THROW_RESULT, self._on_result, complete=True),
        ]

    def stop(self) -> None:
        """Undeclare everything and drain the worker (pending results are still stored)."""
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:  # already closed with the session
                log.debug("undeclare failed", exc_info=True)
        self._decls = []
        if self._worker is not None:
            self._jobs.put(None)
            self._worker.join(timeout=10.0)
            self._worker = None

    # --- read side -----------------------------------------------------------------------------
    def is_online(self, machine_id: str) -> bool:
        """True while the runtime of ``machine_id`` holds its liveliness token."""
        with self._lock:
            return machine_id in self._alive

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
        """The last RuntimeInfo of ``machine_id`` (None if none since it came online)."""
        with self._lock:
            entry = self._infos.get(machine_id)
        return entry[1] if entry else None

    def fresh_info(self, machine_id: str, max_age_s: float = 2.0, timeout_s: float = 1.0) -> RuntimeInfo | None:
        """RuntimeInfo at most ``max_age_s`` old: the cache, else a query (``timeout_s``);
        the stale cached one if the runtime does not answer; None for an offline runtime."""
        if not self.is_online(machine_id):
            return None
        with self._lock:
            entry = self._infos.get(machine_id)
        if entry is not None and time.monotonic() - entry[0] <= max_age_s:
            return entry[1]
        try:
            return self.query_info(machine_id, timeout_s=timeout_s)
        except (RuntimeUnavailable, ValidationError) as e:
            log.debug("RuntimeInfo of %s: %s", machine_id, e)
            return entry[1] if entry else None

    def forget_info(self, machine_id: str) -> None:
        """Drop the cached RuntimeInfo (e.g. after its policies changed) so the next read asks."""
        with self._lock:
            self._infos.pop(machine_id, None)

    # --- queries -------------------------------------------------------------------------------
    def query_info(self, machine_id: str, timeout_s: float | None = None) -> RuntimeInfo:
        """Ask the runtime for its RuntimeInfo (and cache it).

        Raises:
            RuntimeUnavailable: no valid reply within the timeout.
        """
        info = decode(RuntimeInfo, self._query_one(keys.info(machine_id), None, timeout_s))
        with self._lock:
            self._infos[machine_id] = (time.monotonic(), info)
        return info

    def request_throw(self, request: ThrowRequest) -> ThrowAck:
        """Send a ThrowRequest and wait for the runtime's ThrowAck.

        Raises:
            RuntimeUnavailable: no reply within the timeout, an error reply or a malformed ack.
        """
        payload = self._query_one(keys.throw(request.machine_id), encode(request))
        try:
            return decode(ThrowAck, payload)
        except ValidationError as e:
            raise RuntimeUnavailable(f"malformed ThrowAck from {request.machine_id}: {e}") from e

    def abort(self, machine_id: str, reason: str = "operator abort") -> AbortAck:
        """Ask the runtime to stop now (valves to neutral); returns its AbortAck.

        Raises:
            RuntimeUnavailable: no valid reply within the timeout.
        """
        payload = self._query_one(keys.abort(machine_id), encode(AbortRequest(machine_id=machine_id, reason=reason)))
        try:
            return decode(AbortAck, payload)
        except ValidationError as e:
            raise RuntimeUnavailable(f"malformed AbortAck from {machine_id}: {e}") from e

    def _query_one(self, key: str, payload: bytes | None, timeout_s: float | None = None) -> bytes:
        timeout_s = timeout_s or self.query_timeout_s
        kwargs = {"timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = payload
        errors = []
        for reply in self.session.get(key, **kwargs):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            errors.append(reply.err.payload.to_string() if reply.err is not None else "?")
        if errors:
            raise RuntimeUnavailable(f"{key}: error reply: {'; '.join(errors)}")
        raise RuntimeUnavailable(f"no reply on {key} within {timeout_s:.1f} s")

    # --- callbacks (Zenoh threads) -------------------------------------------------------------
    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            machine_id = keys.machine_id_of(str(sample.key_expr))
        except ValueError:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            log.info("runtime %s online", machine_id)
            with self._lock:
                self._alive.add(machine_id)
            self._jobs.put(lambda: self._register(machine_id))
        else:
            log.info("runtime %s offline", machine_id)
            with self._lock:
                self._alive.discard(machine_id)
                self._infos.pop(machine_id, None)

    def _on_state(self, sample: zenoh.Sample) -> None:
        try:
            state = decode(MachineState, sample.payload.to_bytes())
        except ValidationError:
            log.debug("dropped malformed MachineState on %s", sample.key_expr)
            return
        with self._lock:
            self._states[state.machine_id] = state

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = decode(ThrowStatus, sample.payload.to_bytes())
        except ValidationError:
            log.warning("dropped malformed ThrowStatus on %s", sample.key_expr)
            return
        self._jobs.put(lambda: self.store.apply_status(status))

    def _on_result(self, query: zenoh.Query) -> None:
        raw = query.payload.to_bytes() if query.payload is not None else b""
        try:
            result = decode(ThrowResult, raw)
        except ValidationError as e:
            log.warning("malformed ThrowResult refused: %s", e)
            query.reply_err(f"malformed ThrowResult: {e}".encode())
            return
        # The query stays open until replied (or dropped); reply on the worker after the commit.
        self._jobs.put(lambda: self._store_and_ack(query, result))

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

    def _store_and_ack(self, query: zenoh.Query, result: ThrowResult) -> None:
        try:
            self.store.store_result(result)
            stored = True
        except Exception:
            log.exception("storing result of throw %s failed", result.throw_id)
            stored = False
        try:
            query.reply(keys.THROW_RESULT, encode(ResultAck(throw_id=result.throw_id, stored=stored)))
        finally:
            query.drop()
        if stored:
            for listener in list(self.result_listeners):
                try:
                    listener(result.throw_id)
                except Exception:
                    log.exception("result listener failed")
