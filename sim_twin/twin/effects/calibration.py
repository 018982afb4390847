"""Sensor calibration offsets: joint encoders and the gripper IMU read a constant offset.

The measured angle is the true one plus the offset; the runtime's controller and the logs see
the measured one. Replays start from the true state behind the logged one (``initial_state``),
so an IMU offset does not make the replayed gripper swing at the start.

An encoder offset does not show in the encoder channels themselves: the replay starts from the
true pose behind the logged reading and the arm is velocity-commanded, so the replayed encoder
readings follow the log by construction. It shows where gravity and geometry act on the true
pose: the gripper swing (passive), the payload track and the impact. Every joint's offset acts
on those same channels, so the diagnosis fits it as a non-separable per-joint effect (one joint
at a time over all footprint channels, :meth:`sim_twin.diagnosis.select.Evaluator.sweep`).
"""

from __future__ import annotations

import numpy as np

from runtime.machine import PASSIVE_JOINTS
from sim_twin.twin.effects.base import PerJointEffect, joint_params


class _Offset(PerJointEffect):
    stage = "measurement"

    def _vector(self, like: np.ndarray) -> np.ndarray:
        off = np.zeros(like.shape[-1])
        off[list(self.joint_indices())] = self.per_joint_values()
        return off

    def measure(self, hist_q, hist_qd, dt_s, rng):
        return hist_q[0] + self._vector(hist_q[0]), hist_qd[0]

    def initial_state(self, q, qd):
        return q - self._vector(q), qd


class EncoderOffset(_Offset):
    """Zero offsets of the active joints' encoders (rad; m for the telescope)."""

    name = "encoder_offset"
    footprint = ("passive", "payload", "impact")
    separable = False
    summary = "calibration offset of the active-joint encoders, per joint"
    joint_base = "offset"
    params = joint_params("offset", "rad (m for telescope)", 0.0, -0.08, 0.08, "encoder zero offset (measured - true)",
                          "CHOSEN: a re-mounted encoder is off by up to a few degrees / centimetres")


class ImuOffset(_Offset):
    """Mounting offsets of the gripper IMU (pitch and roll angles, rad)."""

    name = "imu_offset"
    footprint = ("passive",)
    summary = "mounting offset of the gripper IMU (pitch, roll)"
    joint_base = "offset"
    joints = PASSIVE_JOINTS
    params = joint_params("offset", "rad", 0.0, -0.1, 0.1, "IMU angle offset (measured - true)",
                          "CHOSEN: an IMU on a bracket sits within ~5 degrees of its nominal orientation", joints=PASSIVE_JOINTS)

    def initial_state(self, q, qd):
        return q, qd  # replays start with the gripper hanging plumb whatever the IMU says
