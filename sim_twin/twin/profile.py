"""Reality profiles: the set of effects and parameters a simulated machine runs with.

A profile is a JSON file::

    {"name": "nominal",
     "release_delay_mean_s": 0.258, "release_delay_std_s": 0.015,
     "passive_viscous_per_s": 0.03, "passive_coulomb_rad_per_s2": 0.1,
     "hydraulics": {"dead_band": 0.05, "delay_s": 0.10, "lag_s": 0.16},
     "sensing": {"imu_latency_s": 0.02, "impact_noise_m": 0.02},
     "effects": [{"effect": "payload_drag", "params": {"drag_coefficient": 0.5}},
                 {"effect": "mypkg.quirks:BoomWobble", "params": {"amplitude_radps": 0.05}}]}

``effects`` (optional) is a list of named effects of the library :mod:`sim_twin.twin.effects`, or user
code as ``package.module:Class``; they apply in order on top of the scalar parameters (an effect
that sets a value, e.g. release_delay's mean, overrides the scalar). Examples in
sim_twin/profiles/*.json.

Scalars apply to all four active joints; lists give one value per joint. The default profile is
the nominal machine: the paper's identified release delay and friction (Sec. III-F), the
nominal hydraulics of :mod:`sim_twin.twin.hydraulics` and the nominal sensing of :class:`SensorParams`
(encoder and gripper-IMU noise and latency, impact-measurement noise). ``sensing`` keys not given
keep their nominal value; the sensing acts before the profile's own measurement effects.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from sim_twin.twin.effects import Effect, EffectStack, effect_from_dict
from sim_twin.twin.effects.sensing import EncoderNoise, ImuPassive
from sim_twin.twin.hydraulics import HydraulicParams
from sim_twin.twin.physics import PAPER_COULOMB_RAD_PER_S2, PAPER_VISCOUS_PER_S


@dataclass
class SensorParams:
    """Nominal sensing of the machine (all CHOSEN: neither the paper nor machine-spec.md gives
    numbers; the paper adds observation noise in training and measures the passive joints with
    a wireless IMU on the gripper).

    Attributes:
        encoder_noise_rad: active-joint position noise std, rad (m for the telescope):
            absolute encoders / cylinder sensors resolve ~0.02 deg = 3.5e-4 rad.
        encoder_rate_noise_radps: active-joint velocity noise std, rad/s (m/s).
        imu_latency_s: gripper-IMU latency (wireless link + orientation filter), s; wireless
            IMUs run 10-100 ms, we take 20 ms (training randomises 0-40 ms).
        imu_angle_noise_rad: passive-joint angle noise std (MEMS orientation ~0.1-0.5 deg), rad.
        imu_rate_noise_radps: passive-joint rate noise std (gyro), rad/s.
        impact_noise_m: std of the measured impact point, per horizontal axis, m (marking the
            landing spot on the ground, e.g. camera or survey pole).
    """

    encoder_noise_rad: float = 3e-4
    encoder_rate_noise_radps: float = 0.003
    imu_latency_s: float = 0.02
    imu_angle_noise_rad: float = 0.003
    imu_rate_noise_radps: float = 0.01
    impact_noise_m: float = 0.02

    def __post_init__(self) -> None:
        for k in self.__dataclass_fields__:
            v = float(getattr(self, k))
            if not (v >= 0 and v < float("inf")):
                raise ValueError(f"sensing {k} must be finite and >= 0, got {v}")
            setattr(self, k, v)

    @classmethod
    def ideal(cls) -> SensorParams:
        """Perfect sensors (no noise, no latency): for tests of exact reproduction."""
        return cls(**{k: 0.0 for k in cls.__dataclass_fields__})

    def effects(self) -> list[Effect]:
        """The measurement effects that implement this sensing (encoders, then the IMU)."""
        return [
            EncoderNoise(angle_noise_rad=self.encoder_noise_rad, rate_noise_radps=self.encoder_rate_noise_radps),
            ImuPassive(latency_s=self.imu_latency_s, angle_noise_rad=self.imu_angle_noise_rad, rate_noise_radps=self.imu_rate_noise_radps),
        ]


@dataclass
class RealityProfile:
    """Physical parameters of one (simulated) machine.

    Attributes:
        name: profile name.
        release_delay_mean_s / release_delay_std_s: gripper opening delay, command to free
            payload (paper: 258 ms, sigma 15 ms over 39 releases).
        passive_viscous_per_s / passive_coulomb_rad_per_s2: paper eq. (1) upsilon and eta.
        hydraulics: valve model parameters.
        sensing: nominal sensors (noise, latency, impact measurement).
        effects: effects switched on (sim_twin.twin.effects), applied in order after the sensing.
        uncertainty: what is not known about the site: parameter ranges, a diagnosis' fitted
            1 sigma, the start-state model (format and meaning: :mod:`sim_twin.twin.uncertainty`;
            checked when loaded). The simulated machine runs the centre values; previews and
            calibration draw from it.
    """

    name: str = "nominal"
    release_delay_mean_s: float = 0.258
    release_delay_std_s: float = 0.015
    passive_viscous_per_s: float = PAPER_VISCOUS_PER_S
    passive_coulomb_rad_per_s2: float = PAPER_COULOMB_RAD_PER_S2
    hydraulics: HydraulicParams = field(default_factory=HydraulicParams)
    sensing: SensorParams = field(default_factory=SensorParams)
    effects: list[Effect] = field(default_factory=list)
    uncertainty: dict = field(default_factory=dict)

    def stack(self) -> EffectStack:
        """The sensing and the profile's effects as one :class:`sim_twin.twin.effects.EffectStack`."""
        return EffectStack(self.sensing.effects() + self.effects)

    def to_dict(self) -> dict:
        """JSON-able profile (inverse of :meth:`from_dict`)."""
        h = self.hydraulics
        return {
            "name": self.name,
            "release_delay_mean_s": self.release_delay_mean_s,
            "release_delay_std_s": self.release_delay_std_s,
            "passive_viscous_per_s": self.passive_viscous_per_s,
            "passive_coulomb_rad_per_s2": self.passive_coulomb_rad_per_s2,
            "hydraulics": {k: getattr(h, k).tolist() for k in ("dead_band", "delay_s", "lag_s", "velocity_limit")},
            "sensing": {k: getattr(self.sensing, k) for k in SensorParams.__dataclass_fields__},
            "effects": [e.to_dict() for e in self.effects],
            **({"uncertainty": dict(self.uncertainty)} if self.uncertainty else {}),
        }

    @classmethod
    def from_dict(cls, data: dict) -> RealityProfile:
        """Build from a parsed JSON profile.

        Raises:
            ValueError: unknown keys or invalid values.
        """
        data = dict(data)
        hyd = data.pop("hydraulics", {})
        sensing = data.pop("sensing", {})
        entries = data.pop("effects", [])
        if not isinstance(entries, list):
            raise ValueError("profile 'effects' must be a list")
        effects = [effect_from_dict(e) for e in entries]
        known = {"name", "release_delay_mean_s", "release_delay_std_s", "passive_viscous_per_s", "passive_coulomb_rad_per_s2", "uncertainty"}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown profile keys: {sorted(unknown)}")
        unknown_h = set(hyd) - {"dead_band", "delay_s", "lag_s", "velocity_limit"}
        if unknown_h:
            raise ValueError(f"unknown hydraulics keys: {sorted(unknown_h)}")
        unknown_s = set(sensing) - set(SensorParams.__dataclass_fields__)
        if unknown_s:
            raise ValueError(f"unknown sensing keys: {sorted(unknown_s)}")
        prof = cls(**data, hydraulics=HydraulicParams(**hyd), sensing=SensorParams(**sensing), effects=effects)
        if prof.release_delay_mean_s < 0 or prof.release_delay_std_s < 0:
            raise ValueError("release delay must be >= 0")
        from sim_twin.twin.uncertainty import parse

        parse(prof.uncertainty)
        return prof

    @classmethod
    def load(cls, path: str | Path) -> RealityProfile:
        """Read a JSON profile file (errors as in from_dict, plus OSError / JSONDecodeError)."""
        return cls.from_dict(json.loads(Path(path).read_text()))
