"""Low-level joint-velocity controller: references (rad/s, m/s) -> valve commands in [-1, 1].

On HEAP "a PID joint velocity controller with feed-forward commands the valves" (Jud et al.
2021, via shared/reference/machine-spec.md); the throwing paper's policy outputs joint-velocity
references at 12.5 Hz and this controller tracks them at 100 Hz. It is also the runtime's safety
layer (docs/architecture.md: "safety clipping lives in runtime's controller, never in the policy"):

* references are clipped to :data:`runtime.machine.ACTIVE_VELOCITY_LIMITS`;
* near a joint limit the reference *towards* that limit ramps linearly to zero (motion away from
  the limit is never restricted). The distance is taken from where the joint will be once the
  valves have answered (predictive limit handling): hydraulic valves keep a joint moving for
  their transport delay plus about one lag time constant after the command changes, so the
  ramp uses q + v * ``stop_horizon_s`` when the joint moves towards the limit, where v is the
  larger (towards that limit) of the measured velocity and the velocity the controller has
  recently COMMANDED (valve command x full speed, held as a peak that decays with
  ``command_hold_s``): with a long transport delay a joint can still stand or even move away
  while the valves already carry a full command towards the end, and judged from its measured
  velocity alone it then accelerates into the end (3D throws with a 0.2 s valve delay: 7 % of
  them ended on the telescope's end stop before this term). With the nominal valves (0.10 s
  delay, 0.16 s lag) and up to slow ones (0.2 s, 0.3 s) the joints stop before their ends
  (tests/test_controller.py);
* any non-finite input gives neutral valves (all zeros) and clears the controller's state.

Per active joint i (ACTIVE_JOINTS order: cabin_turn, boom, dipper, telescope), with
e = (r - qd) / v_max (normalised velocity error) and r the clipped reference::

    u_ff = r / v_max * (1 - c) + sign(r) * c      (c = dead_band_comp, only if |r| > eps)
    u    = clip(u_ff + kp * e + ki * integral(e) + kd * de/dt, -1, 1)

With ``c`` equal to the valve dead band the feed-forward inverts the valve's dead band exactly
(flow = (|u| - db) / (1 - db)); the integrator removes what the feed-forward misses (gravity on
the servo, a wrong dead-band estimate). Anti-windup: the integrator is clamped to
``integral_limit`` and does not integrate further while the output is saturated in the same
direction as the error (conditional integration), nor while the error is larger than
``integral_band`` (a transient the feed-forward and P term are handling: integrating it only
makes overshoot that bleeds off slowly).

Gains (``ControllerGains`` defaults) were tuned in closed loop against the simulated machine with
the earlier nominal profile (dead band 0.05, delay 0.04 s, lag 0.1 s); on the current nominal
(0.10 s delay, 0.16 s lag, sim_twin.twin.hydraulics) the same gains rise to 90 % within 0.55 s without
big overshoot (tests/test_controller.py). Earlier figures: kp 0.6, ki 3.0 1/s, integral band
0.05, integral limit 0.3. Measured velocity steps (every joint alike) of 0.1 / 0.3 / 0.7 v_max:
90 % rise in 0.13-0.16 s, overshoot 6 / 2 / 0 %, error after 1.5 s < 0.5 %. Feed-forward alone
rises in 0.29 s. On a worse machine (dead band 0.10 with compensation 0.05, delay 0.08 s, lag
0.2 s) the same gains rise in 0.31-0.67 s without overshoot. tests/test_controller.py checks it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS, JOINT_LOWER, JOINT_UPPER, NUM_ACTIVE
from runtime.observation import PHYSICS_PERIOD_S

_NEGLIGIBLE_REF = 1e-3  # |r| / v_max below this gets no dead-band compensation


def _per_joint(value) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, dtype=float), (NUM_ACTIVE,)).copy()


@dataclass
class ControllerGains:
    """Gains and safety parameters, each a scalar or (4,) per active joint.

    Attributes:
        kp: proportional gain on the normalised velocity error (valve fraction per unit error).
        ki: integral gain, 1/s.
        kd: derivative gain, s (on the measured error, usually 0: the measured velocity is noisy
            on hardware and the valve lag already damps).
        dead_band_comp: valve dead-band compensation, fraction of full command.
        integral_limit: clamp of the integral term's contribution to u.
        integral_band: the integrator runs only while |normalised error| is below this.
        limit_margin: distance from a joint limit (rad / m) at which the reference towards the
            limit reaches zero. runtime.machine.clearance_violations flags a limit at 1 mrad.
        limit_ramp: distance (rad / m) over which the reference towards a limit ramps down to
            zero, ending at ``limit_margin``.
        stop_horizon_s: how far ahead (s) the joint's motion is extrapolated for the limit ramp:
            the valves' transport delay plus lag time constant (nominal simulated machine 0.26 s;
            0.45 s CHOSEN to also cover slow valves up to 0.2 s + 0.25 s).
        command_hold_s: decay time constant (s) of the commanded-velocity peak the limit ramp
            also extrapolates with (see :func:`commanded_peaks`); CHOSEN 0.25 s, about the
            longest valve transport delay the runtime is expected to meet (HEAP-like 0.2 s) plus
            margin. 0 disables the term.
    """

    kp: np.ndarray = field(default_factory=lambda: _per_joint(0.6))
    ki: np.ndarray = field(default_factory=lambda: _per_joint(3.0))
    kd: np.ndarray = field(default_factory=lambda: _per_joint(0.0))
    dead_band_comp: np.ndarray = field(default_factory=lambda: _per_joint(0.05))
    integral_limit: np.ndarray = field(default_factory=lambda: _per_joint(0.3))
    integral_band: np.ndarray = field(default_factory=lambda: _per_joint(0.05))
    limit_margin: np.ndarray = field(default_factory=lambda: _per_joint(0.03))
    limit_ramp: np.ndarray = field(default_factory=lambda: _per_joint(0.15))
    stop_horizon_s: np.ndarray = field(default_factory=lambda: _per_joint(0.45))
    command_hold_s: np.ndarray = field(default_factory=lambda: _per_joint(0.25))

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            v = _per_joint(getattr(self, name))
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"controller {name} must be finite and >= 0, got {v}")
            setattr(self, name, v)
        if np.any(self.dead_band_comp >= 1):
            raise ValueError("dead_band_comp must be < 1")


@dataclass(frozen=True)
class ControlOutput:
    """What the controller sent (lerobot habit: report the action after safety clipping).

    Attributes:
        valve_u: (4,) valve commands in [-1, 1], ACTIVE_JOINTS order.
        qd_ref: (4,) the reference actually tracked after clipping and limit ramps, rad/s, m/s.
        neutral: True when the input was rejected (non-finite) and the valves are neutral.
    """

    valve_u: np.ndarray
    qd_ref: np.ndarray
    neutral: bool = False


def limit_ramp_scale(q_active, qd_ref, gains: ControllerGains, xp: ModuleType = np, qd_active=None, peaks=None) -> np.ndarray:
    """(4,) factors in [0, 1] scaling each reference that points towards a nearby joint limit.

    Args:
        q_active: (4,) active joint positions, rad / m.
        qd_ref: (4,) references, rad/s / m/s (only their signs are read).
        gains: supplies ``limit_margin``, ``limit_ramp`` and ``stop_horizon_s``.
        xp: array module (numpy on the machine, jax.numpy in training).
        qd_active: (4,) measured joint velocities; when given, a joint moving towards a limit is
            judged from where it will be ``stop_horizon_s`` later (never from further back than
            where it is now).
        peaks: (2, 4) recently commanded velocities, [towards upper (>= 0), towards lower
            (<= 0)] (:func:`commanded_peaks`); when given, the extrapolation towards each limit
            uses the larger of the measured and the commanded velocity.

    Unlimited joints (cabin_turn) always get 1.
    """
    lower, upper = JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE]
    if qd_active is None:
        q_up = q_lo = q_active
    else:
        v_up, v_lo = qd_active, qd_active
        if peaks is not None:
            v_up, v_lo = xp.maximum(qd_active, peaks[0]), xp.minimum(qd_active, peaks[1])
        q_up = xp.maximum(q_active, q_active + v_up * gains.stop_horizon_s)
        q_lo = xp.minimum(q_active, q_active + v_lo * gains.stop_horizon_s)
    dist = xp.where(qd_ref > 0, upper - q_up, xp.where(qd_ref < 0, q_lo - lower, xp.inf))
    scale = xp.clip((dist - gains.limit_margin) / xp.maximum(gains.limit_ramp, 1e-9), 0.0, 1.0)
    return xp.where(xp.isfinite(dist), scale, 1.0)


def commanded_peaks(xp: ModuleType, gains: ControllerGains, vmax, dt_s: float, peaks, u):
    """Update the (2, 4) commanded-velocity peaks with this step's valve command.

    The velocity a valve command asks for is ``u * vmax`` (an upper bound: the dead band only
    lowers it). Each peak decays as exp(-dt / command_hold_s) and is raised to the new command
    in its direction: row 0 holds the largest recent velocity towards the upper limits (>= 0),
    row 1 the most negative towards the lower ones (<= 0). A command sent now reaches the joint
    only after the valve's transport delay and lag; the peak carries it over that time.
    """
    hold = gains.command_hold_s
    decay = xp.where(hold > 0, xp.exp(-dt_s / xp.maximum(hold, 1e-9)), 0.0)
    v = u * vmax
    up = xp.where(hold > 0, xp.maximum(peaks[0] * decay, v), 0.0)
    lo = xp.where(hold > 0, xp.minimum(peaks[1] * decay, v), 0.0)
    return xp.stack([xp.maximum(up, 0.0), xp.minimum(lo, 0.0)])


def pid_ff_law(xp: ModuleType, gains: ControllerGains, vmax, dt_s: float, r, q_a, qd_a, integral, prev_err, peaks=None):
    """The controller's arithmetic for one step, shared with the MJX training environment.

    Args:
        xp: array module.
        gains: ControllerGains.
        vmax: (4,) velocity limits, rad/s and m/s.
        dt_s: control period, s.
        r: (4,) references; q_a, qd_a: (4,) active joint positions and velocities.
        integral: (4,) integrator state (its contribution to u); prev_err: (4,) previous
            normalised error (pass the current error on the first step).
        peaks: (2, 4) commanded-velocity peaks (:func:`commanded_peaks`; zeros at the start),
            or None to judge the limits from the measured velocity alone.

    Returns:
        (u (4,) valve commands in [-1, 1], r (4,) reference after clipping and limit ramps,
        integral (4,) new integrator state, err (4,) normalised error, peaks (2, 4) updated
        with u (None if None was given)).
    """
    g = gains
    r = xp.clip(r, -vmax, vmax)
    r = r * limit_ramp_scale(q_a, r, g, xp, qd_active=qd_a, peaks=peaks)
    r_n = r / vmax
    active = xp.abs(r_n) > _NEGLIGIBLE_REF
    u_ff = xp.where(active, r_n * (1.0 - g.dead_band_comp) + xp.sign(r_n) * g.dead_band_comp, 0.0)
    err = (r - qd_a) / vmax
    d_err = (err - prev_err) / dt_s
    u_unsat = u_ff + g.kp * err + integral + g.kd * d_err
    # conditional integration: do not wind up while saturated in the error's direction
    saturated = (xp.abs(u_unsat) >= 1.0) & (xp.sign(u_unsat) == xp.sign(err))
    hold = saturated | (xp.abs(err) >= g.integral_band)
    integral = xp.where(hold, integral, integral + g.ki * err * dt_s)
    integral = xp.clip(integral, -g.integral_limit, g.integral_limit)
    u = xp.clip(u_ff + g.kp * err + integral + g.kd * d_err, -1.0, 1.0)
    if peaks is not None:
        peaks = commanded_peaks(xp, g, vmax, dt_s, peaks, u)
    return u, r, integral, err, peaks


class JointVelocityController:
    """PI(D) + feed-forward joint-velocity controller for the 4 active joints, 100 Hz.

    Args:
        gains: ControllerGains (defaults: tuned on the nominal simulated machine).
        velocity_limits: (4,) joint speed at full valve opening, rad/s and m/s (default
            runtime.machine.ACTIVE_VELOCITY_LIMITS); references are clipped to it.
        dt_s: control period, s (default 0.01).
    """

    def __init__(
        self,
        gains: ControllerGains | None = None,
        velocity_limits=ACTIVE_VELOCITY_LIMITS,
        dt_s: float = PHYSICS_PERIOD_S,
    ):
        self.gains = gains or ControllerGains()
        self.velocity_limits = _per_joint(velocity_limits)
        if np.any(self.velocity_limits <= 0):
            raise ValueError("velocity limits must be > 0")
        self.dt_s = float(dt_s)
        self.last: ControlOutput = ControlOutput(np.zeros(NUM_ACTIVE), np.zeros(NUM_ACTIVE), True)
        self.reset()

    def reset(self) -> None:
        """Clear the integrator and derivative memory (call at the start of every throw)."""
        self._integral = np.zeros(NUM_ACTIVE)
        self._prev_err: np.ndarray | None = None
        self._peaks = np.zeros((2, NUM_ACTIVE))

    def neutral(self) -> ControlOutput:
        """Neutral valves, state cleared; returns (and records as sent) the neutral output."""
        self.reset()
        self.last = ControlOutput(np.zeros(NUM_ACTIVE), np.zeros(NUM_ACTIVE), True)
        return self.last

    def step(self, qd_ref, q, qd) -> ControlOutput:
        """One 10 ms control step.

        Args:
            qd_ref: (4,) velocity references of the active joints, rad/s and m/s.
            q: (6,) measured joint positions (JOINT_NAMES order), rad / m.
            qd: (6,) measured joint velocities, rad/s and m/s.

        Returns:
            ControlOutput with the valve commands and the reference after safety clipping;
            neutral (zeros) if any input is non-finite or has the wrong shape.
        """
        try:
            r = np.asarray(qd_ref, dtype=float).reshape(NUM_ACTIVE)
            q_a = np.asarray(q, dtype=float).reshape(-1)[:NUM_ACTIVE]
            qd_a = np.asarray(qd, dtype=float).reshape(-1)[:NUM_ACTIVE]
        except (TypeError, ValueError):
            return self.neutral()
        if q_a.shape != (NUM_ACTIVE,) or qd_a.shape != (NUM_ACTIVE,):
            return self.neutral()
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(q_a)) and np.all(np.isfinite(qd_a))):
            return self.neutral()

        with np.errstate(invalid="ignore"):
            prev = self._prev_err if self._prev_err is not None else (r - qd_a) / self.velocity_limits
            u, r, self._integral, self._prev_err, self._peaks = pid_ff_law(
                np, self.gains, self.velocity_limits, self.dt_s, r, q_a, qd_a, self._integral, prev, self._peaks
            )
        self.last = ControlOutput(u, r, False)
        return self.last
