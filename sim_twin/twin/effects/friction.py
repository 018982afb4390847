"""Passive-joint friction of the gripper's pitch and roll axes (paper eq. 1, Sec. III-F-2)."""

from __future__ import annotations

from sim_twin.twin.effects.base import Effect, Param


class PassiveFriction(Effect):
    """theta_ddot_fric = viscous * theta_dot + coulomb * sign(theta_dot) on both passive axes,
    applied as a generalised force (effective inertia x acceleration, sim_twin.twin.physics)."""

    name = "passive_friction"
    footprint = ("passive",)
    summary = "viscous and Coulomb friction of the passive gripper joints"
    stage = "dynamics"
    params = (
        Param("viscous_per_s", "1/s", 0.03, 0.0, 2.0, "viscous damping upsilon (acceleration per joint speed)",
              "paper Sec. III-F-2: 0.03 identified; range CHOSEN (worn or greased bearings, hoses)"),
        Param("coulomb_rad_per_s2", "rad/s^2", 0.1, 0.0, 3.0, "speed-independent friction eta (acceleration)",
              "paper Sec. III-F-2: 0.1 identified; range CHOSEN"),
    )

    def passive_friction(self, viscous_per_s, coulomb_rad_per_s2):
        return self.viscous_per_s, self.coulomb_rad_per_s2
