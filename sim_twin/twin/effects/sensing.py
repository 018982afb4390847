"""Sensing effects: the gripper IMU that measures the passive joints (paper: a wireless IMU)."""

from __future__ import annotations

import math

import numpy as np

from sim_twin.twin.effects.base import Effect, Param

MAX_LATENCY_S = 0.2


class ImuPassive(Effect):
    """Latency and white noise of the passive-joint measurement (gripper_pitch, gripper_roll).

    The measured angle and rate are the true ones ``latency_s`` ago (linear interpolation between
    10 ms steps) plus Gaussian noise (std ``angle_noise_rad`` and ``rate_noise_radps``). The
    active joints' encoders are unaffected.
    """

    name = "imu_passive"
    footprint = ("passive",)
    summary = "gripper-IMU latency and noise on the passive joints"
    stage = "measurement"
    params = (
        Param("latency_s", "s", 0.0, 0.0, MAX_LATENCY_S, "measurement latency (wireless link, filtering)",
              "CHOSEN: wireless IMUs 10-100 ms; the paper does not report it"),
        Param("angle_noise_rad", "rad", 0.0, 0.0, 0.05, "angle noise standard deviation", "CHOSEN", stochastic=True),
        Param("rate_noise_radps", "rad/s", 0.0, 0.0, 0.5, "rate noise standard deviation", "CHOSEN", stochastic=True),
    )

    def history_steps(self) -> int:
        return int(np.ceil(MAX_LATENCY_S / 0.01)) + 2

    def measure(self, hist_q, hist_qd, dt_s, rng):
        # one draw of both noises: the generator fills them one after the other, so they are the
        # values two draws (angle, then rate) gave; fewer NumPy calls on every 10 ms step
        v = self.values
        d = v["latency_s"] / dt_s
        last = hist_q.shape[0] - 1
        i0 = min(math.floor(d + 1e-9), last)
        i1 = min(i0 + 1, last)
        f = d - i0
        q = hist_q[0].astype(float)
        qd = hist_qd[0].astype(float)
        if f == 0.0:  # a whole number of steps (the nominal 20 ms): (1 - 0) * a + 0 * b is a
            q[..., 4:6] = hist_q[i0, ..., 4:6]
            qd[..., 4:6] = hist_qd[i0, ..., 4:6]
        else:
            q[..., 4:6] = (1 - f) * hist_q[i0, ..., 4:6] + f * hist_q[i1, ..., 4:6]
            qd[..., 4:6] = (1 - f) * hist_qd[i0, ..., 4:6] + f * hist_qd[i1, ..., 4:6]
        if rng is not None:
            noise = rng.normal(0.0, 1.0, (2, *q[..., 4:6].shape))
            q[..., 4:6] += noise[0] * v["angle_noise_rad"]
            qd[..., 4:6] += noise[1] * v["rate_noise_radps"]
        return q, qd

    def estimate_spread(self, spreads: dict) -> dict:
        """Noise stds from the white part of the passive residual: first differences of white
        noise have sqrt(2) times its std; the smooth part differences to ~0 at 100 Hz."""
        out = {}
        if spreads.get("passive_q_hf_rad") is not None:
            out["angle_noise_rad"] = float(spreads["passive_q_hf_rad"] / np.sqrt(2))
        if spreads.get("passive_qd_hf_radps") is not None:
            out["rate_noise_radps"] = float(spreads["passive_qd_hf_radps"] / np.sqrt(2))
        return out


class EncoderNoise(Effect):
    """White noise of the active joints' encoders (cabin_turn, boom, dipper, telescope): the
    measured position and velocity are the true ones plus Gaussian noise. Part of every
    profile's base sensing (sim_twin.twin.profile.SensorParams), not a diagnosis candidate (not in
    the library registry): at these levels it does not move throws."""

    name = "encoder_noise"
    summary = "active-joint encoder noise"
    stage = "measurement"
    params = (
        Param("angle_noise_rad", "rad (m)", 0.0, 0.0, 0.01, "position noise standard deviation",
              "CHOSEN: absolute encoders / cylinder position sensors resolve ~0.02 deg", stochastic=True),
        Param("rate_noise_radps", "rad/s (m/s)", 0.0, 0.0, 0.1, "velocity noise standard deviation",
              "CHOSEN: differentiated and filtered encoder signal", stochastic=True),
    )

    def measure(self, hist_q, hist_qd, dt_s, rng):
        q = hist_q[0].astype(float)
        qd = hist_qd[0].astype(float)
        if rng is not None:  # one draw of both noises, as ImuPassive.measure
            v = self.values
            noise = rng.normal(0.0, 1.0, (2, *q[..., :4].shape))
            q[..., :4] += noise[0] * v["angle_noise_rad"]
            qd[..., :4] += noise[1] * v["rate_noise_radps"]
        return q, qd


class ImpactBias(Effect):
    """A constant bias of the measured landing spot in the site frame (x forward from the
    machine, y left), e.g. a camera or total-station calibration error or a target surveyed at
    the wrong place. It moves every measured impact alike and nothing else: no joint, IMU or
    payload channel sees it. It is the diagnosis's measurement-side explanation of an impact-only
    gap: an effect that fits no better than it is not confirmed by the impacts alone."""

    name = "impact_bias"
    footprint = ("impact",)
    summary = "constant bias of the measured impact (camera / survey calibration), site frame"
    stage = "measurement"
    params = (
        Param("bias_x_m", "m", 0.0, -0.5, 0.5, "measured - true landing spot, site x (forward)",
              "CHOSEN: a camera or survey calibration off by up to a few decimetres"),
        Param("bias_y_m", "m", 0.0, -0.5, 0.5, "measured - true landing spot, site y (left)",
              "CHOSEN: as bias_x_m"),
    )

    def measure_impact(self, hit_m):
        return np.asarray(hit_m, dtype=float) + np.array([self.bias_x_m, self.bias_y_m, 0.0])
