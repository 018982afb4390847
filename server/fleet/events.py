"""The server's one listener to the fleet's machine streams, and the typed events it emits.

:class:`FleetListener` declares one Zenoh subscriber per key pattern (runtime liveliness,
``keys.ALL_STATES``, ``keys.ALL_STATUS``, ``keys.ALL_RUNTIME_STATES``, the valve commands),
decodes each message once with :func:`runtime.protocol.messages.decode_on_key` (a message must
name the machine of its key) and hands one event to each registered consumer, in registration
order, on the Zenoh callback thread. :class:`server.fleet.link.Fleet` registers first (its caches are
current before anyone else hears of a change); the live stream (:class:`server.console.live.LiveHub`),
the reconciler (:class:`server.fleet.reconcile.Reconciler`), the drift watch and the 3D scene follow.
:class:`ResultStored` is emitted by the fleet after a result's commit (on its database thread),
through the same consumers.

A consumer is any callable taking one event; it must return quickly (MachineState comes at
100 Hz per machine) and never block. An exception in a consumer is logged and does not reach the
others or Zenoh. Malformed messages are logged (debug) and dropped.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import zenoh
from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import MachineState, Message, RuntimeInfo, ThrowStatus, ValveCommand, decode_on_key
from runtime.zenoh_session import undeclare_all

log = logging.getLogger(__name__)

ALL_VALVE_CMDS = f"{keys.ROOT}/machine/*/valve_cmd"
"""Key pattern of every machine's valve commands (runtime -> machine, 100 Hz)."""
M = TypeVar("M", bound=Message)


@dataclass(frozen=True)
class RuntimeOnline:
    """The runtime of ``machine_id`` took its liveliness token (``keys.runtime_alive``)."""

    machine_id: str


@dataclass(frozen=True)
class RuntimeOffline:
    """The runtime of ``machine_id`` lost its liveliness token (stopped, or its link's lease expired)."""

    machine_id: str


@dataclass(frozen=True)
class RuntimeInfoEvent:
    """A RuntimeInfo the runtime published on ``keys.runtime_state`` (2 Hz and on every change)."""

    info: RuntimeInfo

    @property
    def machine_id(self) -> str:
        return self.info.machine_id


@dataclass(frozen=True)
class MachineStateEvent:
    """A MachineState of the machine (``keys.state``, 100 Hz)."""

    state: MachineState

    @property
    def machine_id(self) -> str:
        return self.state.machine_id


@dataclass(frozen=True)
class ValveCommandEvent:
    """The valve commands a runtime sent its machine (``keys.valve_cmd``, 100 Hz while it commands)."""

    command: ValveCommand

    @property
    def machine_id(self) -> str:
        return self.command.machine_id


@dataclass(frozen=True)
class ThrowStatusEvent:
    """A throw's phase change from its runtime (``keys.status``)."""

    status: ThrowStatus

    @property
    def machine_id(self) -> str:
        return self.status.machine_id


@dataclass(frozen=True)
class ResultStored:
    """The result of throw ``throw_id`` is committed (row and telemetry) and acknowledged."""

    throw_id: str


FleetEvent = (RuntimeOnline | RuntimeOffline | RuntimeInfoEvent | MachineStateEvent | ValveCommandEvent
              | ThrowStatusEvent | ResultStored)
Consumer = Callable[[FleetEvent], None]


def on_results(handler: Callable[[str], None]) -> Consumer:
    """A consumer that calls ``handler(throw_id)`` for each :class:`ResultStored` and ignores the rest."""

    def consume(event: FleetEvent) -> None:
        if isinstance(event, ResultStored):
            handler(event.throw_id)

    return consume


class FleetListener:
    """One subscriber per machine stream; each message decoded once, fanned out as an event.

    Call :meth:`add_consumer` before or after :meth:`start`; :meth:`stop` undeclares the
    subscribers (the caller closes the session).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._consumers: tuple[Consumer, ...] = ()
        self._decls: list = []

    def add_consumer(self, consumer: Consumer) -> None:
        """Register ``consumer``; it gets every event emitted from now on, after those registered before."""
        with self._lock:
            self._consumers = (*self._consumers, consumer)

    def remove_consumer(self, consumer: Consumer) -> None:
        with self._lock:
            self._consumers = tuple(c for c in self._consumers if c is not consumer)

    def emit(self, event: FleetEvent) -> None:
        """Hand ``event`` to every consumer (on the calling thread); a failing consumer is logged."""
        for consumer in self._consumers:
            try:
                consumer(event)
            except Exception:
                log.exception("fleet event consumer %r failed on %s", consumer, type(event).__name__)

    def start(self, session: zenoh.Session) -> None:
        """Declare the subscribers on ``session`` (liveliness with history: runtimes already online
        are reported at once)."""
        self._decls = [
            session.liveliness().declare_subscriber(keys.ALL_RUNTIME_ALIVE, self._on_alive, history=True),
            session.declare_subscriber(keys.ALL_STATES, self._decoder(MachineState, MachineStateEvent)),
            session.declare_subscriber(keys.ALL_STATUS, self._decoder(ThrowStatus, ThrowStatusEvent)),
            session.declare_subscriber(keys.ALL_RUNTIME_STATES, self._decoder(RuntimeInfo, RuntimeInfoEvent)),
            session.declare_subscriber(ALL_VALVE_CMDS, self._decoder(ValveCommand, ValveCommandEvent)),
        ]

    def stop(self) -> None:
        undeclare_all(self._decls)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            machine_id = keys.machine_id_of(str(sample.key_expr))
        except ValueError:
            return
        online = sample.kind == zenoh.SampleKind.PUT
        self.emit(RuntimeOnline(machine_id) if online else RuntimeOffline(machine_id))

    def _decoder(self, message: type[M], event: Callable[[M], FleetEvent]) -> Callable[[zenoh.Sample], None]:
        """The Zenoh callback that decodes one ``message`` per sample and emits ``event(message)``."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode_on_key(message, str(sample.key_expr), sample.payload.to_bytes())
            except (ValidationError, ValueError) as e:
                log.debug("dropped %s on %s: %s", message.__name__, sample.key_expr, e)
                return
            self.emit(event(msg))

        return on_sample
