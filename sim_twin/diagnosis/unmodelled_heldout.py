"""Outside-the-library effects kept OUT of the diagnosis' tuning: written before tuning began,
used only by the final committed benchmark run (``benchmark.HELD_OUT``). Do not tune against
their results.
"""

from __future__ import annotations

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.twin.effects import Effect, Param


class BoomEncoderScale(Effect):
    """The boom encoder's gain is off: measured boom = (1 + scale) * true boom angle."""

    name = "boom_encoder_scale"
    summary = "boom encoder scale error"
    stage = "measurement"
    params = (Param("scale", "-", 0.0, -0.2, 0.2, "relative gain error", "CHOSEN"),)

    def measure(self, hist_q, hist_qd, dt_s, rng):
        q, qd = np.array(hist_q[0], dtype=float, copy=True), np.array(hist_qd[0], dtype=float, copy=True)
        q[..., 1] *= 1.0 + self.scale
        qd[..., 1] *= 1.0 + self.scale
        return q, qd


class PumpDroop(Effect):
    """One pump for all cylinders: every joint slows when the total demanded flow is high,
    sp /= 1 + droop * sum_j |sp_j| / v_j,max."""

    name = "pump_droop"
    summary = "shared pump pressure droop"
    stage = "dynamics"
    params = (Param("droop", "-", 0.0, 0.0, 1.0, "relative slow-down per unit total demand", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        demand = np.sum(np.abs(sp) / ACTIVE_VELOCITY_LIMITS, axis=-1, keepdims=True)
        return sp / (1.0 + self.droop * demand)


class PitchArmature(Effect):
    """Rotational inertia added on the gripper_pitch axis (rotator motor, hose drum), kg m^2."""

    name = "pitch_armature"
    summary = "extra inertia on the gripper_pitch axis"
    stage = "dynamics"
    params = (Param("armature_kgm2", "kg m^2", 0.0, 0.0, 2000.0, "added pitch inertia", "CHOSEN"),)

    def model(self, mj_model) -> None:
        jid = mj_model.joint("gripper_pitch").id
        mj_model.dof_armature[mj_model.jnt_dofadr[jid]] += self.armature_kgm2
