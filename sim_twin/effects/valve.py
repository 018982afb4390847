"""Hydraulic valve and actuator effects on the four active joints (machine-spec.md, "Hydraulic
actuation": u -> dead band -> transport delay -> first-order lag -> rate-limited joint speed).

Each effect sets one parameter for all four active joints alike (a per-joint fit would need
four times the throws); the nominal values are those of :class:`sim_twin.hydraulics.HydraulicParams`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.effects.base import Effect, Param

_HEAP = "HEAP (Egli & Hutter 2020/2022 via machine-spec.md): delays up to ~0.7 s, ~0.5 Hz bandwidth, dead band"


class ValveDeadBand(Effect):
    """Proportional-valve dead band: no flow while |u| < dead_band, then linear to full flow."""

    name = "valve_dead_band"
    summary = "valve dead band (fraction of full command), all active joints"
    stage = "dynamics"
    params = (Param("dead_band", "-", 0.05, 0.0, 0.3, "valve dead band as a fraction of full command", _HEAP + "; nominal 0.05 CHOSEN"),)

    def hydraulics(self, hp):
        return replace(hp, dead_band=np.full(4, self.dead_band))


class ValveDelay(Effect):
    """Transport delay between the valve command and the flow (pilot stage, hoses); fractional
    delays interpolate linearly between 10 ms steps."""

    name = "valve_delay"
    summary = "valve transport delay, all active joints"
    stage = "dynamics"
    params = (Param("delay_s", "s", 0.04, 0.0, 0.3, "transport delay, command to flow", _HEAP + "; nominal 0.04 s CHOSEN"),)

    def hydraulics(self, hp):
        return replace(hp, delay_s=np.full(4, self.delay_s))


class ValveLag(Effect):
    """First-order lag of the flow (spool dynamics, oil compressibility): tau dy/dt = x - y."""

    name = "valve_lag"
    summary = "valve first-order lag time constant, all active joints"
    stage = "dynamics"
    params = (Param("lag_s", "s", 0.10, 0.01, 0.6, "first-order lag time constant", _HEAP + " (0.5 Hz ~ 0.32 s); nominal 0.1 s CHOSEN"),)

    def hydraulics(self, hp):
        return replace(hp, lag_s=np.full(4, self.lag_s))


class JointRateLimit(Effect):
    """Pump-flow saturation: joint speeds are capped at ``fraction`` of the nominal full-open
    speed (runtime.machine.ACTIVE_VELOCITY_LIMITS); below the cap the valve gain is unchanged."""

    name = "joint_rate_limit"
    summary = "joint speed cap as a fraction of the nominal full-open speed, all active joints"
    stage = "dynamics"
    params = (Param("fraction", "-", 1.0, 0.3, 1.0, "speed cap / nominal full-open speed",
                    "machine-spec.md: cylinder speeds give boom 0.3-0.5 rad/s, dipper ~0.6, telescope 0.75 m/s; range CHOSEN"),)

    def setpoint(self, sp, q, qd):
        cap = self.fraction * ACTIVE_VELOCITY_LIMITS
        return np.clip(sp, -cap, cap)
