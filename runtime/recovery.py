"""Recovery action "return to the ready pose": the runtime drives the arm back to a pose from
which a throw can start, with its own joint-velocity controller (pure logic, no I/O, no clock:
time comes from ``MachineState.stamp_s``, like :mod:`runtime.executor`).

The ready pose keeps the cabin angle (turning the cabin is never a recovery move) and puts boom,
dipper and telescope at :data:`READY_POSE`. Motion: a straight line in joint space, each
active joint's velocity reference proportional to its remaining error (gain
:data:`POSITION_GAIN_PER_S`), scaled so that all joints arrive together, capped at
:data:`SPEED_FRACTION` of the joint's speed limit and rate-limited to :data:`MAX_REF_ACCEL`
(rad/s², m/s²). The references go through :class:`runtime.controller.JointVelocityController`,
so its clipping and end-stop braking (limit ramps) apply as in a throw.

Ends:
* ``reached``: every active joint within :data:`POSITION_TOL` of the ready pose and slower than
  :data:`SETTLED_SPEED` for :data:`SETTLE_S`;
* ``failed``: a clearance violation (ground, cabin) that the start pose did not have appears on
  the way, no progress for :data:`STALL_S`, longer than :data:`TIMEOUT_S`, a non-finite state;
* ``stopped``: :meth:`ReturnToReady.stop` (E-STOP, lost machine link, machine fault).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.controller import ControlOutput, JointVelocityController
from runtime.machine import (
    ACTIVE_VELOCITY_LIMITS,
    JOINT_LOWER,
    JOINT_NAMES,
    JOINT_UPPER,
    NUM_ACTIVE,
    clearance_violations,
    forward_kinematics,
)
from runtime.protocol.messages import MachineState

READY_POSE = np.array([-0.8, 1.6, 0.6])
"""boom, dipper (rad), telescope (m) of the ready pose. CHOSEN: inside the start-pose box of
sim_twin.twin.initial_pose, the hanging gripper's centre 2.0 m above the ground and 4.8 m from the
turn axis (2.8 m outside the cabin cylinder), every joint at least 0.5 rad / 0.6 m from its ends."""
POSITION_GAIN_PER_S = 0.8
"""Velocity reference per unit of remaining error, 1/s. CHOSEN below the ~1.5 1/s that the
nominal valves' 0.10 s delay + 0.16 s lag allow without overshoot."""
SPEED_FRACTION = 0.3
"""Largest reference as a fraction of runtime.machine.ACTIVE_VELOCITY_LIMITS (a slow move)."""
MAX_REF_ACCEL = np.array([0.5, 0.3, 0.4, 0.5])
"""Largest change of the references per second (cabin, boom, dipper, telescope), rad/s², m/s²."""
POSITION_TOL = np.array([0.02, 0.02, 0.02])
"""Arrived: boom, dipper within 0.02 rad and telescope within 0.02 m of READY_POSE."""
SETTLED_SPEED = 0.02
SETTLE_S = 0.3
STALL_S = 5.0
TIMEOUT_S = 60.0


def pose_refusal(state: MachineState) -> str | None:
    """Why the machine cannot start a throw from this pose, or None: "joint at end: telescope"
    (an active joint within 1 mrad / 1 mm of its range end) or "pose outside the envelope:
    ground" / ": cabin" (runtime.machine.clearance_violations, which would fail the swing at
    its first tick)."""
    q, qd = np.asarray(state.q, dtype=float), np.asarray(state.qd, dtype=float)
    if not np.all(np.isfinite(q)) or not np.all(np.isfinite(qd)):
        return "machine state is not finite"
    ground, cabin, limit = clearance_violations(np, q, forward_kinematics(np, q, qd))
    if limit:
        at_end = [JOINT_NAMES[j] for j in range(1, 4) if q[j] <= JOINT_LOWER[j] + 1e-3 or q[j] >= JOINT_UPPER[j] - 1e-3]
        return f"joint at end: {', '.join(at_end)}"
    if ground or cabin:
        return f"pose outside the envelope: {'ground' if ground else 'cabin'}"
    return None


POSE_REASONS = ("joint at end", "pose outside the envelope")
"""Not-ready reasons of :func:`pose_refusal`: the return to the ready pose recovers from them."""


@dataclass(frozen=True)
class RecoveryStatus:
    """Where a return to the ready pose stands.

    Attributes:
        active: still moving.
        progress: 0..1, share of the start's largest remaining joint distance covered.
        result: None while active, else "reached the ready pose", "failed: <why>" or
            "stopped: <why>".
    """

    active: bool
    progress: float
    result: str | None


def ready_target(q) -> np.ndarray:
    """(4,) active joint targets: the current cabin angle, then READY_POSE."""
    return np.concatenate([[float(np.asarray(q, dtype=float)[0])], READY_POSE])


def _violations(q: np.ndarray) -> set[str]:
    ground, cabin, _limit = clearance_violations(np, q, forward_kinematics(np, q, np.zeros_like(q)))
    return {name for name, flag in (("ground", ground), ("cabin", cabin)) if flag}


class ReturnToReady:
    """One return to the ready pose, ticked at 100 Hz with the machine state.

    Args:
        q: (6,) joint positions at the start, rad / m.
        stamp_s: machine time of that state, s.
        controller: the joint-velocity controller to drive with (reset here).

    Raises:
        ValueError: ``q`` is not 6 finite values.
    """

    def __init__(self, q, stamp_s: float, controller: JointVelocityController):
        q = np.asarray(q, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError("return to ready needs 6 finite joint positions")
        self.target = ready_target(q)
        self.controller = controller
        self.controller.reset()
        self._allowed = _violations(q)  # what the start pose already violates may persist on the way out
        self._dist0 = max(self._distance(q), 1e-9)
        self._best = self._dist0
        self._start_s = self._best_s = stamp_s
        self._last_s: float | None = None
        self._settled_since: float | None = None
        self._ref = np.zeros(NUM_ACTIVE)
        self.status = RecoveryStatus(True, 0.0, None)

    def _distance(self, q: np.ndarray) -> float:
        """Largest remaining joint distance in seconds at full speed (joints compare fairly)."""
        return float(np.max(np.abs(self.target[1:] - q[1:4]) / ACTIVE_VELOCITY_LIMITS[1:]))

    def stop(self, why: str) -> ControlOutput:
        """End now (valves neutral) with result "stopped: <why>"; no effect once ended."""
        if self.status.active:
            self.status = RecoveryStatus(False, self.status.progress, f"stopped: {why}")
        return self.controller.neutral()

    def _end(self, result: str, progress: float) -> ControlOutput:
        self.status = RecoveryStatus(False, progress, result)
        return self.controller.neutral()

    def tick(self, q, qd, stamp_s: float) -> ControlOutput:
        """One 10 ms step: the valve commands for joint state (q, qd) (6,) at ``stamp_s``."""
        if not self.status.active:
            return self.controller.neutral()
        q, qd = np.asarray(q, dtype=float), np.asarray(qd, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            return self._end("failed: non-finite machine state", self.status.progress)
        dist = self._distance(q)
        progress = float(np.clip(1.0 - dist / self._dist0, 0.0, 1.0))
        new = _violations(q) - self._allowed
        if new:
            return self._end(f"failed: the way back would hit the {', '.join(sorted(new))}", progress)
        if dist < self._best - 0.01:
            self._best, self._best_s = dist, stamp_s
        if stamp_s - self._best_s > STALL_S:
            return self._end(f"failed: no progress for {STALL_S:.0f} s", progress)
        if stamp_s - self._start_s > TIMEOUT_S:
            return self._end(f"failed: not there within {TIMEOUT_S:.0f} s", progress)
        err = self.target[1:] - q[1:4]
        arrived = bool(np.all(np.abs(err) < POSITION_TOL) and np.all(np.abs(qd[1:4]) < SETTLED_SPEED))
        self._settled_since = (self._settled_since or stamp_s) if arrived else None
        if self._settled_since is not None and stamp_s - self._settled_since >= SETTLE_S:
            return self._end("reached the ready pose", 1.0)
        self.status = RecoveryStatus(True, progress, None)
        return self.controller.step(self._reference(err, stamp_s), q, qd)

    def _reference(self, err: np.ndarray, stamp_s: float) -> np.ndarray:
        """(4,) velocity references: proportional, synchronised, capped and rate-limited."""
        vmax = SPEED_FRACTION * ACTIVE_VELOCITY_LIMITS[1:]
        want = POSITION_GAIN_PER_S * err
        # the same time scale for every joint (straight line in joint space): shrink all
        # references by the factor the most limited joint needs
        scale = float(np.min(np.where(np.abs(want) > vmax, vmax / np.maximum(np.abs(want), 1e-12), 1.0)))
        ref = np.concatenate([[0.0], want * scale])  # the cabin holds still
        dt = 0.01 if self._last_s is None else float(np.clip(stamp_s - self._last_s, 0.0, 0.1))
        self._last_s = stamp_s
        step = MAX_REF_ACCEL * dt
        self._ref = self._ref + np.clip(ref - self._ref, -step, step)
        return self._ref
