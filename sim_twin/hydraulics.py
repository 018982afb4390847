"""Hydraulic valve-to-joint-velocity model of the simulated machine (machine-spec.md,
"Hydraulic actuation"): per active joint, valve command u in [-1, 1] -> dead band -> transport
delay -> first-order lag -> rate-limited joint velocity. The result is the setpoint of the twin's
stiff joint-velocity servo.

Reported for HEAP (Egli & Hutter 2020/2022, via machine-spec.md): response delays up to ~0.7 s,
velocity bandwidth ~0.5 Hz, proportional pilot valves with a dead band. The nominal parameters in
:class:`HydraulicParams` are milder, CHOSEN for a well-tuned machine; reality profiles change them.
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

    dead_band: np.ndarray = field(default_factory=lambda: np.full(4, 0.05))
    delay_s: np.ndarray = field(default_factory=lambda: np.full(4, 0.04))
    lag_s: np.ndarray = field(default_factory=lambda: np.full(4, 0.10))
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
        self._buffer = np.zeros((int(self._delay_steps.max()) + 2, 4))
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
        self._buffer = np.roll(self._buffer, 1, axis=0)
        self._buffer[0] = flow
        cols = np.arange(4)
        delayed = self._buffer[self._delay_steps, cols]
        if np.any(self._delay_frac > 0):
            frac = self._delay_frac
            delayed = (1.0 - frac) * delayed + frac * self._buffer[self._delay_steps + 1, cols]
        self._lagged = lag_step(self._lagged, delayed, self.params.lag_s, self.dt)
        vmax = self.params.velocity_limit
        return np.clip(self._lagged * vmax, -vmax, vmax)
