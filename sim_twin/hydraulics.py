"""Hydraulic valve-to-joint-velocity model of the simulated machine (machine-spec.md,
"Hydraulic actuation"): per active joint, valve command u in [-1, 1] -> dead band -> transport
delay -> first-order lag -> rate-limited joint velocity (:class:`ValveModel`), then the cylinder
(:func:`cylinder_step`): the oil displaced by that flow sets where the joint is, closed valves
hold the load (oil is incompressible: no sag or drift at neutral valves, however long), and the
cylinder's stroke ends are hard stops (no flow moves a joint past its end). The result is the
setpoint of the twin's stiff joint-velocity servo (MJCF ``<velocity>`` actuators), which alone
would let gravity sag the arm at F / kv (boom ~2 mrad/s, telescope ~4 mm/s).

Nominal parameters (:class:`HydraulicParams` defaults), a HEAP-class machine:

=================  ==========  ==============================================================
parameter          nominal     source
=================  ==========  ==============================================================
transport delay    0.10 s      HEAP: response delays up to ~0.7 s (Egli & Hutter 2020/2022 via
                               machine-spec.md); hydraulic-excavator literature 0.1-0.7 s. We
                               take the low end (a well-kept machine with electro-hydraulic
                               pilot valves; the 0.7 s are HEAP's worst case) so that the
                               12.5 Hz policy can still close the loop; profiles and training
                               randomisation cover 0.05-0.25 s.
first-order lag    0.16 s      bandwidth 1/(2 pi 0.16 s) = 1.0 Hz, inside HEAP's ~0.5 Hz and
                               the literature's 0.5-2 Hz (0.5 Hz = 0.32 s, 2 Hz = 0.08 s).
dead band          0.05        proportional pilot valves with a dead band (machine-spec.md);
                               5 % of full command CHOSEN (typical 3-10 %).
rate limit         ACTIVE_     joint speed at full valve opening (runtime.machine: boom 0.45,
                   VELOCITY_   dipper 0.6 rad/s, telescope 0.75 m/s, cabin 1.0 rad/s, from the
                   LIMITS      cylinder speeds in machine-spec.md).
=================  ==========  ==============================================================

The previous nominal (0.04 s delay, 0.1 s lag) was faster than any machine of this class.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from runtime.observation import PHYSICS_PERIOD_S


def dead_band_flow(xp: ModuleType, u, dead_band):
    """Normalised flow through a proportional valve with a dead band: 0 inside |u| < db, then
    linear to 1 at |u| = 1. u and dead_band broadcast; any array module."""
    return xp.sign(u) * xp.maximum(xp.abs(u) - dead_band, 0.0) / (1.0 - dead_band)


NOMINAL_DEAD_BAND = 0.05
NOMINAL_DELAY_S = 0.10
NOMINAL_LAG_S = 0.16
"""Nominal valve parameters (module docstring: sources)."""

HOLD_GAIN_PER_S = 10.0
"""Gain of the cylinder's position hold, 1/s: the servo corrects the gap between the oil-column
position and the joint at this rate (a 10 ms step closes 10 % of it; stable below 1/dt = 100).
CHOSEN: with the MJCF servo gains the static gravity sag becomes F / (kv * gain) < 0.5 mrad / mm."""


def cylinder_step(xp: ModuleType, x_ref, v_flow, q_active, lower, upper, dt_s: float, hold_gain=HOLD_GAIN_PER_S):
    """One step of the hydraulic cylinders of the active joints (any array module, broadcasts
    over leading batch axes).

    The oil the valve lets through moves the cylinder: ``x_ref`` (the joint position the oil
    column holds, rad / m) integrates the valve's joint-velocity flow and stops at the stroke
    ends. The servo setpoint follows the flow that really moved plus a hold term pulling the
    joint onto ``x_ref``, so with neutral valves the joint stays where it is (no sag) and no
    flow pushes it past an end.

    Args:
        xp: array module.
        x_ref: (..., 4) oil-column positions, rad / m (start them at the joint positions).
        v_flow: (..., 4) joint velocities the valves command, rad/s / m/s.
        q_active: (..., 4) true active joint positions.
        lower, upper: (4,) stroke ends (runtime.machine.JOINT_LOWER/UPPER[:4]; +-inf = none).
        dt_s: step, s.
        hold_gain: HOLD_GAIN_PER_S.

    Returns:
        (x_ref (..., 4) new oil-column positions, setpoint (..., 4) servo velocities).
    """
    x_new = xp.clip(x_ref + v_flow * dt_s, lower, upper)
    moved = (x_new - x_ref) / dt_s
    return x_new, moved + hold_gain * (x_new - q_active)


def lag_step(y, x, lag_s, dt_s: float):
    """One backward-Euler step of the first-order lag tau * dy/dt = x - y."""
    return y + dt_s / (lag_s + dt_s) * (x - y)


@dataclass
class HydraulicParams:
    """Per-joint parameters, arrays of shape (4,) in ACTIVE_JOINTS order.

    Attributes:
        dead_band: valve dead band, fraction of full command (0..1).
        delay_s: transport delay, s (a fraction of a 10 ms physics step interpolates linearly
            between the neighbouring steps; whole steps behave as a pure shift).
        lag_s: first-order lag time constant, s.
        velocity_limit: joint speed at full valve opening, rad/s or m/s.
    """

    dead_band: np.ndarray = field(default_factory=lambda: np.full(4, NOMINAL_DEAD_BAND))
    delay_s: np.ndarray = field(default_factory=lambda: np.full(4, NOMINAL_DELAY_S))
    lag_s: np.ndarray = field(default_factory=lambda: np.full(4, NOMINAL_LAG_S))
    velocity_limit: np.ndarray = field(default_factory=lambda: ACTIVE_VELOCITY_LIMITS.copy())

    def __post_init__(self) -> None:
        for name in ("dead_band", "delay_s", "lag_s", "velocity_limit"):
            v = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (4,)).copy()
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"hydraulic {name} must be finite and >= 0, got {v}")
            setattr(self, name, v)
        if np.any(self.dead_band >= 1):
            raise ValueError("dead band must be < 1")


class ValveModel:
    """Stateful valve model for the four active joints, stepped at 100 Hz."""

    def __init__(self, params: HydraulicParams, dt: float = PHYSICS_PERIOD_S):
        self.params = params
        self.dt = dt
        steps = np.round(params.delay_s / dt, 9)
        self._delay_steps = np.floor(steps).astype(int)
        self._delay_frac = steps - self._delay_steps
        self._buffer = np.zeros((int(self._delay_steps.max()) + 2, 4))  # ring: row _head is the newest flow
        self._head = 0
        self._cols = np.arange(4)
        self._lagged = np.zeros(4)

    def reset(self) -> None:
        """Valves neutral, joints at rest."""
        self._buffer[:] = 0.0
        self._lagged[:] = 0.0

    def step(self, u: np.ndarray) -> np.ndarray:
        """Advance one physics period.

        Args:
            u: (4,) valve commands; values outside [-1, 1] are clipped (the valve saturates).

        Returns:
            (4,) joint-velocity setpoints, rad/s and m/s.
        """
        u = np.clip(np.asarray(u, dtype=float), -1.0, 1.0)
        flow = dead_band_flow(np, u, self.params.dead_band)
        n = len(self._buffer)
        self._head = (self._head - 1) % n
        self._buffer[self._head] = flow
        cols = self._cols
        delayed = self._buffer[(self._head + self._delay_steps) % n, cols]
        if np.any(self._delay_frac > 0):
            frac = self._delay_frac
            delayed = (1.0 - frac) * delayed + frac * self._buffer[(self._head + self._delay_steps + 1) % n, cols]
        self._lagged = lag_step(self._lagged, delayed, self.params.lag_s, self.dt)
        vmax = self.params.velocity_limit
        return np.clip(self._lagged * vmax, -vmax, vmax)
