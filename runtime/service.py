"""The runtime's message handling, without Zenoh: wire bytes in, wire bytes out.

:class:`RuntimeService` wraps a ThrowExecutor behind a lock (Zenoh callbacks arrive on other
threads), decodes and checks every message (malformed, NaN or foreign-machine messages are logged
and dropped), publishes through an injected ``send(key, payload)`` and hands finished throws to
the outbox. :mod:`runtime.node` connects it to a Zenoh session; tests drive it directly.

Per valid MachineState: executor.tick -> ValveCommand (every tick, neutral when idle),
GripperCommand (on change), SimReset (when requested), ThrowStatus (on phase changes),
ThrowResult (to the outbox). Watchdog (:meth:`check_watchdog`, called periodically): no valid
state for ``link_timeout_s`` during a throw -> neutral valves, throw failed "machine link lost".
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import numpy as np

from runtime.executor import ThrowExecutor
from runtime.outcome import TickOutput
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    AbortRequest,
    GripperCommand,
    ImpactReport,
    MachineState,
    PolicyInfo,
    RuntimeInfo,
    SimReset,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    ThrowStatus,
    ValidationError,
    ValveCommand,
    decode,
    encode,
)

log = logging.getLogger(__name__)

LINK_TIMEOUT_S = 0.2
"""No valid MachineState for this long during a throw ends it ("machine link lost")."""

ONLINE_TIMEOUT_S = 1.0
"""RuntimeInfo.machine_online: a valid state arrived within this time."""

Send = Callable[[str, bytes], None]


def _short(e: ValidationError) -> str:
    errs = e.errors()
    return f"{errs[0]['loc']}: {errs[0]['msg']}" if errs else str(e)


class RuntimeService:
    """Thread-safe message handling of one runtime.

    Args:
        machine_id: this runtime's machine.
        executor: the throw state machine.
        send: publishes ``payload`` on key expression ``key``.
        on_result: receives every finished ThrowResult (normally ``Outbox.put``).
        clock: monotonic seconds of this process (watchdog only; throw timing uses stamps).
        link_timeout_s: see LINK_TIMEOUT_S.
    """

    def __init__(
        self,
        machine_id: str,
        executor: ThrowExecutor,
        send: Send,
        on_result: Callable[[ThrowResult], object],
        clock: Callable[[], float] = time.monotonic,
        link_timeout_s: float = LINK_TIMEOUT_S,
    ):
        self.machine_id = keys.validate_machine_id(machine_id)
        self.executor = executor
        self.send = send
        self.on_result = on_result
        self.clock = clock
        self.link_timeout_s = link_timeout_s
        self.lock = threading.RLock()
        self.latest_state: MachineState | None = None
        self._state_rx_s = -np.inf
        self._gripper_sent: bool | None = None
        self.dropped = 0  # malformed / foreign messages dropped (for tests and diagnostics)

    # --- incoming machine messages -----------------------------------------------------------
    def _decode(self, cls, payload):
        try:
            msg = decode(cls, payload)
        except ValidationError as e:
            self.dropped += 1
            log.warning("dropping malformed %s: %s", cls.__name__, _short(e))
            return None
        if getattr(msg, "machine_id", self.machine_id) != self.machine_id:
            self.dropped += 1
            log.warning("dropping %s of machine %r", cls.__name__, msg.machine_id)
            return None
        return msg

    def on_state(self, payload: bytes) -> None:
        """A MachineState arrived: tick the executor and publish its commands."""
        state = self._decode(MachineState, payload)
        if state is None:
            return
        with self.lock:
            self.latest_state, self._state_rx_s = state, self.clock()
            self._publish(self.executor.tick(state), state.stamp_s)

    def on_impact(self, payload: bytes) -> None:
        """An ImpactReport arrived: a released throw lands."""
        report = self._decode(ImpactReport, payload)
        if report is None:
            return
        with self.lock:
            self._publish(self.executor.on_impact(report), report.stamp_s)

    def check_watchdog(self) -> bool:
        """Fail the running throw if the machine link is silent; returns True if it did."""
        with self.lock:
            if not self.executor.busy or self.clock() - self._state_rx_s <= self.link_timeout_s:
                return False
            log.error("no machine state for %.0f ms: throw %s failed", self.link_timeout_s * 1e3, self.executor.throw_id)
            stamp = self.latest_state.stamp_s if self.latest_state else 0.0
            self._publish(self.executor.fail("machine link lost"), stamp)
            return True

    # --- queries ------------------------------------------------------------------------------
    def handle_throw(self, payload: bytes) -> bytes:
        """ThrowRequest -> ThrowAck (accepted, or refused with a reason)."""
        try:
            req = decode(ThrowRequest, payload)
        except ValidationError as e:
            self.dropped += 1
            log.warning("malformed ThrowRequest: %s", _short(e))
            return encode(ThrowAck(throw_id="", accepted=False, reason=f"malformed request: {_short(e)}"))
        if req.machine_id != self.machine_id:
            return encode(ThrowAck(throw_id=req.throw_id, accepted=False, reason=f"this runtime serves {self.machine_id!r}"))
        with self.lock:
            state = self.latest_state if self._online(self.link_timeout_s) else None
            reason = "machine offline (no recent state)" if state is None and not self.executor.busy else None
            reason = reason or self.executor.start(req, state)
            policy = self.executor.policies.get(req.mode)
            if reason is None:
                log.info("throw %s accepted: %s at %s", req.throw_id, req.mode, req.target_m)
                self._publish(self.executor.drain(), state.stamp_s)  # the preparing status
            else:
                log.info("throw %s refused: %s", req.throw_id, reason)
        return encode(ThrowAck(throw_id=req.throw_id, accepted=reason is None, reason=reason, policy_version=policy.version if policy else None))

    def handle_abort(self, payload: bytes) -> bytes:
        """AbortRequest -> AbortAck; an empty payload aborts with the default reason."""
        try:
            req = decode(AbortRequest, payload) if payload else AbortRequest(machine_id=self.machine_id)
        except ValidationError as e:
            self.dropped += 1
            log.warning("malformed AbortRequest (aborting anyway): %s", _short(e))
            req = AbortRequest(machine_id=self.machine_id, reason="abort (malformed request)")
        with self.lock:
            throw_id = self.executor.throw_id
            stamp = self.latest_state.stamp_s if self.latest_state else 0.0
            self._publish(self.executor.abort(req.reason), stamp)
        if throw_id:
            log.info("throw %s aborted: %s", throw_id, req.reason)
        return encode(AbortAck(machine_id=self.machine_id, aborted_throw_id=throw_id))

    def shutdown(self) -> None:
        """Abort a running throw (neutral valves, result to the outbox) before the node exits."""
        with self.lock:
            if self.executor.busy:
                stamp = self.latest_state.stamp_s if self.latest_state else 0.0
                self._publish(self.executor.abort("runtime shutting down"), stamp)

    def handle_info(self) -> bytes:
        """-> RuntimeInfo (policies as version = manifest name, sha256)."""
        with self.lock:
            info = RuntimeInfo(
                machine_id=self.machine_id,
                busy=self.executor.busy,
                policies=[PolicyInfo(mode=m, version=p.version, sha256=p.sha256) for m, p in sorted(self.executor.policies.items())],
                machine_online=self._online(ONLINE_TIMEOUT_S),
                simulated=bool(self.latest_state and self.latest_state.simulated),
            )
        return encode(info)

    # --- outgoing -----------------------------------------------------------------------------
    def _online(self, within_s: float) -> bool:
        return self.latest_state is not None and self.clock() - self._state_rx_s <= within_s

    def _publish(self, out: TickOutput, stamp_s: float) -> None:
        mid = self.machine_id
        u = np.clip(out.valve_u, -1.0, 1.0)
        self.send(keys.valve_cmd(mid), encode(ValveCommand(machine_id=mid, stamp_s=stamp_s, u=u.tolist())))
        if out.gripper_open != self._gripper_sent:
            self.send(keys.gripper_cmd(mid), encode(GripperCommand(machine_id=mid, stamp_s=stamp_s, open=out.gripper_open)))
            self._gripper_sent = out.gripper_open
        if out.sim_reset is not None:
            self.send(keys.sim_reset(mid), encode(out.sim_reset))
        for ev in out.events:
            log.info("throw %s: %s%s", ev.throw_id, ev.phase, f" ({ev.detail})" if ev.detail else "")
            status = ThrowStatus(machine_id=mid, stamp_s=ev.stamp_s, throw_id=ev.throw_id, phase=ev.phase, detail=ev.detail)
            self.send(keys.status(mid), encode(status))
        if out.finished is not None:
            if out.finished.status != "aborted" and self.latest_state is not None and self.latest_state.simulated:
                # simulated machine: pick up the next payload now, so the machine waits loaded
                # and at rest, and a preview from its current state predicts the next throw
                self.send(keys.sim_reset(mid), encode(SimReset(machine_id=mid, stamp_s=stamp_s)))
            try:
                self.on_result(out.finished.to_message(mid))
            except Exception:  # the outbox failing must not stop the control loop
                log.exception("could not store the result of throw %s", out.finished.throw_id)
