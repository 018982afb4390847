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

The law is written once, elementwise against an array module ``xp`` (:func:`_pid_ff` and the
helpers below it). :func:`pid_ff_law` runs it on (4,) arrays (jax.numpy in the MJX training
environment, numpy in tests); :meth:`JointVelocityController.step` runs it on each joint's Python
floats with runtime.float_xp (NumPy's functions for floats), which is several times cheaper than
the (4,)-array calls and gives the same doubles (tests/test_controller.py, tests/test_float_xp.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from types import ModuleType, SimpleNamespace

import numpy as np

from runtime import float_xp
from runtime.machine import ACTIVE_VELOCITY_LIMITS, JOINT_LOWER, JOINT_UPPER, NUM_ACTIVE
from runtime.observation import PHYSICS_PERIOD_S

_NEGLIGIBLE_REF = 1e-3  # |r| / v_max below this gets no dead-band compensation


def _per_joint(value) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, dtype=float), (NUM_ACTIVE,)).copy()


@dataclass(frozen=True)
class ControllerGains:
    """Gains and safety parameters, each a scalar or (4,) per active joint; stored as read-only
    (4,) float arrays (the dataclass is frozen: make another, e.g. with dataclasses.replace).

    Raises:
        ValueError: a value negative or not finite, or ``dead_band_comp`` >= 1.

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
            v.flags.writeable = False
            object.__setattr__(self, name, v)  # a frozen dataclass sets its own fields this way
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

    Unlimited joints (cabin_turn) always get 1. The arithmetic is :func:`_stop_positions` and
    :func:`_ramp_scale`, which :func:`pid_ff_law` runs too.
    """
    if qd_active is None:
        q_up = q_lo = q_active
    else:
        p_up, p_lo = (None, None) if peaks is None else (peaks[0], peaks[1])
        q_up, q_lo = _stop_positions(xp, gains, q_active, qd_active, p_up, p_lo)
    return _ramp_scale(xp, gains, JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE], qd_ref, q_up, q_lo)


def peak_decay(xp: ModuleType, gains: ControllerGains, dt_s: float):
    """(4,) factor by which a commanded-velocity peak decays in one step of ``dt_s`` seconds:
    exp(-dt / command_hold_s), 0 where ``command_hold_s`` is 0 (the term disabled)."""
    hold = gains.command_hold_s
    return xp.where(hold > 0, xp.exp(-dt_s / xp.maximum(hold, 1e-9)), 0.0)


def commanded_peaks(xp: ModuleType, gains: ControllerGains, vmax, dt_s: float, peaks, u):
    """Update the (2, 4) commanded-velocity peaks with this step's valve command.

    The velocity a valve command asks for is ``u * vmax`` (an upper bound: the dead band only
    lowers it). Each peak decays as exp(-dt / command_hold_s) and is raised to the new command
    in its direction: row 0 holds the largest recent velocity towards the upper limits (>= 0),
    row 1 the most negative towards the lower ones (<= 0). A command sent now reaches the joint
    only after the valve's transport delay and lag; the peak carries it over that time.
    The arithmetic is :func:`_raise_peaks`, which :func:`pid_ff_law` runs too.
    """
    up, lo = _raise_peaks(xp, gains, peak_decay(xp, gains, dt_s), peaks[0], peaks[1], u * vmax)
    return xp.stack([up, lo])


def pid_ff_law(xp: ModuleType, gains: ControllerGains, vmax, dt_s: float, r, q_a, qd_a, integral, prev_err, peaks=None):
    """The controller's arithmetic for one step on (4,) arrays (the MJX training environment's).

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

    The arithmetic is :func:`_pid_ff`, elementwise; JointVelocityController.step runs the same
    function on Python floats, joint by joint (runtime.float_xp).
    """
    lower, upper = JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE]
    if peaks is None:
        u, r, integral, err, _, _ = _pid_ff(xp, gains, vmax, lower, upper, None, dt_s, r, q_a, qd_a, integral, prev_err, None, None)
        return u, r, integral, err, None
    decay = peak_decay(xp, gains, dt_s)
    u, r, integral, err, up, lo = _pid_ff(xp, gains, vmax, lower, upper, decay, dt_s, r, q_a, qd_a, integral, prev_err, peaks[0], peaks[1])
    return u, r, integral, err, xp.stack([up, lo])


# The law, written once. Each function is elementwise: its arguments are all (4,) arrays (or
# arrays broadcasting to (4,)) with ``xp`` numpy or jax.numpy, or all floats of one joint with
# ``xp`` runtime.float_xp. ``g`` is a ControllerGains, or for one joint an object with the same
# attribute names holding that joint's floats. Python ``if`` tests only what is None.


def _pid_ff(xp, g, vmax, lower, upper, decay, dt_s, r, q, qd, integral, prev_err, p_up, p_lo):
    """One step of the PI(D) + feed-forward law with the safety clipping (module docstring).

    Args: as :func:`pid_ff_law`, elementwise; lower, upper: the joint limits (rad / m, +-inf for
    cabin_turn); decay: :func:`peak_decay`; p_up, p_lo: the peaks' two rows (or both None).
    Returns (u, r, integral, err, p_up, p_lo), the peaks raised by u (None if None was given).
    """
    r = xp.clip(r, -vmax, vmax)
    q_up, q_lo = _stop_positions(xp, g, q, qd, p_up, p_lo)
    r = r * _ramp_scale(xp, g, lower, upper, r, q_up, q_lo)
    r_n = r / vmax
    active = xp.abs(r_n) > _NEGLIGIBLE_REF
    u_ff = xp.where(active, r_n * (1.0 - g.dead_band_comp) + xp.sign(r_n) * g.dead_band_comp, 0.0)
    err = (r - qd) / vmax
    d_err = (err - prev_err) / dt_s
    u_unsat = u_ff + g.kp * err + integral + g.kd * d_err
    # conditional integration: do not wind up while saturated in the error's direction
    saturated = (xp.abs(u_unsat) >= 1.0) & (xp.sign(u_unsat) == xp.sign(err))
    hold = saturated | (xp.abs(err) >= g.integral_band)
    integral = xp.where(hold, integral, integral + g.ki * err * dt_s)
    integral = xp.clip(integral, -g.integral_limit, g.integral_limit)
    u = xp.clip(u_ff + g.kp * err + integral + g.kd * d_err, -1.0, 1.0)
    if p_up is not None:
        p_up, p_lo = _raise_peaks(xp, g, decay, p_up, p_lo, u * vmax)
    return u, r, integral, err, p_up, p_lo


def _stop_positions(xp, g, q, qd, p_up, p_lo):
    """Where the joint will be ``stop_horizon_s`` later if it moves towards its upper / lower
    limit (never further back than ``q``), with the larger of the measured velocity and the
    commanded peak (p_up, p_lo; both None: the measured velocity alone)."""
    v_up, v_lo = qd, qd
    if p_up is not None:
        v_up, v_lo = xp.maximum(qd, p_up), xp.minimum(qd, p_lo)
    return xp.maximum(q, q + v_up * g.stop_horizon_s), xp.minimum(q, q + v_lo * g.stop_horizon_s)


def _ramp_scale(xp, g, lower, upper, r, q_up, q_lo):
    """The factor in [0, 1] for a reference ``r`` towards a limit (1 for r = 0 and for a joint
    without limits): a linear ramp over ``limit_ramp``, zero at ``limit_margin`` from the limit."""
    dist = xp.where(r > 0, upper - q_up, xp.where(r < 0, q_lo - lower, xp.inf))
    scale = xp.clip((dist - g.limit_margin) / xp.maximum(g.limit_ramp, 1e-9), 0.0, 1.0)
    return xp.where(xp.isfinite(dist), scale, 1.0)


def _raise_peaks(xp, g, decay, p_up, p_lo, v):
    """The commanded-velocity peaks decayed by ``decay`` and raised to the commanded velocity
    ``v`` in its direction (:func:`commanded_peaks`); zero where ``command_hold_s`` is 0."""
    on = g.command_hold_s > 0
    up = xp.where(on, xp.maximum(p_up * decay, v), 0.0)
    lo = xp.where(on, xp.minimum(p_lo * decay, v), 0.0)
    return xp.maximum(up, 0.0), xp.minimum(lo, 0.0)


class JointVelocityController:
    """PI(D) + feed-forward joint-velocity controller for the 4 active joints, 100 Hz.

    Args:
        gains: ControllerGains (defaults: tuned on the nominal simulated machine).
        velocity_limits: (4,) joint speed at full valve opening, rad/s and m/s (default
            runtime.machine.ACTIVE_VELOCITY_LIMITS); references are clipped to it.
        dt_s: control period, s (default 0.01).

    Raises:
        ValueError: a velocity limit <= 0 (also when ``velocity_limits`` is set later).

    ``gains``, ``velocity_limits`` and ``dt_s`` may be replaced between steps; the per-joint
    constants :meth:`step` reads are made again from them on the next step (ControllerGains is
    frozen and its arrays, like ``velocity_limits``, are read-only, so they cannot change in place).
    """

    def __init__(
        self,
        gains: ControllerGains | None = None,
        velocity_limits=ACTIVE_VELOCITY_LIMITS,
        dt_s: float = PHYSICS_PERIOD_S,
    ):
        self.gains = gains or ControllerGains()
        self.velocity_limits = velocity_limits
        self.dt_s = dt_s
        self.last: ControlOutput = ControlOutput(np.zeros(NUM_ACTIVE), np.zeros(NUM_ACTIVE), True)
        self.reset()

    @property
    def gains(self) -> ControllerGains:
        """The ControllerGains in use."""
        return self._gains

    @gains.setter
    def gains(self, value: ControllerGains) -> None:
        self._gains = value
        self._joints: tuple | None = None

    @property
    def velocity_limits(self) -> np.ndarray:
        """(4,) read-only velocity limits, rad/s and m/s."""
        return self._velocity_limits

    @velocity_limits.setter
    def velocity_limits(self, value) -> None:
        v = _per_joint(value)
        if np.any(v <= 0):
            raise ValueError("velocity limits must be > 0")
        v.flags.writeable = False
        self._velocity_limits = v
        self._joints = None

    @property
    def dt_s(self) -> float:
        """Control period, s."""
        return self._dt_s

    @dt_s.setter
    def dt_s(self, value: float) -> None:
        self._dt_s = float(value)
        self._joints = None

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

        The arithmetic is :func:`pid_ff_law`'s elementwise law (:func:`_pid_ff`), run joint by
        joint on Python floats with runtime.float_xp (:meth:`_law_floats`): about a fifth of the
        CPU time of the (4,)-array NumPy calls, the same doubles (tests/test_controller.py).
        """
        try:
            r = np.asarray(qd_ref, dtype=float).reshape(NUM_ACTIVE)
            q_a = np.asarray(q, dtype=float).reshape(-1)[:NUM_ACTIVE]
            qd_a = np.asarray(qd, dtype=float).reshape(-1)[:NUM_ACTIVE]
        except (TypeError, ValueError):
            return self.neutral()
        if q_a.shape != (NUM_ACTIVE,) or qd_a.shape != (NUM_ACTIVE,):
            return self.neutral()
        r_l, q_l, qd_l = r.tolist(), q_a.tolist(), qd_a.tolist()
        if not all(map(math.isfinite, r_l + q_l + qd_l)):
            return self.neutral()
        if self.dt_s > 0:
            u, r, self._integral, self._prev_err, self._peaks = self._law_floats(r_l, q_l, qd_l)
        else:  # a zero period divides by zero: numpy's inf/nan as before, not an exception
            with np.errstate(invalid="ignore", divide="ignore"):
                prev = self._prev_err if self._prev_err is not None else (r - qd_a) / self.velocity_limits
                u, r, self._integral, self._prev_err, self._peaks = pid_ff_law(
                    np, self.gains, self.velocity_limits, self.dt_s, r, q_a, qd_a, self._integral, prev, self._peaks
                )
        self.last = ControlOutput(u, r, False)
        return self.last

    def _joint_constants(self) -> tuple:
        """Per active joint: (its gains as floats under ControllerGains' names, vmax, lower and
        upper limit, the peaks' decay per step from NumPy's exp as :func:`pid_ff_law` computes it)."""
        g = self.gains
        names = [f.name for f in fields(ControllerGains)]
        per_joint = zip(*(getattr(g, n).tolist() for n in names))
        return tuple(
            (SimpleNamespace(**dict(zip(names, values))), vmax, lower, upper, decay)
            for values, vmax, lower, upper, decay in zip(
                per_joint, self.velocity_limits.tolist(), JOINT_LOWER[:NUM_ACTIVE].tolist(), JOINT_UPPER[:NUM_ACTIVE].tolist(),
                peak_decay(np, g, self.dt_s).tolist())
        )

    def _law_floats(self, r_l: list, q_l: list, qd_l: list):
        """:func:`pid_ff_law` with ``peaks`` for this controller's state, as :func:`_pid_ff` on
        the floats of each joint. Arguments are (4,) float lists (finite, checked by :meth:`step`);
        returns what pid_ff_law returns, as (4,) / (2, 4) arrays."""
        if self._joints is None:
            self._joints = self._joint_constants()
        dt = self.dt_s
        integ = self._integral.tolist()
        prev = None if self._prev_err is None else self._prev_err.tolist()
        p_up, p_lo = self._peaks.tolist()
        rows = []
        for j, (g, vmax, lower, upper, decay) in enumerate(self._joints):
            r, qd = r_l[j], qd_l[j]
            e_prev = (r - qd) / vmax if prev is None else prev[j]  # first step: the current error
            rows.append(_pid_ff(float_xp, g, vmax, lower, upper, decay, dt, r, q_l[j], qd, integ[j], e_prev, p_up[j], p_lo[j]))
        out = np.array(list(zip(*rows)))  # (6, 4) in one NumPy call; the rows do not overlap
        return out[0], out[1], out[2], out[3], out[4:6]
