"""Structural effects of the arm: compliance to the swinging gripper and stiction of the
cylinders at rest."""

from __future__ import annotations

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.twin.effects.base import Effect, Param

REST_SPEED = 0.02  # rad/s or m/s: below this a joint counts as at rest (CHOSEN, ~encoder noise)


class StructuralCompliance(Effect):
    """The swinging gripper pulls the boom through its compliant lift cylinder (oil column, boom
    flex): the boom's speed setpoint gets ``coupling`` times the gripper_pitch rate added, and
    the runtime's controller fights it."""

    name = "structural_compliance"
    footprint = ("active",)
    summary = "boom speed disturbed by the passive swing (compliant lift cylinder)"
    stage = "dynamics"
    params = (Param("coupling", "(rad/s)/(rad/s)", 0.0, -0.5, 0.5, "boom speed per gripper_pitch rate",
                    "CHOSEN: oil-column stiffness of a 2 m cylinder gives a few percent of the swing rate"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 1] = out[..., 1] + self.coupling * qd[..., 4]
        return out


class Stiction(Effect):
    """Cylinder stiction: a joint at rest (|speed| < 0.02) does not move until its speed setpoint
    exceeds ``breakaway_fraction`` of its full-open speed; once moving it follows normally."""

    name = "stiction"
    footprint = ("active",)
    summary = "breakaway of the active joints from rest (seal friction)"
    stage = "dynamics"
    params = (Param("breakaway_fraction", "-", 0.0, 0.0, 0.4, "setpoint needed to break away, fraction of full-open speed",
                    "CHOSEN: seal friction of hydraulic cylinders, a few to tens of percent of the stroke force"),)

    def setpoint(self, sp, q, qd):
        stuck = (np.abs(qd[..., :4]) < REST_SPEED) & (np.abs(sp) < self.breakaway_fraction * ACTIVE_VELOCITY_LIMITS)
        return np.where(stuck, 0.0, sp)
