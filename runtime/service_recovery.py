"""Return to the ready pose, the runtime's recovery command (split out of :mod:`runtime.service`).

:class:`RecoveryHandling` is the recovery half of :class:`runtime.service.RuntimeService`: a
signed ReturnToReady starts a :class:`runtime.recovery.ReturnToReady` (the arm driven back to the
ready pose with the throw controller's gains); it is refused while E-STOP is latched, a throw
runs, the machine is offline or faulted. While it runs each MachineState ticks it instead of the
executor; it is stopped with a reason (abort, machine fault, silent link, shutdown) and reports
its progress in 5 % steps for RuntimeInfo.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from runtime.outcome import TickOutput
from runtime.protocol.messages import MachineState, Message, ReturnToReady, ReturnToReadyAck, encode
from runtime.recovery import ReturnToReady as Recovery

if TYPE_CHECKING:
    from runtime.controller import JointVelocityController
    from runtime.executor import ThrowExecutor

log = logging.getLogger("runtime.service")  # the logger of runtime.service, as before the split


class RecoveryHandling:
    """The return to the ready pose; a base of :class:`runtime.service.RuntimeService`, which
    provides what these methods use: ``machine_id``, ``executor``, ``lock``, ``latest_state``,
    ``link_timeout_s`` (s), ``estop_reason``, ``recovery`` (the current or last
    :class:`runtime.recovery.ReturnToReady`), ``_recovery_ctrl``, ``_gripper_sent``,
    :meth:`~runtime.service.RuntimeService.authorize`, ``_addressed``, ``_who``, ``_online``
    and :meth:`~runtime.service.RuntimeService.publish_info`.
    """

    if TYPE_CHECKING:  # provided by runtime.service.RuntimeService (declared here for the type checker)
        machine_id: str
        executor: ThrowExecutor
        lock: threading.RLock
        latest_state: MachineState | None
        link_timeout_s: float
        estop_reason: str | None
        recovery: Recovery | None
        _recovery_ctrl: JointVelocityController
        _gripper_sent: bool | None

        def authorize(self, msg: Message) -> str | None: ...

        def _addressed(self, payload: bytes, command_type: type[Message],
                       refusal: Callable[[str], bytes]) -> tuple[Any, bytes | None]: ...

        @staticmethod
        def _who(msg: Message) -> str: ...

        def _online(self, within_s: float) -> bool: ...

        def publish_info(self, now_s: float | None = None) -> bool: ...

    @property
    def returning(self) -> bool:
        """A return to the ready pose is running."""
        return self.recovery is not None and self.recovery.status.active

    def handle_return_to_ready(self, payload: bytes) -> bytes:
        """ReturnToReady (signed) -> ReturnToReadyAck; starts driving the arm to the ready pose."""
        req, refused = self._addressed(payload, ReturnToReady, lambda why: encode(
            ReturnToReadyAck(machine_id=self.machine_id, accepted=False, reason=why)))
        if refused is not None:
            return refused
        reason = self.authorize(req)
        with self.lock:
            state = self.latest_state if self._online(self.link_timeout_s) else None
            if reason is None:
                reason = self._return_refusal(state)
            if reason is None and not self.returning:
                if state is None:  # _return_refusal refuses without a state
                    raise RuntimeError("return to the ready pose accepted without a machine state")
                self.recovery = Recovery(state.q, state.stamp_s, self._recovery_ctrl)
                self._return_trips = state.watchdog_trips
                self.publish_info()
        log.log(logging.WARNING if reason else logging.INFO, "return to the ready pose %s for %s%s",
                "refused" if reason else "started", self._who(req), f": {reason}" if reason else "")
        return encode(ReturnToReadyAck(machine_id=self.machine_id, accepted=reason is None, reason=reason))

    def _return_refusal(self, state: MachineState | None) -> str | None:
        if self.estop_reason is not None:
            return f"E-STOP latched: {self.estop_reason}"
        if self.executor.busy:
            return f"a throw runs: {self.executor.throw_id}"
        if state is None:
            return "machine offline (no recent state)"
        if state.machine_fault:
            return f"machine fault: {state.machine_fault}"
        return None

    def _current_recovery(self) -> Recovery:
        """The current or last return to the ready pose.

        Raises:
            RuntimeError: none was ever started (callers check :attr:`returning` or ``recovery`` first).
        """
        if self.recovery is None:
            raise RuntimeError("no return to the ready pose was started")
        return self.recovery

    _return_trips: int | None = None
    """The machine's valve-watchdog count when the current return started (None: not reported)."""

    def _tick_return(self, state: MachineState) -> TickOutput:
        """One machine state of a return to the ready pose; a valve-watchdog trip of the machine
        since it started stops it for good (finality, as for a throw)."""
        recovery = self._current_recovery()
        trips = state.watchdog_trips
        if trips is not None and (self._return_trips is None or trips > self._return_trips):
            self._stop_return("machine link lost: the machine's valve watchdog stopped the arm")
            return TickOutput(np.zeros(4), np.zeros(4), bool(self._gripper_sent), (), None)
        ctrl = recovery.tick(state.q, state.qd, state.stamp_s)
        if not recovery.status.active:
            log.info("return to the ready pose: %s", recovery.status.result)
        return TickOutput(ctrl.valve_u.copy(), ctrl.qd_ref.copy(), bool(self._gripper_sent), (), None)

    def _stop_return(self, why: str) -> None:
        self._current_recovery().stop(why)
        log.warning("return to the ready pose stopped: %s", why)

    def _return_progress(self) -> float:
        """The recovery's progress in 5 % steps (RuntimeInfo is published on every change)."""
        return round(20 * self._current_recovery().status.progress) / 20
