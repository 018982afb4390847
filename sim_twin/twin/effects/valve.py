"""Hydraulic valve and actuator effects on the four active joints (machine-spec.md, "Hydraulic
actuation": u -> dead band -> transport delay -> first-order lag -> rate-limited joint speed).

The valve effects have one parameter per active joint (``<name>_<joint>``, ACTIVE_JOINTS order);
the keyword ``<name>`` alone sets all four alike (``ValveLag(lag_s=0.3)``). Unset joints keep the
nominal value of :class:`sim_twin.twin.hydraulics.HydraulicParams`. The diagnosis fits them per joint
(:data:`Effect.per_joint`), from each joint's own channels.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.twin.effects.base import Effect, Param, PerJointEffect, joint_params
from sim_twin.twin.hydraulics import NOMINAL_DEAD_BAND, NOMINAL_DELAY_S, NOMINAL_LAG_S

_HEAP = "HEAP (Egli & Hutter 2020/2022 via machine-spec.md): delays up to ~0.7 s, ~0.5 Hz bandwidth, dead band"


class ValveDeadBand(PerJointEffect):
    """Proportional-valve dead band: no flow while |u| < dead_band, then linear to full flow."""

    name = "valve_dead_band"
    footprint = ("active",)
    summary = "valve dead band (fraction of full command), per active joint"
    stage = "dynamics"
    joint_base = "dead_band"
    params = joint_params("dead_band", "-", NOMINAL_DEAD_BAND, 0.0, 0.3, "valve dead band as a fraction of full command", _HEAP + "; nominal: sim_twin.twin.hydraulics")

    def hydraulics(self, hp):
        return replace(hp, dead_band=self.per_joint_values())


class ValveDelay(PerJointEffect):
    """Transport delay between the valve command and the flow (pilot stage, hoses); fractional
    delays interpolate linearly between 10 ms steps."""

    name = "valve_delay"
    footprint = ("active",)
    summary = "valve transport delay, per active joint"
    stage = "dynamics"
    joint_base = "delay_s"
    params = joint_params("delay_s", "s", NOMINAL_DELAY_S, 0.0, 0.7, "transport delay, command to flow", _HEAP + "; nominal: sim_twin.twin.hydraulics")

    def hydraulics(self, hp):
        return replace(hp, delay_s=self.per_joint_values())


class ValveLag(PerJointEffect):
    """First-order lag of the flow (spool dynamics, oil compressibility): tau dy/dt = x - y."""

    name = "valve_lag"
    footprint = ("active",)
    summary = "valve first-order lag time constant, per active joint"
    stage = "dynamics"
    joint_base = "lag_s"
    params = joint_params("lag_s", "s", NOMINAL_LAG_S, 0.01, 0.6, "first-order lag time constant", _HEAP + " (0.5 Hz ~ 0.32 s); nominal: sim_twin.twin.hydraulics")

    def hydraulics(self, hp):
        return replace(hp, lag_s=self.per_joint_values())


class ValveAsymmetry(PerJointEffect):
    """Asymmetric valve gain (differential cylinder: the rod side has less area): joint speed
    setpoints in the positive direction are scaled by (1 + a), negative ones by (1 - a)."""

    name = "valve_asymmetry"
    footprint = ("active",)
    summary = "direction-dependent valve gain (extend vs retract), per active joint"
    stage = "dynamics"
    joint_base = "asymmetry"
    params = joint_params("asymmetry", "-", 0.0, -0.5, 0.5, "relative gain difference, positive direction faster",
                          "differential cylinders: area ratio ~1.5-2 (machine-spec.md cylinder sizes); range CHOSEN")

    def setpoint(self, sp, q, qd):
        a = self.per_joint_values()
        return np.where(sp >= 0, sp * (1.0 + a), sp * (1.0 - a))


class JointRateLimit(Effect):
    """Pump-flow saturation: joint speeds are capped at ``fraction`` of the nominal full-open
    speed (runtime.machine.ACTIVE_VELOCITY_LIMITS); below the cap the valve gain is unchanged."""

    name = "joint_rate_limit"
    footprint = ("active",)
    summary = "joint speed cap as a fraction of the nominal full-open speed, all active joints"
    stage = "dynamics"
    params = (Param("fraction", "-", 1.0, 0.3, 1.0, "speed cap / nominal full-open speed",
                    "machine-spec.md: cylinder speeds give boom 0.3-0.5 rad/s, dipper ~0.6, telescope 0.75 m/s; range CHOSEN"),)

    def setpoint(self, sp, q, qd):
        cap = self.fraction * ACTIVE_VELOCITY_LIMITS
        return np.clip(sp, -cap, cap)
