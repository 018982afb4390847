"""The runtime's message handling, without Zenoh: wire bytes in, wire bytes out.

:class:`RuntimeService` wraps a ThrowExecutor behind a lock (Zenoh callbacks arrive on other
threads), decodes and checks every message (malformed, NaN or foreign-machine messages are logged
and dropped), publishes through an injected ``send(key, payload)`` and hands finished throws to
the outbox. :mod:`runtime.node` connects it to a Zenoh session; tests drive it directly.

Per valid MachineState: executor.tick -> ValveCommand (every tick, neutral when idle; carries
this runtime's claim epoch), GripperCommand (on change), ThrowStatus (on phase changes),
ThrowResult (MAC'ed, to the outbox), RuntimeInfo on keys.runtime_state (on change and at 2 Hz).
Watchdog (:meth:`check_watchdog`, called periodically): no valid state for ``link_timeout_s``
during a throw -> neutral valves, throw failed "machine link lost".

Command checks (runtime.command_auth, issue 8): throws, E-STOP resets and policy offers must be
signed with the machine's command key for this runtime's epoch, fresh and not replayed; without
a key (``verifier=None``) every one is refused "no command key configured" (fail safe). An abort
is honoured even unsigned and LATCHES E-STOP: valves neutral every tick, throws refused
"E-STOP latched: <reason>" until a signed EstopReset. The latch is durable
(:class:`runtime.estop_latch.EstopLatchFile`, given as ``latch``): written and fsynced before the
stop is acknowledged, read at start (a runtime restarted after a stop comes up latched), removed
only by a signed EstopReset. The server's E-STOP arrives as a put on keys.estop
(:meth:`on_estop`) and is confirmed by an AbortAck on keys.estop_ack; the query keys.abort
(:meth:`handle_abort`) does the same for other callers. A MachineState with ``machine_fault``
refuses throws and fails a running one. The runtime never asks whether the machine is simulated:
what only the simulated machine does (reloading a payload) happens inside the plant.

Finality (a throw that a watchdog stopped never resumes): every entry (a state, a query, the
watchdog tick) measures the monotonic time since the previous one; a gap over
``stall_timeout_s`` means this runtime's own loop stalled (SIGSTOP, swapping, a starved host),
during which the machine's valve watchdog has put the valves neutral. The running throw then
fails "machine link lost: runtime stalled 1.23 s" (a return to the ready pose stops; a throw
that has released keeps its arm stopped and still lands: ThrowExecutor.stop_arm) before
anything queued during the stall is acted on; after a stall of STALL_REFUSE_S or more, commands
issued before it ended are refused (:data:`STALLED`), and machine states later than ``stale_state_s`` (judged by the state's stamp
against its receive time, relative to the smallest such lag of the last :data:`LAG_WINDOW_S`,
so the machine's clock need not be this host's) are dropped, failing a running throw. The
executor fails a throw whose machine states lie too far apart or during which the machine's
valve watchdog tripped (runtime.executor). A failed throw leaves the executor idle: READY again
only at rest, and only a new signed ThrowRequest starts anything.

E-STOP edges: a confirmed EstopReset ends the stops that reached the runtime before it: a queued
put of such a stop (same ``request_id``, fresh per press) is logged and ignored, never
re-latching; every other abort latches. Warm-up: with ``warm_up=True`` throws are refused
"runtime warming up" (and RuntimeInfo is not ready with that reason) until :meth:`warm_up`
has run each policy, the release check and the telemetry writer once.

One writer per machine (the lease): the runtime obeys one server at a time, named by its signed
``CommandAuth.server`` (servers that name none count as one unnamed server). Every signed
command the runtime authorises (throw, E-STOP reset, return to the ready pose, policy offer, a
LeaseRequest) gives its server the lease when nobody holds it or the holder's lease expired,
and renews it for its holder; the lease expires after LEASE_S without an authorised command of
its holder, never while the holder's throw or a return to the ready pose runs. Another server's
command is refused with the reason (its ThrowAck / EstopResetAck / ReturnToReadyAck /
PolicyOfferAck says "machine m1 is commanded by server ...") until then, or until it takes the
lease over deliberately with a signed ``LeaseRequest(takeover=True)`` (refused while a throw
runs). E-STOPs are never refused: any server, or none, stops the machine. Each result carries
the server that issued its throw (``ThrowResult.server_id``); RuntimeInfo names the holder.

Recovery (:mod:`runtime.recovery`): a signed ReturnToReady drives the arm back to the ready pose
with the same controller gains; refused while E-STOP is latched, a throw runs, the machine is
offline or faulted; stopped by an abort (E-STOP), a machine fault or a silent machine link.
RuntimeInfo offers it (``recovery``) when the pose is why the machine is not ready, and reports
``returning`` / ``return_progress`` / ``return_result``. The ReturnToReady handling lives in
:mod:`runtime.service_recovery` (a base of :class:`RuntimeService`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from runtime import telemetry
from runtime.command_auth import CommandVerifier, sign, verify_mac
from runtime.controller import JointVelocityController
from runtime.estop_latch import EstopLatchFile
from runtime.executor import ThrowExecutor
from runtime.outcome import TickOutput
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    AbortRequest,
    EstopReset,
    EstopResetAck,
    GripperCommand,
    ImpactReport,
    LeaseAck,
    LeaseRequest,
    MachineState,
    Message,
    PolicyInfo,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    ThrowStatus,
    ValidationError,
    ValveCommand,
    decode,
    encode,
)
from runtime.recovery import POSE_REASONS, pose_refusal
from runtime.recovery import ReturnToReady as Recovery
from runtime.service_recovery import RecoveryHandling

log = logging.getLogger(__name__)

LINK_TIMEOUT_S = 0.2
"""No valid MachineState for this long during a throw ends it ("machine link lost")."""

ONLINE_TIMEOUT_S = 1.0
"""RuntimeInfo.machine_online: a valid state arrived within this time."""

AT_REST_MPS_OR_RADPS = 0.05
"""An active joint faster than this (rad/s, m/s for the telescope) is moving: no throw starts
and the runtime is not READY (a preview made now would start from another state)."""

INFO_PERIOD_S = 0.5
"""RuntimeInfo is published on keys.runtime_state at least this often (2 Hz) and on change."""

NO_KEY = "no command key configured"

STALL_TIMEOUT_S = 0.2
"""No entry into the runtime (machine state, query, watchdog tick every 50 ms) for this long: the
runtime's own loop stalled; a running throw fails (module docstring: finality). CHOSEN 0.2 s: the
link timeout; four watchdog periods, so a loaded host's late tick is not a stall, while the
machine's 0.1 s valve watchdog has surely stopped the arm."""

STALL_REFUSE_S = 1.0
"""A stall at least this long also refuses the commands issued before it ended (STALLED). CHOSEN
1 s: a loaded host stalls an idle runtime for some 100 ms now and then, while the server still
awaits the reply (5 s); a frozen runtime (seconds) must not act on what queued meanwhile."""

STALE_STATE_S = 0.2
"""A machine state received this much later than the freshest lag of the last LAG_WINDOW_S is stale
(queued during a stall): dropped, a running throw fails."""

LAG_WINDOW_S = 10.0
"""Window of the receive-minus-stamp baseline, s: long enough to span any stall the runtime survives
to judge, short enough that clock-rate drift between the machine and this host (50 ppm: 0.5 ms
per window) does not count."""

REBASE_S = 1.0
"""Machine states that stay stale this long (receive time) mean the machine's clock changed (its
bridge restarted), not a stall, whose queue drains in a burst: the lag baseline starts afresh."""

LEASE_S = 30.0
"""A server's lease on this machine expires after this long without an authorised command of it
(never during its throw), s. CHOSEN 30 s: longer than an operator's preview-then-throw, short
enough that a replaced server takes over without a deliberate takeover within half a minute."""

STALLED = "issued before this runtime's stall ended: not acted on"
WARMING = "runtime warming up"
CLEARED_STOPS = 256
"""How many E-STOP request ids ended by resets are remembered (queued repeats of them are ignored)."""

Send = Callable[[str, bytes], None]


def _short(e: ValidationError) -> str:
    errs = e.errors()
    return f"{errs[0]['loc']}: {errs[0]['msg']}" if errs else str(e)


class RuntimeService(RecoveryHandling):
    """Thread-safe message handling of one runtime (the return to the ready pose:
    :class:`runtime.service_recovery.RecoveryHandling`).

    Args:
        machine_id: this runtime's machine.
        executor: the throw state machine.
        send: publishes ``payload`` on key expression ``key``.
        on_result: receives every finished ThrowResult (normally ``Outbox.put``).
        verifier: checks signed commands (key + this runtime's epoch); None: no command key,
            every throw, E-STOP reset and policy offer is refused with NO_KEY.
        clock: monotonic seconds of this process (watchdog only; throw timing uses stamps).
        link_timeout_s: see LINK_TIMEOUT_S.
        epoch: this runtime's claim epoch (put into every ValveCommand and RuntimeInfo);
            default: the verifier's, else 0.
        latch: the durable E-STOP latch (None: the latch lives in memory only, e.g. in tests);
            a latch on disk at construction starts this runtime latched.
        wall_clock: this host's wall clock, Unix s, reported as RuntimeInfo.clock_unix_s
            (default: the verifier's, else time.time).
        stall_timeout_s: see STALL_TIMEOUT_S.
        stale_state_s: see STALE_STATE_S.
        warm_up: refuse throws "runtime warming up" until :meth:`warm_up` ran (the node);
            False (tests that drive the service directly): ready at once.
        lease_s: see LEASE_S.
        undeliverable: how many results the outbox set aside (RuntimeInfo.undeliverable_results;
            the node passes the outbox's count), None: 0.
    """

    def __init__(
        self,
        machine_id: str,
        executor: ThrowExecutor,
        send: Send,
        on_result: Callable[[ThrowResult], object],
        verifier: CommandVerifier | None = None,
        clock: Callable[[], float] = time.monotonic,
        link_timeout_s: float = LINK_TIMEOUT_S,
        epoch: int | None = None,
        latch: EstopLatchFile | None = None,
        wall_clock: Callable[[], float] | None = None,
        stall_timeout_s: float = STALL_TIMEOUT_S,
        stale_state_s: float = STALE_STATE_S,
        warm_up: bool = False,
        lease_s: float = LEASE_S,
        undeliverable: Callable[[], int] | None = None,
    ):
        self.machine_id = keys.validate_machine_id(machine_id)
        self.executor = executor
        self.send = send
        self.on_result = on_result
        self.verifier = verifier
        self.epoch = int(epoch if epoch is not None else (verifier.epoch if verifier else 0))
        self.clock = clock
        self.wall_clock = wall_clock or (verifier.wall_clock if verifier is not None else time.time)
        self.link_timeout_s = link_timeout_s
        self.lock = threading.RLock()
        self.latest_state: MachineState | None = None
        self._state_rx_s = -np.inf
        self._gripper_sent: bool | None = None
        self.latch = latch
        self.estop_reason: str | None = latch.load() if latch is not None else None
        self._latch_on_disk = self.estop_reason is not None
        if self.estop_reason is not None:
            log.warning("E-STOP latched since before this start (%s): throws refused until a signed reset", self.estop_reason)
        self._info_sent: RuntimeInfo | None = None
        self._info_sent_s = -np.inf
        self._pose_judged: tuple[tuple, str | None] | None = None  # (q, qd) -> pose_refusal, see _pose_refusal
        self.dropped = 0  # malformed / foreign messages dropped (for tests and diagnostics)
        ctrl = executor.controller
        self._recovery_ctrl = JointVelocityController(ctrl.gains, ctrl.velocity_limits, ctrl.dt_s)
        self.recovery: Recovery | None = None
        """The current or last return to the ready pose."""
        self.stall_timeout_s, self.stale_state_s = float(stall_timeout_s), float(stale_state_s)
        self._alive_s: float | None = None  # monotonic time of the last entry (None: none yet)
        self._stall_wall_s: float | None = None  # this host's wall clock when the last stall was detected
        self.stalls = 0
        self.stale_states = 0  # machine states dropped as stale (for tests and diagnostics)
        self._lags: deque[tuple[float, float]] = deque()  # (receive s, receive - stamp s), lags increasing
        self._stale_since: float | None = None  # receive time of the first of the current run of stale states
        self._stops_latched: set[str] = set()  # request ids of the E-STOP puts since the last reset
        self._stops_cleared: deque[str] = deque(maxlen=CLEARED_STOPS)
        self.warming: str | None = WARMING if warm_up else None
        self.lease_s = float(lease_s)
        self.lease_holder: str | None = None
        """The server that commands this machine ("" an unnamed one), None before the first."""
        self._lease_until_s = -np.inf
        self._throw_server: str | None = None  # the server of the running (or last) throw
        self.undeliverable = undeliverable or (lambda: 0)

    # --- command authentication ---------------------------------------------------------------
    def authorize(self, msg: Message) -> str | None:
        """None if the signed command ``msg`` may run, else the refusal reason (NO_KEY,
        "unsigned", "bad signature", "wrong epoch: ...", "stale (...)", "replayed nonce")."""
        if self.verifier is None:
            return NO_KEY
        denied = self.verifier.check(msg)
        if denied:
            return denied
        with self.lock:
            self._note_alive()
            return self._stall_refusal(msg) or self._lease(msg)

    def idle(self) -> bool:
        """No throw and no return to the ready pose runs (the runtime's housekeeping, e.g. giving
        the free heap back (runtime.heap), waits for this)."""
        with self.lock:
            return not self.executor.busy and not self.returning

    # --- one writer per machine: the lease -------------------------------------------------------
    @staticmethod
    def _server_of(msg: Message) -> str:
        auth = getattr(msg, "auth", None)
        return (auth.server or "") if auth is not None else ""

    def _lease_free(self, now: float) -> bool:
        """Nobody holds the lease, or its holder's expired (never while a throw or a return runs)."""
        return self.lease_holder is None or (now > self._lease_until_s and self.idle())

    def _lease(self, msg: Message, takeover: bool = False) -> str | None:
        """Give (or renew) the lease to the server of the authorised ``msg``, or the refusal
        reason when another server holds it (module docstring). Caller holds the lock."""
        server, now, holder = self._server_of(msg), self.clock(), self.lease_holder
        if holder is not None and holder != server and not self._lease_free(now):
            if not takeover:
                left = max(self._lease_until_s - now, 0.0)
                return (f"machine {self.machine_id} is commanded by server {holder or '(unnamed)'}: another server's commands "
                        f"are refused until it is silent for {self.lease_s:.0f} s ({left:.0f} s more) or takes over deliberately")
            if self.executor.busy:
                return f"takeover refused: throw {self.executor.throw_id} of server {holder or '(unnamed)'} runs"
        if holder != server:
            log.warning("server %s now commands machine %s%s", server or "(unnamed)", self.machine_id,
                        f" (taken over from {holder or '(unnamed)'})" if holder is not None else "")
        self.lease_holder, self._lease_until_s = server, now + self.lease_s
        return None

    def handle_lease(self, payload: bytes) -> bytes:
        """LeaseRequest (signed) -> LeaseAck: the lease given, renewed or taken over, or why not."""
        req, refused = self._addressed(payload, LeaseRequest, lambda why: encode(
            LeaseAck(machine_id=self.machine_id, granted=False, holder=self.lease_holder, reason=why)))
        if refused is not None:
            return refused
        denied = self.verifier.check(req) if self.verifier is not None else NO_KEY
        with self.lock:
            if not denied:
                self._note_alive()
                denied = self._stall_refusal(req) or self._lease(req, takeover=req.takeover)
            left = max(self._lease_until_s - self.clock(), 0.0) if self.lease_holder is not None else None
            self.publish_info()
            return encode(LeaseAck(machine_id=self.machine_id, granted=denied is None, holder=self.lease_holder,
                                   expires_in_s=left, reason=denied))

    # --- finality: stalls and stale messages ----------------------------------------------------
    def _note_alive(self) -> None:
        """An entry into the runtime (caller holds the lock): a gap since the previous one over
        ``stall_timeout_s`` is a stall of this runtime (:meth:`_stalled`)."""
        now = self.clock()
        last, self._alive_s = self._alive_s, now
        if last is not None and now - last > self.stall_timeout_s:
            self._stalled(now - last)

    def _stalled(self, gap_s: float) -> None:
        """This runtime did not run for ``gap_s``: fail the running throw (stop a return) before
        anything queued meanwhile is acted on; after a stall of STALL_REFUSE_S or more, commands
        issued until now are refused (STALLED)."""
        self.stalls += 1
        if gap_s >= STALL_REFUSE_S:
            self._stall_wall_s = self.wall_clock()
        why = f"machine link lost: runtime stalled {gap_s:.2f} s"
        if self.returning:
            self._stop_return(why)
        if self.executor.busy:
            log.error("runtime stalled for %.0f ms: throw %s stopped", gap_s * 1e3, self.executor.throw_id)
            self._publish(self.executor.stop_arm(why), self._stamp())
        else:
            log.warning("runtime stalled for %.0f ms (idle)%s", gap_s * 1e3,
                        ": commands issued before now are refused" if gap_s >= STALL_REFUSE_S else "")

    def _stall_refusal(self, msg: Message) -> str | None:
        """STALLED if the signed ``msg`` was issued before the last stall was detected."""
        auth = getattr(msg, "auth", None)
        if self._stall_wall_s is not None and auth is not None and auth.issued_unix_s <= self._stall_wall_s:
            return STALLED
        return None

    def _lateness(self, state: MachineState, now: float) -> float:
        """How much later than the freshest of the last LAG_WINDOW_S ``state`` arrived, s:
        receive time minus stamp, against the window's smallest (a sliding-window minimum; the
        machine's stamps may run on another clock)."""
        lag, lags = now - state.stamp_s, self._lags
        while lags and lags[-1][1] >= lag:
            lags.pop()
        lags.append((now, lag))
        while lags[0][0] < now - LAG_WINDOW_S:
            lags.popleft()
        late = lag - lags[0][1]
        if late <= self.stale_state_s:
            self._stale_since = None
        elif self._stale_since is None:
            self._stale_since = now
            log.warning("dropping machine states %.0f ms late (queued during a stall?)", late * 1e3)
        elif now - self._stale_since > REBASE_S:
            log.warning("machine states late for %.1f s: the machine's clock changed; judging lateness afresh", now - self._stale_since)
            lags.clear()
            lags.append((now, lag))
            self._stale_since, late = None, 0.0
        return late

    @staticmethod
    def _who(msg: Message) -> str:
        auth = getattr(msg, "auth", None)
        return auth.user if auth is not None else "?"

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
            self._note_alive()
            now = self.clock()
            late = self._lateness(state, now)
            if late > self.stale_state_s:
                self._drop_stale(late)
                return
            if self.executor.busy and now - self._state_rx_s > self.link_timeout_s:  # the watchdog did not run
                self._publish(self.executor.fail("machine link lost"), self._stamp())
            self.latest_state, self._state_rx_s = state, now
            if state.machine_fault and self.executor.busy:
                log.error("machine fault during throw %s: %s", self.executor.throw_id, state.machine_fault)
                self._publish(self.executor.fail(f"machine fault: {state.machine_fault}"), state.stamp_s)
            if state.machine_fault and self.returning:
                self._stop_return(f"machine fault: {state.machine_fault}")
            self._publish(self._tick_return(state) if self.returning else self.executor.tick(state), state.stamp_s)
            self.publish_info()

    def _drop_stale(self, late_s: float) -> None:
        """A machine state ``late_s`` late (queued during a stall): not acted on; a running throw
        fails, a return to the ready pose stops. Caller holds the lock."""
        self.stale_states += 1
        why = f"machine link lost: machine state {late_s:.2f} s late"
        if self.returning:
            self._stop_return(why)
        if self.executor.busy:
            self._publish(self.executor.stop_arm(why), self._stamp())
            self.publish_info()

    def on_impact(self, payload: bytes) -> None:
        """An ImpactReport arrived: a released throw lands."""
        report = self._decode(ImpactReport, payload)
        if report is None:
            return
        with self.lock:
            self._publish(self.executor.on_impact(report), report.stamp_s)

    def check_watchdog(self) -> bool:
        """Fail the running throw (stop a return to the ready pose) if the machine link is
        silent or this runtime stalled (:meth:`_note_alive`); returns True if it did."""
        with self.lock:
            busy = not self.idle()
            self._note_alive()
            if busy and self.idle():  # the stall ended it
                self.publish_info()
                return True
            if self.returning and self.clock() - self._state_rx_s > self.link_timeout_s:
                self._stop_return("machine link lost")
                self._publish(TickOutput(np.zeros(4), np.zeros(4), bool(self._gripper_sent), (), None), self._stamp())
                self.publish_info()
                return True
            if not self.executor.busy or self.clock() - self._state_rx_s <= self.link_timeout_s:
                return False
            log.error("no machine state for %.0f ms: throw %s failed", self.link_timeout_s * 1e3, self.executor.throw_id)
            self._publish(self.executor.fail("machine link lost"), self._stamp())
            self.publish_info()
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
        denied = self.authorize(req)
        with self.lock:
            self._note_alive()
            state = self.latest_state if self._online(self.link_timeout_s) else None
            reason = denied or self._throw_refusal(state) or self.executor.start(req, state)
            policy = self.executor.policies.get(req.mode)
            if reason is None:
                if state is None:  # _throw_refusal refuses without a state
                    raise RuntimeError(f"throw {req.throw_id} accepted without a machine state")
                self._throw_server = self._server_of(req)
                log.info("throw %s accepted for %s: %s at %s", req.throw_id, self._who(req), req.mode, req.target_m)
                self._publish(self.executor.drain(), state.stamp_s)  # the preparing status
                self.publish_info()
            else:
                log.warning("throw %s refused%s: %s", req.throw_id, "" if denied else f" for {self._who(req)}", reason)
        return encode(ThrowAck(throw_id=req.throw_id, accepted=reason is None, reason=reason, policy_version=policy.version if policy else None,
                               policy_sha256=policy.sha256 if policy else None))

    def _throw_refusal(self, state: MachineState | None) -> str | None:
        """Why no throw may start now (E-STOP, machine fault, pose), before the executor's checks."""
        if self.estop_reason is not None:
            return f"E-STOP latched: {self.estop_reason}"
        if self.warming is not None:
            return self.warming
        if self.executor.busy:
            return None  # the executor says "busy"
        if self.returning:
            return "returning to the ready pose"
        if state is None:
            return "machine offline (no recent state)"
        if state.machine_fault:
            return f"machine fault: {state.machine_fault}"
        return self._start_refusal(state)

    def _start_refusal(self, state: MachineState) -> str | None:
        """Why a throw cannot really start from ``state`` (READY only when it can): no payload
        in the gripper (e.g. the next one not loaded yet after a landing), the gripper open, an
        active joint still moving (faster than AT_REST_MPS_OR_RADPS), or the pose
        (:meth:`_pose_refusal`)."""
        if not state.payload_attached:
            return "no payload loaded"
        if state.gripper_open:
            return "gripper open"
        moving = max(abs(v) for v in state.qd[:4])
        if moving > AT_REST_MPS_OR_RADPS:
            return f"machine moving ({moving:.2f} rad/s or m/s)"
        return self._pose_refusal(state)

    def _pose_refusal(self, state: MachineState) -> str | None:
        """runtime.recovery.pose_refusal of ``state``, judged once per pose: a machine at rest
        publishes the same q and qd at 20 Hz, and RuntimeInfo is built 20 times a second."""
        key = (tuple(state.q), tuple(state.qd))
        if self._pose_judged is None or self._pose_judged[0] != key:
            self._pose_judged = (key, pose_refusal(state))
        return self._pose_judged[1]

    def handle_abort(self, payload: bytes) -> bytes:
        """AbortRequest -> AbortAck; latches E-STOP. Honoured signed or not (an empty or
        malformed payload aborts with a default reason); the log says who asked, if signed.
        Valves go neutral first; the latch is written to disk before the ack is returned.
        A stop that a confirmed reset already ended (:meth:`_ended_stop`) is acked and ignored."""
        req, signed = self._abort_request(payload)
        if self._ended_stop(req):
            return encode(AbortAck(machine_id=self.machine_id, request_id=req.request_id, latch_persisted=False))
        return self._abort(req, signed)

    def _abort_request(self, payload: bytes) -> tuple[AbortRequest, bool]:
        """The AbortRequest in ``payload`` (a default one for an empty or malformed payload) and
        whether its MAC holds under this runtime's key."""
        try:
            req = decode(AbortRequest, payload) if payload else AbortRequest(machine_id=self.machine_id)
        except ValidationError as e:
            self.dropped += 1
            log.warning("malformed AbortRequest (aborting anyway): %s", _short(e))
            req = AbortRequest(machine_id=self.machine_id, reason="abort (malformed request)")
        return req, self.verifier is not None and verify_mac(req, self.verifier.key) is None

    def _ended_stop(self, req: AbortRequest) -> bool:
        """True (logged) if ``req`` is a stop a confirmed reset already ended: a repeat of an
        E-STOP put whose ``request_id`` (fresh per press, server.fleet.estop) reached this runtime before
        the reset (a slowed runtime still had it queued). Requests without a request id, and every
        new press, always stop: a stop is never dated by a clock, whose estimate may move."""
        with self.lock:
            ended = req.request_id is not None and req.request_id in self._stops_cleared
        if ended:
            log.warning("ignoring E-STOP request %s (%s): a confirmed reset already ended it", req.request_id, req.reason)
        return ended

    def _abort(self, req: AbortRequest, signed: bool) -> bytes:
        """Abort and latch for ``req`` (handle_abort's body)."""
        with self.lock:
            if req.request_id is not None:
                self._stops_latched.add(req.request_id)
            throw_id = self.executor.throw_id
            self._publish(self.executor.abort(req.reason), self._stamp())
            if self.returning:
                self._stop_return(f"E-STOP: {req.reason}")
            repeated = self.estop_reason is not None
            if not repeated:
                self.estop_reason = req.reason
            persisted = self._persist_latch(repeated)
            self.publish_info()
        log.warning("E-STOP %s (%s abort by %s): %s%s", "still latched" if repeated else "latched",
                    "signed" if signed else "UNSIGNED", self._who(req) if signed else "unknown", req.reason,
                    f"; throw {throw_id} aborted" if throw_id else "")
        return encode(AbortAck(machine_id=self.machine_id, aborted_throw_id=throw_id, request_id=req.request_id,
                               latch_persisted=persisted))

    def _persist_latch(self, already: bool) -> bool:
        """Write the latch (``self.estop_reason``) to disk unless ``already`` latched (then it is
        on disk since that stop); True if it is on disk. Caller holds the lock."""
        if self.latch is None:
            return False
        if already and self._latch_on_disk:
            return True
        if self.estop_reason is None:  # callers latch first
            raise RuntimeError("E-STOP latch written without a reason")
        try:
            self.latch.write(self.estop_reason)
            self._latch_on_disk = True
        except OSError as e:
            self._latch_on_disk = False
            log.error("E-STOP latch NOT written to %s (%s): it holds until this runtime stops", self.latch.path, e)
        return self._latch_on_disk

    def on_estop(self, payload: bytes) -> None:
        """An E-STOP put (keys.estop) arrived: :meth:`handle_abort`, then publish its AbortAck on
        keys.estop_ack (the sender waits for it; repeated puts of one stop are acked each). A put
        of a stop that a confirmed reset ended (:meth:`_ended_stop`) is ignored, unanswered."""
        req, signed = self._abort_request(payload)
        if self._ended_stop(req):
            return
        self.send(keys.estop_ack(self.machine_id), self._abort(req, signed))

    def _addressed(self, payload: bytes, command_type, refusal):
        """Decode a command query for this machine: ``(request, None)``, or ``(None, refusal(why))``
        for a malformed request (counted in ``dropped``) or one addressed to another machine.
        The signature is checked by the caller (:meth:`authorize`)."""
        try:
            req = decode(command_type, payload)
        except ValidationError as e:
            self.dropped += 1
            return None, refusal(f"malformed request: {_short(e)}")
        if req.machine_id != self.machine_id:
            return None, refusal(f"this runtime serves {self.machine_id!r}")
        return req, None

    def handle_estop_reset(self, payload: bytes) -> bytes:
        """EstopReset (signed) -> EstopResetAck; releases a latched E-STOP."""
        req, refused = self._addressed(payload, EstopReset, lambda why: encode(
            EstopResetAck(machine_id=self.machine_id, reset=False, reason=why)))
        if refused is not None:
            return refused
        denied = self.authorize(req)
        if denied:
            log.warning("E-STOP reset refused: %s", denied)
            return encode(EstopResetAck(machine_id=self.machine_id, reset=False, reason=denied))
        with self.lock:
            if self.latch is not None:
                try:
                    self.latch.clear()
                except OSError as e:
                    why = f"E-STOP latch file could not be removed ({e.strerror}): still latched"
                    log.error("E-STOP reset by %s refused: %s", self._who(req), why)
                    return encode(EstopResetAck(machine_id=self.machine_id, reset=False, reason=why))
            was, self.estop_reason, self._latch_on_disk = self.estop_reason, None, False
            self._stops_cleared.extend(self._stops_latched)
            self._stops_latched.clear()
            self.publish_info()
        log.warning("E-STOP reset by %s (was latched: %s)", self._who(req), was)
        return encode(EstopResetAck(machine_id=self.machine_id, reset=True))

    # --- warm-up -----------------------------------------------------------------------------
    def warm_up(self) -> float:
        """Run each policy, the release check and the telemetry writer once
        (ThrowExecutor.warm_up, runtime.telemetry.warm), then accept throws; returns the seconds
        it took. Throws are refused "runtime warming up" until it returns; E-STOPs work meanwhile."""
        t0 = time.monotonic()
        self.executor.warm_up()  # no lock: the executor is idle (throws refused) and the policies are read only
        telemetry.warm()
        with self.lock:
            self.warming = None
            self._alive_s = None  # the warm-up's own time is no stall
            self.publish_info()
        took = time.monotonic() - t0
        log.info("warmed up in %.2f s: throws accepted", took)
        return took

    # --- shutdown and RuntimeInfo ---------------------------------------------------------------
    def shutdown(self) -> None:
        """Abort a running throw (neutral valves, result to the outbox) before the node exits."""
        with self.lock:
            if self.returning:
                self._stop_return("runtime shutting down")
            if self.executor.busy:
                self._publish(self.executor.abort("runtime shutting down"), self._stamp())

    def info(self) -> RuntimeInfo:
        """What this runtime is and can do now (policies as version = manifest name, sha256)."""
        with self.lock:
            ex, state = self.executor, self.latest_state
            online = self._online(ONLINE_TIMEOUT_S)
            why: str | None
            if self.estop_reason is not None:
                why = "E-STOP latched"
            elif self.warming is not None:
                why = self.warming
            elif self.verifier is None:
                why = NO_KEY
            elif ex.busy:
                why = f"busy with throw {ex.throw_id}"
            elif self.returning:
                why = f"returning to the ready pose ({100 * self._return_progress():.0f} %)"
            elif not online or state is None:  # online implies a state
                why = "machine offline"
            elif not ex.policies:
                why = "no policy loaded"
            else:
                why = f"machine fault: {state.machine_fault}" if state.machine_fault else self._start_refusal(state)
            return RuntimeInfo(
                machine_id=self.machine_id,
                busy=ex.busy,
                policies=[PolicyInfo(mode=m, version=p.version, sha256=p.sha256) for m, p in sorted(ex.policies.items())],
                machine_online=online,
                simulated=bool(state and state.simulated),
                epoch=self.epoch,
                estop_latched=self.estop_reason is not None,
                estop_reason=self.estop_reason,
                ready=why is None,
                not_ready_reason=why,
                phase=ex.phase,
                throw_id=ex.throw_id,
                recovery="return_to_ready" if why and why.startswith(POSE_REASONS) else None,
                returning=self.returning,
                return_progress=self._return_progress() if self.recovery is not None else None,
                return_result=self.recovery.status.result if self.recovery is not None else None,
                lease_holder=self.lease_holder,
                undeliverable_results=self.undeliverable(),
            )

    def handle_info(self) -> bytes:
        """-> RuntimeInfo (the queryable keys.info), stamped with this host's wall clock."""
        return encode(self.info().model_copy(update={"clock_unix_s": self.wall_clock()}))

    def publish_info(self, now_s: float | None = None) -> bool:
        """Publish RuntimeInfo on keys.runtime_state if it changed or INFO_PERIOD_S passed since
        the last one (stamped with this host's wall clock, which is not a change); returns True
        if it published."""
        with self.lock:
            info, now = self.info(), self.clock() if now_s is None else now_s
            if info == self._info_sent and now - self._info_sent_s < INFO_PERIOD_S:
                return False
            self._info_sent, self._info_sent_s = info, now
            self.send(keys.runtime_state(self.machine_id), encode(info.model_copy(update={"clock_unix_s": self.wall_clock()})))
            return True

    # --- outgoing -----------------------------------------------------------------------------
    def _online(self, within_s: float) -> bool:
        return self.latest_state is not None and self.clock() - self._state_rx_s <= within_s

    def _stamp(self) -> float:
        return self.latest_state.stamp_s if self.latest_state else 0.0

    def _publish(self, out: TickOutput, stamp_s: float) -> None:
        mid = self.machine_id
        u = np.zeros(4) if self.estop_reason is not None else np.clip(out.valve_u, -1.0, 1.0)
        self.send(keys.valve_cmd(mid), encode(ValveCommand(machine_id=mid, stamp_s=stamp_s, u=u.tolist(), epoch=self.epoch)))
        if out.gripper_open != self._gripper_sent:
            self.send(keys.gripper_cmd(mid), encode(GripperCommand(machine_id=mid, stamp_s=stamp_s, open=out.gripper_open)))
            self._gripper_sent = out.gripper_open
        for ev in out.events:
            log.info("throw %s: %s%s", ev.throw_id, ev.phase, f" ({ev.detail})" if ev.detail else "")
            status = ThrowStatus(machine_id=mid, stamp_s=ev.stamp_s, throw_id=ev.throw_id, phase=ev.phase, detail=ev.detail)
            self.send(keys.status(mid), encode(status))
        if out.finished is not None:
            try:
                result = out.finished.to_message(mid).model_copy(update={"server_id": self._throw_server or None})
                if self.verifier is not None:
                    result = sign(result, self.verifier.key, f"runtime:{mid}", self.epoch)
                self.on_result(result)
            except Exception:  # the outbox failing must not stop the control loop
                log.exception("could not store the result of throw %s", out.finished.throw_id)
