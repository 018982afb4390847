"""Effects deliberately OUTSIDE the candidate library, written the way a user writes a quirk of
their own machine and loaded like user code (``sim_twin.diagnosis.unmodelled:CrossWind`` in a
reality profile). The blind benchmark uses them to check that the diagnosis answers
"unexplained" when no candidate can explain the gap.
"""

from __future__ import annotations

import numpy as np

from sim_twin.effects import Effect, Param
from sim_twin.effects.payload import AIR_DENSITY_KG_M3
from sim_twin.model import PAYLOAD_MASS_KG, PAYLOAD_RADIUS_M


class CrossWind(Effect):
    """Wind across the machine frame's y axis: quadratic drag (Cd 0.5) on the payload relative
    to the moving air, a = -rho Cd A |v - w| (v - w) / (2 m), w = (0, wind_mps, 0)."""

    name = "cross_wind"
    summary = "steady wind along y acting on the payload in flight"
    stage = "flight"
    params = (Param("wind_mps", "m/s", 0.0, -15.0, 15.0, "wind speed along the machine frame's y axis", "CHOSEN"),)

    def flight_accel(self, pos_m, vel_mps):
        rel = vel_mps - np.array([0.0, self.wind_mps, 0.0])
        k = AIR_DENSITY_KG_M3 * 0.5 * np.pi * PAYLOAD_RADIUS_M**2 / (2 * PAYLOAD_MASS_KG)
        return -k * np.linalg.norm(rel, axis=-1, keepdims=True) * rel


class BoomCompliance(Effect):
    """The swinging gripper pulls the boom through a compliant lift cylinder: the boom's servo
    setpoint gets ``coupling`` times the gripper_pitch rate added (the controller fights it)."""

    name = "boom_compliance"
    summary = "boom speed disturbed by the passive swing"
    stage = "dynamics"
    params = (Param("coupling", "(rad/s)/(rad/s)", 0.0, -0.5, 0.5, "boom speed per gripper_pitch rate", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 1] = out[..., 1] + self.coupling * qd[..., 4]
        return out
