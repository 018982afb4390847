"""Machine-body effects: cabin drift under vibration and the hanging (gripper + payload) mass."""

from __future__ import annotations

import numpy as np

from sim_twin.twin.effects.base import Effect, Param

GRIPPER_BODY = "gripper"
NOMINAL_GRIPPER_MASS_KG = 839.0  # MJCF: gripper parts 52 + 61 + 267 kg and jaws 233 + 226 kg


class CabinDrift(Effect):
    """The slew brake slips when the arm swings hard: a creep of the cabin turn proportional to
    the arm's speed, added to the cabin servo's setpoint (the runtime's controller fights it):

        qd_cabin += rate_per_arm_speed * (|qd_boom| + |qd_dipper|)      (rad/s, sign = direction)
    """

    name = "cabin_drift"
    footprint = ("active",)
    summary = "cabin-turn creep proportional to arm speed (vibration)"
    stage = "dynamics"
    params = (Param("rate_per_arm_speed", "(rad/s)/(rad/s)", 0.0, -0.2, 0.2, "cabin creep per unit boom + dipper speed, left positive",
                    "CHOSEN: no published value; slew-brake slip of a few degrees per throw"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 0] = out[..., 0] + self.rate_per_arm_speed * (np.abs(qd[..., 1]) + np.abs(qd[..., 2]))
        return out


class HangingMass(Effect):
    """Mass hanging on the passive joints below the rotator: the gripper plus any held load (at
    the gripper centre, which is also the gripper's centre of mass), with the gripper body's
    inertia scaled by the same factor. It changes the compound pendulum of the passive joints
    (rotator 388 kg at 0.25 m below the axes, gripper at 1.0 m); passive friction stays an
    acceleration (paper eq. 1). The 0.6 kg ball itself is negligible; in flight only drag would
    see a payload's mass (PayloadDrag uses the model's 0.6 kg)."""

    name = "hanging_mass"
    footprint = ("passive",)
    summary = "gripper + held load mass (passive pendulum dynamics)"
    stage = "dynamics"
    params = (
        Param("gripper_mass_kg", "kg", NOMINAL_GRIPPER_MASS_KG, 300.0, 2500.0, "gripper plus held load, without the rotator",
              "machine-spec.md: 52 + 61 + 267 + 233 + 226 kg; range CHOSEN (other grippers, loads up to ~1.5 t)"),
    )

    def model(self, mj_model) -> None:
        bid = mj_model.body(GRIPPER_BODY).id
        scale = self.gripper_mass_kg / NOMINAL_GRIPPER_MASS_KG
        mj_model.body_inertia[bid] = mj_model.body_inertia[bid] * scale
        mj_model.body_mass[bid] = self.gripper_mass_kg


