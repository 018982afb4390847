"""The library of named physical effects the twin can switch on (docs/architecture.md: "Effect").

::

    from sim_twin.twin.effects import EFFECTS, make_effect, load_effect
    make_effect("payload_drag", drag_coefficient=0.5)
    make_effect("mypkg.quirks:BoomWobble", amplitude_radps=0.05)   # user code

Library effects are registered by name in :data:`EFFECTS` (one module per family: release,
friction, valve, payload, machine, sensing); the diagnosis fits every registered effect as a
candidate. Users model a quirk of their own machine with a class implementing the interface of
:class:`sim_twin.twin.effects.base.Effect` and name it ``package.module:Class`` in a reality profile.
"""

from __future__ import annotations

import importlib

from sim_twin.twin.effects.base import STAGES, Effect, EffectStack, Param, PerJointEffect
from sim_twin.twin.effects.calibration import EncoderOffset, ImuOffset
from sim_twin.twin.effects.friction import PassiveFriction
from sim_twin.twin.effects.machine import CabinDrift, HangingMass
from sim_twin.twin.effects.payload import GraspOffset, PayloadDrag
from sim_twin.twin.effects.release import ReleaseDelay
from sim_twin.twin.effects.sensing import ImpactBias, ImuPassive
from sim_twin.twin.effects.site import Wind
from sim_twin.twin.effects.structure import Stiction, StructuralCompliance
from sim_twin.twin.effects.valve import JointRateLimit, ValveAsymmetry, ValveDeadBand, ValveDelay, ValveLag

EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        ReleaseDelay, PassiveFriction, ValveDeadBand, ValveDelay, ValveLag, JointRateLimit,
        PayloadDrag, GraspOffset, CabinDrift, ImuPassive, HangingMass,
        Wind, EncoderOffset, ImuOffset, ValveAsymmetry, StructuralCompliance, Stiction, ImpactBias,
    )
}
"""Library effects by name, in a stable order."""

__all__ = ["EFFECTS", "STAGES", "Effect", "EffectStack", "Param", "PerJointEffect", "effect_class", "effect_from_dict", "load_effect", "make_effect"]


def load_effect(spec: str) -> type[Effect]:
    """Import a user effect class from ``"package.module:Class"``.

    Raises:
        ValueError: malformed spec, module or class not found, or not an Effect subclass with a
            name and valid stage (the message says which).
    """
    if not isinstance(spec, str) or spec.count(":") != 1:
        raise ValueError(f"effect {spec!r}: expected a library name {sorted(EFFECTS)} or 'package.module:Class'")
    module_name, _, class_name = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"effect {spec!r}: cannot import module {module_name!r}: {e}") from e
    cls = getattr(module, class_name, None)
    if cls is None:
        raise ValueError(f"effect {spec!r}: module {module_name!r} has no {class_name!r}")
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise ValueError(f"effect {spec!r}: {class_name} is not a subclass of sim_twin.twin.effects.Effect")  # profile errors are ValueError
    if not cls.name or cls.stage not in STAGES:
        raise ValueError(f"effect {spec!r}: needs a non-empty 'name' and a stage in {STAGES}")
    return cls


def effect_class(spec: str) -> type[Effect]:
    """A library effect by name, else a user effect by ``package.module:Class``."""
    if spec in EFFECTS:
        return EFFECTS[spec]
    if ":" not in str(spec):
        raise ValueError(f"unknown effect {spec!r}: library effects are {sorted(EFFECTS)}; user code as 'package.module:Class'")
    return load_effect(spec)


def make_effect(spec: str, **params: float) -> Effect:
    """Instantiate an effect by library name or ``package.module:Class`` (errors: ValueError)."""
    cls = effect_class(spec)
    try:
        return cls(**params)
    except TypeError as e:
        raise ValueError(f"effect {spec!r}: {e}") from e


def effect_from_dict(entry: dict) -> Effect:
    """``{"effect": "payload_drag", "params": {"drag_coefficient": 0.5}}`` -> Effect."""
    if not isinstance(entry, dict) or "effect" not in entry:
        raise ValueError(f"profile effect entry needs an 'effect' key, got {entry!r}")
    extra = set(entry) - {"effect", "params"}
    if extra:
        raise ValueError(f"profile effect entry: unknown keys {sorted(extra)}")
    params = entry.get("params") or {}
    if not isinstance(params, dict):
        raise ValueError(f"effect {entry['effect']!r}: 'params' must be an object")
    return make_effect(entry["effect"], **params)
