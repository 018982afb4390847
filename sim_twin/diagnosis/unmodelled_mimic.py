"""Effects OUTSIDE the candidate library that mimic a library effect in some channels (benchmark
kind ``mimic``, tests): backlash, a valve gain error, sensor scale errors and compliance of
another joint. Loaded like user code (``sim_twin.diagnosis.unmodelled_mimic:BoomBacklash``); the
diagnosis never names from them. Each docstring says which library effect looks alike where, and
where it does not: the right answer is "unexplained", "ambiguous" or "partly consistent with X",
never a library effect confirmed (not even as a part of the answer).

``ValveGain`` is also the benchmark's drifting outside effect (its gain changes over the log).
"""

from __future__ import annotations

import numpy as np

from runtime.machine import ACTIVE_VELOCITY_LIMITS
from sim_twin.twin.effects import Effect, Param


class BoomBacklash(Effect):
    """Play in the boom's valve linkage: when the boom's speed setpoint opposes the boom's motion
    (a reversal), the first ``play`` of the full-open speed is lost in the play,
    sp_out = sign(sp) max(|sp| - play v_max, 0); in the direction of motion it passes unchanged.
    A boom valve dead band (``valve_dead_band``) or lag (``valve_lag``) looks alike at the reversals
    in the boom channel, but those act in both directions and at every small command."""

    name = "boom_backlash"
    summary = "play in the boom valve linkage at reversals"
    stage = "dynamics"
    params = (Param("play", "-", 0.0, 0.0, 0.6, "setpoint lost at a reversal, fraction of the full-open speed", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        s, v = out[..., 1], np.asarray(qd)[..., 1]
        rev = s * v < 0.0
        out[..., 1] = np.where(rev, np.sign(s) * np.maximum(np.abs(s) - self.play * ACTIVE_VELOCITY_LIMITS[1], 0.0), s)
        return out


class ValveGain(Effect):
    """The dipper valve delivers ``gain`` times the flow it should in both directions (a worn spool,
    a weak pilot pressure): sp_dipper *= gain. A dipper valve lag or asymmetry (``valve_lag``,
    ``valve_asymmetry``) looks alike in the dipper channel, but a lag delays instead of scaling
    and an asymmetry scales one direction only."""

    name = "valve_gain"
    summary = "dipper valve flow gain error"
    stage = "dynamics"
    params = (Param("gain", "-", 1.0, 0.4, 1.6, "delivered / commanded dipper flow", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 2] = out[..., 2] * self.gain
        return out


class PitchImuScale(Effect):
    """The gripper IMU's pitch gain is off: measured pitch = (1 + scale) true pitch, and so its
    rate. A library IMU offset (``imu_offset``) on gripper_pitch looks alike while the gripper
    hangs at one angle, not over the swing."""

    name = "pitch_imu_scale"
    summary = "gripper IMU pitch scale error"
    stage = "measurement"
    params = (Param("scale", "-", 0.0, -0.3, 0.3, "relative gain error of the measured pitch", "CHOSEN"),)

    def measure(self, hist_q, hist_qd, dt_s, rng):
        q, qd = np.array(hist_q[0], dtype=float, copy=True), np.array(hist_qd[0], dtype=float, copy=True)
        q[..., 4] *= 1.0 + self.scale
        qd[..., 4] *= 1.0 + self.scale
        return q, qd


class DipperEncoderScale(Effect):
    """The dipper encoder's gain is off: measured dipper = (1 + scale) true dipper angle. A dipper
    encoder offset (``encoder_offset``) looks alike near one pose, not over the stroke."""

    name = "dipper_encoder_scale"
    summary = "dipper encoder scale error"
    stage = "measurement"
    params = (Param("scale", "-", 0.0, -0.2, 0.2, "relative gain error", "CHOSEN"),)

    def measure(self, hist_q, hist_qd, dt_s, rng):
        q, qd = np.array(hist_q[0], dtype=float, copy=True), np.array(hist_qd[0], dtype=float, copy=True)
        q[..., 2] *= 1.0 + self.scale
        qd[..., 2] *= 1.0 + self.scale
        return q, qd


class DipperCompliance(Effect):
    """The swinging gripper pulls the dipper (not the boom) through its compliant cylinder: the
    dipper's speed setpoint gets ``coupling`` times the gripper_pitch rate added. The library's
    ``structural_compliance`` (the boom's) looks alike in the passive swing, not in the joints."""

    name = "dipper_compliance"
    summary = "dipper speed disturbed by the passive swing"
    stage = "dynamics"
    params = (Param("coupling", "(rad/s)/(rad/s)", 0.0, -0.5, 0.5, "dipper speed per gripper_pitch rate", "CHOSEN"),)

    def setpoint(self, sp, q, qd):
        out = np.array(sp, dtype=float, copy=True)
        out[..., 2] = out[..., 2] + self.coupling * np.asarray(qd)[..., 4]
        return out
