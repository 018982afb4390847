"""Reality profiles: the set of effects and parameters a simulated machine runs with.

A profile is a JSON file::

    {"name": "nominal",
     "release_delay_mean_s": 0.258, "release_delay_std_s": 0.015,
     "passive_viscous_per_s": 0.03, "passive_coulomb_rad_per_s2": 0.1,
     "hydraulics": {"dead_band": 0.05, "delay_s": 0.04, "lag_s": 0.1},
     "effects": [{"effect": "payload_drag", "params": {"drag_coefficient": 0.5}},
                 {"effect": "mypkg.quirks:BoomWobble", "params": {"amplitude_radps": 0.05}}]}

``effects`` (optional) is a list of named effects of the library :mod:`sim_twin.effects`, or user
code as ``package.module:Class``; they apply in order on top of the scalar parameters (an effect
that sets a value, e.g. release_delay's mean, overrides the scalar). Examples in
sim_twin/profiles/*.json.

Scalars apply to all four active joints; lists give one value per joint. The default profile is
the nominal machine: the paper's identified release delay and friction (Sec. III-F) and the
nominal hydraulics of :mod:`sim_twin.hydraulics`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from sim_twin.effects import Effect, EffectStack, effect_from_dict
from sim_twin.hydraulics import HydraulicParams
from sim_twin.physics import PAPER_COULOMB_RAD_PER_S2, PAPER_VISCOUS_PER_S


@dataclass
class RealityProfile:
    """Physical parameters of one (simulated) machine.

    Attributes:
        name: profile name.
        release_delay_mean_s / release_delay_std_s: gripper opening delay, command to free
            payload (paper: 258 ms, sigma 15 ms over 39 releases).
        passive_viscous_per_s / passive_coulomb_rad_per_s2: paper eq. (1) upsilon and eta.
        hydraulics: valve model parameters.
        effects: effects switched on (sim_twin.effects), applied in order.
    """

    name: str = "nominal"
    release_delay_mean_s: float = 0.258
    release_delay_std_s: float = 0.015
    passive_viscous_per_s: float = PAPER_VISCOUS_PER_S
    passive_coulomb_rad_per_s2: float = PAPER_COULOMB_RAD_PER_S2
    hydraulics: HydraulicParams = field(default_factory=HydraulicParams)
    effects: list[Effect] = field(default_factory=list)

    def stack(self) -> EffectStack:
        """The profile's effects as one :class:`sim_twin.effects.EffectStack`."""
        return EffectStack(self.effects)

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
            "effects": [e.to_dict() for e in self.effects],
        }

    @classmethod
    def from_dict(cls, data: dict) -> "RealityProfile":
        """Build from a parsed JSON profile.

        Raises:
            ValueError: unknown keys or invalid values.
        """
        data = dict(data)
        hyd = data.pop("hydraulics", {})
        entries = data.pop("effects", [])
        if not isinstance(entries, list):
            raise ValueError("profile 'effects' must be a list")
        effects = [effect_from_dict(e) for e in entries]
        known = {"name", "release_delay_mean_s", "release_delay_std_s", "passive_viscous_per_s", "passive_coulomb_rad_per_s2"}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown profile keys: {sorted(unknown)}")
        unknown_h = set(hyd) - {"dead_band", "delay_s", "lag_s", "velocity_limit"}
        if unknown_h:
            raise ValueError(f"unknown hydraulics keys: {sorted(unknown_h)}")
        prof = cls(**data, hydraulics=HydraulicParams(**hyd), effects=effects)
        if prof.release_delay_mean_s < 0 or prof.release_delay_std_s < 0:
            raise ValueError("release delay must be >= 0")
        return prof

    @classmethod
    def load(cls, path: str | Path) -> "RealityProfile":
        """Read a JSON profile file (errors as in from_dict, plus OSError / JSONDecodeError)."""
        return cls.from_dict(json.loads(Path(path).read_text()))
