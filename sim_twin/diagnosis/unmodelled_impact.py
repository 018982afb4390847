"""Outside-the-library effects that show only in the measured impact (benchmark kind
``impact_only``): no joint, IMU or payload channel of a real machine's log sees them, so the
right answer is "consistent with X, not confirmed" with the alternatives, never a confident name.
"""

from __future__ import annotations

import numpy as np

from sim_twin.twin.effects import Effect, Param


class SidewaysGrasp(Effect):
    """The payload is held beside the gripper centre, along the gripper's y axis (m). The library's
    grasp offset covers forward and up only."""

    name = "sideways_grasp"
    summary = "payload held off-centre sideways"
    stage = "payload"
    params = (Param("side_m", "m", 0.0, -0.5, 0.5, "offset along the gripper y axis", "CHOSEN"),)

    def grasp_offset(self):
        return np.array([0.0, self.side_m, 0.0])


class ImpactScale(Effect):
    """The impact measurement's scale is off (a camera's focal length or a survey's scale):
    measured = (1 + scale) * true landing spot, site frame, machine at the origin."""

    name = "impact_scale"
    summary = "scale error of the impact measurement"
    stage = "measurement"
    params = (Param("scale", "-", 0.0, -0.1, 0.1, "relative scale error", "CHOSEN"),)

    def measure_impact(self, hit_m):
        h = np.array(hit_m, dtype=float, copy=True)
        h[..., :2] *= 1.0 + self.scale
        return h
