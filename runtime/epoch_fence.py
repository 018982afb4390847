"""What a machine-side process makes of the machine-interface commands it receives: decoded for
its own machine id only, and valve commands of the newest runtime epoch only (one driver; see
runtime/protocol/README.md). Used by the simulated machine (sim_twin.twin.plant) and the ROS 2 bridge
(runtime.ros2.bridge)."""

from __future__ import annotations

import logging

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
