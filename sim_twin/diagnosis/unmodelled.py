"""Effects deliberately OUTSIDE the candidate library, written the way a user writes a quirk of
their own machine and loaded like user code (``sim_twin.diagnosis.unmodelled:HoseSpring`` in a
reality profile). The blind benchmark uses them to check that the diagnosis does not name a
library effect for a gap no candidate explains. Each is chosen so that some library effect can
mimic it in one channel but not everywhere (see each docstring).

``CrossWind`` and ``BoomCompliance`` predate the library's ``wind`` and
``structural_compliance`` and stay for profiles that name them.
"""

from __future__ import annotations

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.twin.effects import Effect, Param
from sim_twin.twin.effects.payload import AIR_DENSITY_KG_M3
from sim_twin.twin.model import PAYLOAD_MASS_KG, PAYLOAD_RADIUS_M


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


class HoseSpring(Effect):
    """Hydraulic hoses to the rotator stiffen the gripper_pitch joint: a torsional spring
    (N m/rad) towards the joint's zero (gripper in line with the telescope). Changes the passive
    swing (hanging_mass and passive_friction mimic it in gripper_pitch) and the release."""

    name = "hose_spring"
    summary = "torsional spring on gripper_pitch from the hoses"
    stage = "dynamics"
    params = (Param("stiffness_nm_per_rad", "N m/rad", 0.0, 0.0, 20000.0, "pitch spring stiffness", "CHOSEN"),)

    def model(self, mj_model) -> None:
        jid = mj_model.joint("gripper_pitch").id
        mj_model.jnt_stiffness[jid] = self.stiffness_nm_per_rad
        mj_model.qpos_spring[mj_model.jnt_qposadr[jid]] = 0.0


class ValveCrossFlow(Effect):
    """Boom and dipper share a pump section: the dipper gets less flow while the boom moves,
    sp_dipper *= 1 - share * |sp_boom| / v_boom_max. Mimicked in the dipper channel by a dipper
    valve lag, dead band or asymmetry, but those do not follow the boom."""

    name = "valve_cross_flow"
    summary = "dipper flow stolen by the boom"
    stage = "dynamics"
    params = (Param("share", "-", 0.0, 0.0, 0.9, "fraction of dipper flow lost at full boom speed", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 2] = out[..., 2] * (1.0 - self.share * np.minimum(np.abs(sp[..., 1]) / ACTIVE_VELOCITY_LIMITS[1], 1.0))
        return out


class SpinLift(Effect):
    """The swing spins the payload backwards; Magnus lift a = c (w x v) with the spin axis
    along the machine frame's y and |w| fixed: lift ~ ``lift_per_mps`` * |v| perpendicular to v
    in the x-z plane. Flight only: drag and wind mimic it at the impact."""

    name = "spin_lift"
    summary = "Magnus lift of a spinning payload"
    stage = "flight"
    params = (Param("lift_per_s", "1/s", 0.0, -1.0, 1.0, "lift acceleration per unit speed", "CHOSEN"),)

    def flight_accel(self, pos_m, vel_mps):
        v = np.asarray(vel_mps, dtype=float)
        perp = np.stack([-v[..., 2], np.zeros_like(v[..., 0]), v[..., 0]], axis=-1)  # y x v rotated into x-z
        return self.lift_per_s * perp


class TelescopeCreep(Effect):
    """The telescope is pulled out by the swinging gripper's centrifugal load:
    sp_telescope += gain * qd_pitch^2 (m/s per (rad/s)^2). Mimicked in the telescope channel by
    a telescope encoder offset or valve asymmetry, not in the passive swing."""

    name = "telescope_creep"
    summary = "telescope pulled out by the swing"
    stage = "dynamics"
    params = (Param("gain", "m/s/(rad/s)^2", 0.0, 0.0, 0.5, "creep speed per squared pitch rate", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 3] = out[..., 3] + self.gain * qd[..., 4] ** 2
        return out
