"""Site effects: steady wind on the payload in flight."""

from __future__ import annotations

import numpy as np

from sim_twin.twin.effects.base import Effect, Param
from sim_twin.twin.effects.payload import AIR_DENSITY_KG_M3
from sim_twin.twin.model import PAYLOAD_MASS_KG, PAYLOAD_RADIUS_M

WIND_DRAG_COEFFICIENT = 0.5  # basketball, subcritical Re (wind-tunnel literature; PayloadDrag's source)


class Wind(Effect):
    """Steady horizontal wind w = (wind_x_mps, wind_y_mps, 0) in the machine frame. It adds the
    wind's share of the quadratic drag (Cd 0.5 on pi r^2):

        a = -k (|v - w| (v - w) - |v| v),   k = rho Cd A / (2 m)

    i.e. the drag relative to moving air minus the still-air drag, so that zero wind is the
    nominal twin and still-air drag stays the business of ``payload_drag``."""

    name = "wind"
    summary = "steady horizontal wind acting on the payload in flight"
    stage = "flight"
    params = (
        Param("wind_x_mps", "m/s", 0.0, -15.0, 15.0, "wind along the machine frame's x axis", "CHOSEN: up to a fresh breeze (Beaufort 5-6)"),
        Param("wind_y_mps", "m/s", 0.0, -15.0, 15.0, "wind along the machine frame's y axis (left positive)", "CHOSEN: as wind_x_mps"),
    )

    def flight_accel(self, pos_m, vel_mps):
        k = AIR_DENSITY_KG_M3 * WIND_DRAG_COEFFICIENT * np.pi * PAYLOAD_RADIUS_M**2 / (2 * PAYLOAD_MASS_KG)
        rel = vel_mps - np.array([self.wind_x_mps, self.wind_y_mps, 0.0])
        return -k * (np.linalg.norm(rel, axis=-1, keepdims=True) * rel - np.linalg.norm(vel_mps, axis=-1, keepdims=True) * vel_mps)
