"""What a machine-side process makes of the machine-interface commands it receives: decoded for
its own machine id only, valve commands of the newest runtime epoch only (one driver; see
runtime/protocol/README.md), and, after its valve watchdog tripped, neutral valves until the runtime
sends a neutral command. Used by the simulated machine (sim_twin.twin.plant) and the ROS 2 bridge
(runtime.ros2.bridge)."""

from __future__ import annotations

import logging
from collections.abc import Iterable

from runtime.protocol.messages import M, ValidationError, ValveCommand, decode, machine_id_in

log = logging.getLogger(__name__)


def decode_for(cls: type[M], payload: bytes, machine_id: str) -> M | None:
    """The ``cls`` message in ``payload`` if it is valid and for ``machine_id``, else None (logged)."""
    try:
        msg = decode(cls, payload)
    except ValidationError as e:
        log.warning("dropping malformed %s: %s", cls.__name__, e.errors()[0]["msg"] if e.errors() else e)
        return None
    if machine_id_in(msg) != machine_id:
        log.warning("dropping %s for machine %r", cls.__name__, machine_id_in(msg))
        return None
    return msg


class EpochFence:
    """Follows the newest runtime epoch seen in ValveCommands: a newer one takes over (logged),
    older ones (and epoch-less commands once an epoch was seen) are refused, logged once per epoch.
    Not thread-safe: call under the caller's lock."""

    def __init__(self) -> None:
        self.epoch: int | None = None
        self._stale_logged: set[int | None] = set()

    def admit(self, msg: ValveCommand) -> bool:
        """True if ``msg`` is from the newest epoch (which it may make the newest)."""
        if self.epoch is not None and (msg.epoch is None or msg.epoch < self.epoch):
            if msg.epoch not in self._stale_logged:
                self._stale_logged.add(msg.epoch)
                log.warning("ignoring valve commands of runtime epoch %s: following the newer epoch %d", msg.epoch, self.epoch)
            return False
        if msg.epoch is not None and msg.epoch != self.epoch:
            if self.epoch is not None:
                log.warning("a second runtime (epoch %d) took over from epoch %d", msg.epoch, self.epoch)
            self.epoch = msg.epoch
        return True


class WatchdogLatch:
    """The valve watchdog's latch. When a machine-side process's watchdog puts moving valves neutral
    because the runtime fell silent (``trip``), the throw in flight is over: the runtime fails it on
    the grown ``trips`` count (MachineState.watchdog_trips, runtime.executor). Valve commands the
    runtime sends on afterwards (a late or resumed throw) must not move the arm, so non-neutral
    commands are held neutral until a neutral one arrives, which the runtime sends when its throw
    has ended; that command re-arms the latch (logged). Not thread-safe: call under the caller's lock.

    Attributes:
        armed: False from a trip until a neutral command.
        trips: trips so far (published as MachineState.watchdog_trips).
    """

    def __init__(self) -> None:
        self.armed = True
        self.trips = 0

    def trip(self) -> None:
        """The watchdog put moving valves neutral: count it and hold the valves neutral from now on."""
        self.armed = False
        self.trips += 1

    def admit(self, u: Iterable[float]) -> bool:
        """True if the valve command ``u`` (4 spool positions, [-1, 1]) may drive the valves; False
        after a trip while ``u`` is non-neutral (the caller sends neutral instead). A neutral ``u``
        re-arms the latch."""
        if self.armed:
            return True
        if any(float(x) != 0.0 for x in u):
            return False
        self.armed = True
        log.info("valve watchdog re-armed by a neutral command")
        return True
