"""Hydraulic valve-to-joint-velocity model of the simulated machine: the stateful valves
(:class:`ValveModel`: dead band -> transport delay -> first-order lag -> rate-limited joint
velocity) with per-joint parameters (:class:`HydraulicParams`). The mechanism, its nominal
parameters and their sources (dead band, valve lag step, cylinder step) are the runtime's
(runtime.dynamics.hydraulics: the release check simulates them too); their names are imported
here for the twin.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from runtime.dynamics.hydraulics import (  # noqa: F401 (re-exported)
    HOLD_GAIN_PER_S,
    NOMINAL_DEAD_BAND,
    NOMINAL_DELAY_S,
    NOMINAL_LAG_S,
    cylinder_step,
    dead_band_flow,
    lag_step,
)
from runtime.machine import ACTIVE_VELOCITY_LIMITS
from runtime.observation import PHYSICS_PERIOD_S


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
        # constants of step() (the parameters are fixed once the model is made)
        self._fractional = bool(np.any(self._delay_frac > 0))
        self._keep_frac = 1.0 - self._delay_frac
        n = len(self._buffer)  # the delayed rows for each position of the ring's head
        self._rows = (np.arange(n)[:, None] + self._delay_steps) % n
        self._rows_next = (self._rows + 1) % n
        self._lag_gain = self.dt / (params.lag_s + self.dt)  # runtime.dynamics.hydraulics.lag_step's factor
        self._neg_vmax = -params.velocity_limit

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

        Clipping is ``minimum(maximum(.))`` and the lag is lag_step's arithmetic with its
        constant factor taken once: the same values as np.clip and lag_step, with fewer NumPy
        calls per 10 ms step (a preview's rollouts spend most of their time in such calls).
        """
        u = np.minimum(np.maximum(np.asarray(u, dtype=float), -1.0), 1.0)
        flow = dead_band_flow(np, u, self.params.dead_band)
        n = len(self._buffer)
        self._head = (self._head - 1) % n
        self._buffer[self._head] = flow
        cols = self._cols
        delayed = self._buffer[self._rows[self._head], cols]
        if self._fractional:
            delayed = self._keep_frac * delayed + self._delay_frac * self._buffer[self._rows_next[self._head], cols]
        lagged = self._lagged
        self._lagged = lagged + self._lag_gain * (delayed - lagged)
        vmax = self.params.velocity_limit
        return np.minimum(np.maximum(self._lagged * vmax, self._neg_vmax), vmax)
