"""The throw state machine, as pure logic: no I/O, no threads, no wall clock.

Time comes only from ``MachineState.stamp_s``. The same class runs inside the Zenoh runtime
(:mod:`runtime.node` via :mod:`runtime.service`) and directly in a Python loop in the twin's
evaluation and preview code::

    ex = ThrowExecutor({"2d": PolicyRunner.load(path)}, JointVelocityController())
    refusal = ex.start(ThrowRequest(...), state)
    while True:
        out = ex.tick(state)                  # one call per 100 Hz machine state
        machine.step(out.valve_u, out.gripper_open)
        state = <MachineState of the machine>
        if <payload landed>: out = ex.on_impact(report)
        if out.finished: break                # a ThrowOutcome

Phases (messages.ThrowPhase): preparing -> swinging -> released -> landed | failed | aborted.

* preparing: gripper commanded closed, valves neutral; wait until the payload is attached, the
  gripper closed and both passive joints slower than ``passive_still_radps``. Timeout -> failed.
  The executor never asks whether the machine is simulated: loading a payload is the machine's
  business (the simulated machine, sim_twin.twin.plant, reloads by itself after its payload landed).
* swinging: every SUBSTEPS-th tick (12.5 Hz) the observation is built from the history
  and the policy's aim target (the requested target, or a site-adapted version's aim correction
  of it: PolicyRunner.aim_target)
  (control-step history, newest first, filled with the swing-start state; previous action zeros),
  the policy runs and its action is decoded to velocity references and a release flag; the
  controller tracks the latest references at 100 Hz. The first release flag that passes the
  release check commands the gripper open (once per throw) -> released.
* release check (runtime.release_check, ``ExecutorConfig.release_check_radius_m``): on a release
  flag the impact point of a release now is predicted (MuJoCo over the gripper's opening delay,
  then drag-free flight); if it is farther than the radius from the REQUESTED target, the release
  is held: gripper closed, still swinging, a "swinging" event with the detail "release held:
  predicted impact X m from target"; later flags are checked again, and without a passing one
  the release timeout fails the throw with the payload held. The policy's observation is not
  touched (previous action = its raw action with the flag, opened = 0: as during the opening
  delay in training). The requested target, not an adapted version's aim point: the radius is a
  zone around the spot the operator asked for; the aim point may lie up to
  runtime.aim.MAX_OFFSET_M from it. If the predictor cannot be loaded (no MuJoCo / twin model on
  this runtime), :meth:`ThrowExecutor.start` refuses every throw (fail closed, with the reason)
  unless the check is switched off (radius None).
* released: the policy keeps running (paper Sec. III). :meth:`on_impact` -> landed, with the
  impact errors of runtime.throw_geometry.impact_errors.
* every tick of swinging/released: runtime.machine.clearance_violations (ground, cabin, joint
  limit), non-finite state, no release within ``release_timeout_s`` of swing start, a payload
  lost before the release command (the machine reports its gripper open or the payload no longer
  attached: a gripper fault or a slipping load; the arm stops at once instead of swinging on with
  nothing to throw), a gripper
  not reported open within ``opening_timeout_s`` of the release command (the gripper is then
  commanded closed again) and no impact within ``impact_timeout_s`` of the release command each
  end the throw as failed.
* finality: a throw that a watchdog stopped never resumes. Every tick of a throw (any phase)
  fails it "machine link lost: ..." when two consecutive machine states lie more than
  ``max_state_gap_s`` apart in machine time (the machine or its link stalled: the machine's
  valve watchdog has put the valves neutral meanwhile), or when the machine reports that its
  valve watchdog tripped since the throw started (``MachineState.watchdog_trips`` grew). The
  runtime's own stalls are judged by runtime.service (monotonic time between its ticks), which
  calls :meth:`ThrowExecutor.stop_arm`. A throw that has already released is not failed by a
  watchdog: its payload flies on, so the arm is held with neutral valves for good (a "released"
  event with the detail "arm stopped: <reason>") and the throw still lands on its impact report
  (or fails at the impact timeout).

Once a throw ends the executor is idle: valves neutral (references zero), gripper command kept
(but for a gripper that did not open, commanded closed).
Every tick of a throw is recorded (runtime.telemetry.TelemetryRecorder).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from runtime.controller import JointVelocityController
from runtime.machine import NUM_ACTIVE, clearance_violations, forward_kinematics
from runtime.observation import (
    HISTORY_STEPS,
    SUBSTEPS,
    build_observation,
    decode_action,
    num_actions,
)
from runtime.outcome import PhaseEvent, ThrowOutcome, TickOutput
from runtime.policy import PolicyError, PolicyRunner
from runtime.protocol.messages import ImpactReport, MachineState, ThrowRequest
from runtime.recovery import READY_POSE
from runtime.release_check import DEFAULT_RADIUS_M, ReleaseCheck
from runtime.telemetry import TelemetryRecorder
from runtime.throw_geometry import impact_errors, target_refusal

log = logging.getLogger(__name__)


@dataclass
class ExecutorConfig:
    """Timeouts and thresholds (seconds of machine time, rad/s).

    Attributes:
        prepare_timeout_s: longest wait in preparing (payload loaded, gripper closed, at rest).
        passive_still_radps: passive joints must be slower than this to start swinging.
        release_timeout_s: the policy must release within this time of swing start.
        impact_timeout_s: an impact must be reported within this time of the release command.
        opening_timeout_s: the machine must report its gripper open (``MachineState.gripper_open``)
            within this time of the release command, or the throw fails "gripper did not open" and
            the gripper is commanded closed again. The opening command is sent once and never again
            (runtime.service sends gripper commands on change): a machine drops an opening command
            that answers a state older than runtime.protocol.messages.STALE_COMMAND_S (a stalled
            runtime or link), and a resent one would release late, where nobody aimed. CHOSEN 1.0 s:
            about four times the identified opening delay (258 ms mean, 15 ms standard deviation
            over 39 releases, ../shared/reference/machine-spec.md) and three times the site matrix's
            worn gripper (0.34 s).
        release_check_radius_m: a release flag whose predicted impact (runtime.release_check) is
            farther than this from the requested target is held, m; None switches the check off.
            CHOSEN 3.0 m: well above the predictor's error on normal throws of the deployed
            policies (p99 <= 0.55 m nominal, <= 0.8 m on slow_hydraulics but 2.3 m in its 3D
            9.5 m cell; the largest predicted distance of a throw that landed within 3 m was 1.2 m;
            runtime.release_check, reports/release_check_accuracy.json in reports/ARCHIVE.md), far below the 5-21 m of the wild releases.
        max_state_gap_s: two machine states of a running throw further apart than this (machine
            time, s) fail it (finality, module docstring). CHOSEN 0.2 s: the runtime's link
            timeout (runtime.service.LINK_TIMEOUT_S), twice the simulated machine's valve
            watchdog (sim_twin.twin.plant.VALVE_WATCHDOG_S) and four periods of a resting machine's
            20 Hz states.
        record_ticks: keep every tick in the throw's telemetry (ThrowOutcome.telemetry rows);
            False keeps only its phase events. The twin's previews (sim_twin.preview), which read
            only how a throw ended, turn it off: a tenth of their rollouts' time went into rows
            nobody read. Nothing the executor commands depends on it.
    """

    prepare_timeout_s: float = 20.0
    passive_still_radps: float = 0.05
    release_timeout_s: float = 10.0
    impact_timeout_s: float = 6.0
    opening_timeout_s: float = 1.0
    release_check_radius_m: float | None = DEFAULT_RADIUS_M
    max_state_gap_s: float = 0.2
    record_ticks: bool = True


@dataclass
class _Throw:
    request: ThrowRequest
    policy: PolicyRunner
    start_stamp_s: float
    aim_m: np.ndarray  # the target the policy is given (runtime.aim: the site's aim correction)
    phase: str = "preparing"
    swing_stamp_s: float = 0.0
    swing_ticks: int = 0
    q_hist: np.ndarray = field(default_factory=lambda: np.zeros((HISTORY_STEPS, 6)))  # (policy.history_steps, 6) from the swing on
    qd_hist: np.ndarray = field(default_factory=lambda: np.zeros((HISTORY_STEPS, 6)))
    prev_action: np.ndarray | None = None
    qd_ref: np.ndarray = field(default_factory=lambda: np.zeros(NUM_ACTIVE))
    release_stamp_s: float | None = None
    opening_stamp_s: float | None = None
    watchdog_trips: int | None = None  # the machine's valve-watchdog count at the start (None: not reported)
    arm_stopped: str | None = None  # why a watchdog stopped the arm after the release (valves neutral for good)
    recorder: TelemetryRecorder = field(default_factory=TelemetryRecorder)


def _pushed(hist: np.ndarray, newest: np.ndarray) -> np.ndarray:
    """A new (H, 6) history: ``newest`` (6,) in row 0, ``hist``'s rows 0..N-2 after it
    (np.roll by one row and the new row written in, at a third of the cost)."""
    out = np.empty_like(hist)
    out[1:] = hist[:-1]
    out[0] = newest
    return out


def _state_finite(state: MachineState) -> bool:
    """Six positions, six velocities and a stamp, all finite (math.isfinite: as np.isfinite for
    numbers, a few microseconds less on every 10 ms tick)."""
    return len(state.q) == 6 and len(state.qd) == 6 and all(map(math.isfinite, (*state.q, *state.qd, state.stamp_s)))


class ThrowExecutor:
    """Runs one throw at a time. Not thread-safe: callers serialise access (the node uses a lock).

    Args:
        policies: loaded policies by mode ("2d", "3d"); each runner's ``mode`` must match its key.
        controller: the joint-velocity controller (safety clipping lives there).
        config: timeouts and thresholds.
        release_check: the release check (runtime.release_check.ReleaseCheck: a predictor, or
            why there is none: then every throw is refused with that reason), used while
            ``config.release_check_radius_m`` is not None; None builds one for this executor
            (ReleaseCheck.load). Callers that make many executors in one thread hand the same one
            to each (it is not thread-safe).

    Raises:
        ValueError: if a policy is filed under the wrong mode.
    """

    def __init__(self, policies: dict[str, PolicyRunner], controller: JointVelocityController | None = None,
                 config: ExecutorConfig | None = None, release_check: ReleaseCheck | None = None):
        for mode, runner in policies.items():
            if runner.mode != mode:
                raise ValueError(f"policy {runner.version!r} is a {runner.mode} policy, filed under {mode!r}")
        self.policies = dict(policies)
        self.controller = controller or JointVelocityController()
        self.config = config or ExecutorConfig()
        self._throw: _Throw | None = None
        self._gripper_cmd = False
        self._events: list[PhaseEvent] = []
        self._finished: ThrowOutcome | None = None
        self._last_stamp_s: float | None = None
        self.unhealthy: dict[str, str] = {}
        """Policy SHA-256 -> why that version is unhealthy on this machine (it emitted a
        non-finite or misshaped action); throws with it are refused until another file is loaded."""
        self._predictor, self._check_unavailable = None, None
        if self.config.release_check_radius_m is not None:
            check = release_check or ReleaseCheck.load()
            self._predictor, self._check_unavailable = check.predictor, check.unavailable
            if self._predictor is None:
                log.error("release check unavailable (%s): every throw will be refused; install MuJoCo "
                          "(slinger-runtime[release-check]) or switch the check off", self._check_unavailable)

    # --- queries ----------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        return self._throw is not None

    @property
    def throw_id(self) -> str | None:
        return self._throw.request.throw_id if self._throw else None

    @property
    def phase(self) -> str | None:
        return self._throw.phase if self._throw else None

    def warm_up(self) -> None:
        """Run each policy once on a zero observation and the release check's predictor once from
        the ready pose, so that the first throw does not pay for the inference sessions' and
        MuJoCo's first calls in its control loop (runtime.service: no throw before warm-up)."""
        for runner in self.policies.values():
            runner.act(np.zeros(runner.manifest["observation_size"], dtype=np.float32))
        if self._predictor is not None:
            q = np.array([0.0, *READY_POSE, 0.0, 0.0])
            self._predictor.predict(q, np.zeros(6), np.zeros(NUM_ACTIVE))

    # --- commands ---------------------------------------------------------------------------
    def start(self, request: ThrowRequest, state: MachineState | None) -> str | None:
        """Begin a throw; returns the reason it is refused, or None when accepted.

        Args:
            request: the validated ThrowRequest.
            state: the latest machine state (None if none has arrived yet).

        Refused when: busy, no policy for the mode, the mode's policy version is marked unhealthy
        (:attr:`unhealthy`), no or non-finite machine state, or the
        target is not servable (runtime.throw_geometry.target_refusal with the policy's
        ``target_range_m`` and the current cabin angle).
        """
        if self._throw is not None:
            return f"runtime busy with throw {self._throw.request.throw_id!r}"
        policy = self.policies.get(request.mode)
        if policy is None:
            return f"no {request.mode} policy loaded on this runtime"
        if policy.sha256 in self.unhealthy:
            return f"policy {policy.version} is marked unhealthy on this machine: {self.unhealthy[policy.sha256]}"
        if state is None:
            return "no machine state received yet"
        if not _state_finite(state):
            return "machine state is not finite"
        if self._check_unavailable is not None:
            return (f"release check unavailable ({self._check_unavailable}); install MuJoCo "
                    "(slinger-runtime[release-check]) or switch the check off")
        refusal = target_refusal(request.mode, request.target_m, float(state.q[0]), policy.target_range_m)
        if refusal:
            return refusal
        self._throw = _Throw(request=request, policy=policy, start_stamp_s=state.stamp_s, aim_m=policy.aim_target(request.target_m),
                             watchdog_trips=state.watchdog_trips)
        self._last_stamp_s = state.stamp_s
        self._gripper_cmd = False
        self.controller.neutral()
        self._emit("preparing", state.stamp_s)
        return None

    def tick(self, state: MachineState) -> TickOutput:
        """Advance one 100 Hz machine state; returns the commands to send."""
        th = self._throw
        last, self._last_stamp_s = self._last_stamp_s, state.stamp_s
        if th is None:
            return self._output(self.controller.neutral())
        if not _state_finite(state):
            return self._finish("failed", "non-finite machine state", state.stamp_s)
        stopped = self._watchdog_stop(th, state, last)
        if stopped and th.arm_stopped is None:
            if th.phase != "released":
                return self._finish("failed", f"machine link lost: {stopped}", state.stamp_s)
            self._hold_arm(th, f"machine link lost: {stopped}", state.stamp_s)
        if th.phase == "preparing":
            return self._tick_preparing(th, state)
        return self._tick_swinging(th, state)

    def drain(self) -> TickOutput:
        """The last commands again with the events (and outcome) pending since the last output,
        without advancing the throw (e.g. to publish "preparing" right after :meth:`start`)."""
        return self._output(self.controller.last)

    def on_impact(self, report: ImpactReport) -> TickOutput:
        """The payload hit the ground: a released throw ends as landed. Ignored otherwise."""
        th = self._throw
        if th is None or th.phase != "released":
            return self.drain()
        impact = np.asarray(report.impact_pos_m, dtype=float)
        down, cross = impact_errors(th.request.target_m, impact)
        th.opening_stamp_s = report.opening_stamp_s
        end = max(report.impact_stamp_s, self._last_stamp_s or report.stamp_s)
        return self._finish(
            "landed",
            f"downrange {down:+.2f} m, crossrange {cross:+.2f} m",
            end,
            impact_m=impact,
            downrange_error_m=down,
            crossrange_error_m=cross,
            impact=report,
        )

    def abort(self, reason: str = "operator abort") -> TickOutput:
        """End the current throw as aborted (valves neutral). No effect when idle."""
        if self._throw is None:
            return self._output(self.controller.neutral())
        return self._finish("aborted", reason, self._last_stamp_s)

    def stop_arm(self, reason: str) -> TickOutput:
        """A watchdog stopped the arm (finality, module docstring): a throw that has not released
        ends failed with ``reason``; a released one holds the arm with neutral valves for good and
        keeps waiting for its impact. No effect when idle."""
        th = self._throw
        if th is None or th.phase != "released":
            return self.fail(reason)
        if th.arm_stopped is None:
            self._hold_arm(th, reason, self._last_stamp_s or th.start_stamp_s)
        return self._output(self.controller.neutral())

    def _hold_arm(self, th: _Throw, reason: str, stamp_s: float) -> None:
        """Hold the released throw ``th``'s arm with neutral valves for good (stop_arm)."""
        th.arm_stopped = reason
        log.warning("throw %s: arm stopped after the release (%s); awaiting the impact", th.request.throw_id, reason)
        self._emit("released", stamp_s, f"arm stopped: {reason}")

    def fail(self, reason: str) -> TickOutput:
        """End the current throw as failed (valves neutral), e.g. "machine link lost"."""
        if self._throw is None:
            return self._output(self.controller.neutral())
        return self._finish("failed", reason, self._last_stamp_s)

    def _watchdog_stop(self, th: _Throw, state: MachineState, last_stamp_s: float | None) -> str | None:
        """Why a watchdog has stopped the running throw ``th`` before ``state`` (finality, module
        docstring), or None."""
        gap = None if last_stamp_s is None else state.stamp_s - last_stamp_s
        if gap is not None and gap > self.config.max_state_gap_s:
            return f"machine states {gap:.2f} s apart (a watchdog stopped the arm)"
        trips = state.watchdog_trips
        if trips is not None and (th.watchdog_trips is None or trips > th.watchdog_trips):
            return "the machine's valve watchdog stopped the arm"
        return None

    # --- phases -----------------------------------------------------------------------------
    def _tick_preparing(self, th: _Throw, state: MachineState) -> TickOutput:
        cfg = self.config
        still = bool(np.all(np.abs(np.asarray(state.qd[4:6])) < cfg.passive_still_radps))
        if state.payload_attached and not state.gripper_open and still:
            return self._begin_swing(th, state)
        if state.stamp_s - th.start_stamp_s > cfg.prepare_timeout_s:
            return self._finish("failed", f"not ready to swing within {cfg.prepare_timeout_s:.0f} s (payload, gripper or passive joints)", state.stamp_s)
        out = self.controller.neutral()
        self._record(th, state, out.valve_u, out.qd_ref)
        return self._output(out)

    def _begin_swing(self, th: _Throw, state: MachineState) -> TickOutput:
        th.phase, th.swing_stamp_s, th.swing_ticks = "swinging", state.stamp_s, 0
        steps = th.policy.history_steps  # as many control steps as this policy reads (its manifest)
        th.q_hist = np.tile(np.asarray(state.q, dtype=float), (steps, 1))
        th.qd_hist = np.tile(np.asarray(state.qd, dtype=float), (steps, 1))
        th.prev_action = np.zeros(num_actions(th.request.mode), dtype=np.float32)
        self.controller.reset()
        self._emit("swinging", state.stamp_s)
        return self._tick_swinging(th, state)

    def _tick_swinging(self, th: _Throw, state: MachineState) -> TickOutput:
        cfg, now = self.config, state.stamp_s
        q, qd = np.asarray(state.q, dtype=float), np.asarray(state.qd, dtype=float)
        ground, cabin, limit = clearance_violations(np, q, forward_kinematics(np, q, qd))
        for flag, why in ((ground, "ground"), (cabin, "cabin"), (limit, "joint limit")):
            if flag:
                return self._finish("failed", f"clearance violation: {why}", now)
        if th.release_stamp_s is None and now - th.swing_stamp_s > cfg.release_timeout_s:
            return self._finish("failed", f"no release within {cfg.release_timeout_s:.0f} s", now)
        if th.release_stamp_s is None and (state.gripper_open or not state.payload_attached):
            why = "the gripper opened" if state.gripper_open else "the payload is no longer attached"
            return self._finish("failed", f"payload lost during the swing: {why} without a release command", now)
        if th.release_stamp_s is not None and now - th.release_stamp_s > cfg.impact_timeout_s:
            return self._finish("failed", f"no impact within {cfg.impact_timeout_s:.0f} s of release", now)
        if (th.release_stamp_s is not None and th.opening_stamp_s is None and not state.gripper_open
                and now - th.release_stamp_s > cfg.opening_timeout_s):
            self._gripper_cmd = False  # the payload is still held: an opening now would be a late release
            return self._finish("failed", f"gripper did not open within {cfg.opening_timeout_s:.1f} s of the release command "
                                "(the command was lost, or dropped at the machine as stale); payload still held", now)
        if th.arm_stopped is not None:  # a watchdog stopped the arm after the release: it stays stopped
            if th.opening_stamp_s is None and state.gripper_open:
                th.opening_stamp_s = now
            out = self.controller.neutral()
            self._record(th, state, out.valve_u, out.qd_ref)
            return self._output(out)
        release_flag = False
        if th.swing_ticks % SUBSTEPS == 0:
            failure, release_flag = self._control_step(th, state, q, qd)
            if failure:
                return self._finish("failed", failure, now)
        th.swing_ticks += 1
        if th.release_stamp_s is not None and th.opening_stamp_s is None and state.gripper_open:
            th.opening_stamp_s = now
        out = self.controller.step(th.qd_ref, q, qd)
        if release_flag and th.release_stamp_s is None:
            self._release_or_hold(th, now, q, qd, out.qd_ref)
        self._record(th, state, out.valve_u, out.qd_ref)
        return self._output(out)

    def _control_step(self, th: _Throw, state: MachineState, q: np.ndarray, qd: np.ndarray) -> tuple[str | None, bool]:
        """One 12.5 Hz policy step; returns (a failure reason or None, the policy's release flag)."""
        th.q_hist, th.qd_hist = _pushed(th.q_hist, q), _pushed(th.qd_hist, qd)
        mode = th.request.mode
        opened = 1.0 if state.gripper_open else 0.0
        obs = build_observation(np, mode, th.q_hist, th.qd_hist, th.prev_action, th.aim_m, opened)
        try:
            action = np.asarray(th.policy.act(obs), dtype=np.float32)
        except PolicyError as e:
            return f"policy error: {e}", False
        if action.shape != (num_actions(mode),) or not np.all(np.isfinite(action)):
            reason = f"it returned a non-finite or misshaped action in throw {th.request.throw_id}"
            self.unhealthy[th.policy.sha256] = reason
            log.error("policy %s marked unhealthy: %s", th.policy.version, reason)
            return "policy returned a non-finite or misshaped action", False
        th.prev_action = action
        qd_ref, release = decode_action(np, mode, action)
        th.qd_ref = np.asarray(qd_ref, dtype=float)
        return None, bool(release)

    def _release_or_hold(self, th: _Throw, now: float, q: np.ndarray, qd: np.ndarray, qd_ref: np.ndarray) -> None:
        """A release flag: command the gripper open (-> released), or hold it (module docstring)."""
        held = self._release_held(th, q, qd, qd_ref)
        if held:
            self._emit("swinging", now, held)
            return
        th.release_stamp_s = now
        self._gripper_cmd = True
        th.phase = "released"
        self._emit("released", now)

    def _release_held(self, th: _Throw, q: np.ndarray, qd: np.ndarray, qd_ref: np.ndarray) -> str | None:
        """Why a release flag at measured state q, qd (6,) with the controller's references
        qd_ref (4,) of that tick (after safety clipping) is held, or None to release."""
        radius = self.config.release_check_radius_m
        if radius is None or self._predictor is None:
            return None
        try:
            hit = self._predictor.predict(q, qd, qd_ref)
        except ValueError as e:
            return f"release held: impact prediction failed ({e})"
        miss = float(np.hypot(*(hit[:2] - np.asarray(th.request.target_m, dtype=float)[:2])))
        if miss > radius:
            return f"release held: predicted impact {miss:.1f} m from target"
        return None

    # --- helpers ----------------------------------------------------------------------------
    def _emit(self, phase: str, stamp_s: float, detail: str | None = None) -> None:
        th = self._throw
        assert th is not None, "no throw running"
        self._events.append(PhaseEvent(th.request.throw_id, phase, stamp_s, detail))
        th.recorder.event(stamp_s, phase, detail)

    def _record(self, th: _Throw, state: MachineState, valve_u, qd_ref) -> None:
        if not self.config.record_ticks:
            return
        th.recorder.record(
            state.stamp_s, state.q, state.qd, qd_ref, valve_u, self._gripper_cmd, state.gripper_open,
            th.phase, state.payload_pos_m, state.payload_vel_mps,
        )

    def _finish(self, status: str, detail: str | None, stamp_s: float | None, **result) -> TickOutput:
        th = self._throw
        assert th is not None, "no throw running"
        end = th.start_stamp_s if stamp_s is None else stamp_s
        self._emit(status, end, detail)
        self._finished = ThrowOutcome(
            throw_id=th.request.throw_id,
            mode=th.request.mode,
            status=status,
            failure_reason=None if status == "landed" else detail,
            target_m=np.asarray(th.request.target_m, dtype=float),
            policy_version=th.policy.version,
            policy_sha256=th.policy.sha256,
            start_stamp_s=th.start_stamp_s,
            end_stamp_s=end,
            telemetry=th.recorder,
            release_stamp_s=th.release_stamp_s,
            opening_stamp_s=th.opening_stamp_s,
            **result,
        )
        self._throw = None
        return self._output(self.controller.neutral())

    def _output(self, ctrl) -> TickOutput:
        events, self._events = tuple(self._events), []
        finished, self._finished = self._finished, None
        return TickOutput(ctrl.valve_u.copy(), ctrl.qd_ref.copy(), self._gripper_cmd, events, finished)
