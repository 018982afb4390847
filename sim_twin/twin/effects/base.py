"""The effect interface: a named, parameterised physical phenomenon the twin can switch on.

An effect is a class with a unique ``name``, a documented tuple of :class:`Param` (physical
meaning, unit, the value that reproduces the nominal twin, prior range, source) and any of the
hooks below. The simulated machine (:mod:`sim_twin.twin.simulated_machine`) and the diagnosis's
batched replay (:mod:`sim_twin.diagnosis.replay`) call the same hooks, so an effect behaves the
same in the machine that generates throws and in the twin that explains them.

Hooks (defaults leave everything unchanged; arrays may carry leading batch dimensions ``...``):

=====================  =============================================================  ==========
hook                   what it changes                                                stage
=====================  =============================================================  ==========
``hydraulics(hp)``     valve parameters (dead band, transport delay, lag, full-open   dynamics
                       speed) -> a new :class:`sim_twin.twin.hydraulics.HydraulicParams`
``setpoint(sp, q, qd)`` joint-velocity servo setpoints (..., 4) after the valve model  dynamics
                       (rate limits, disturbances), given the true state (..., 6)
``passive_friction``   (viscous 1/s, coulomb rad/s^2) of the passive joints           dynamics
``model(m)``           masses / inertias of a private ``mujoco.MjModel`` copy          dynamics
``release_delay``      (mean s, std s) of the gripper opening delay                    release
``grasp_offset()``     (3,) payload position in the gripper frame relative to the      payload
                       gripper centre, m (x along the jaws, z up)
``flight_accel(p, v)`` extra payload acceleration in flight (..., 3), m/s^2            flight
``measure(hq, hqd,     measured (q, qd) (..., 6) from the history of true states       measurement
  dt, rng)``           (newest first, (H, ..., 6)); rng None = noise-free expectation
``measure_impact(h)``  the measured landing spot (3,) from the true one (site frame,   measurement
                       m): impact-measurement calibration, target survey error
``initial_state(q,     the true state (6,) behind a measured one at rest (inverse of   measurement
  qd)``                a static ``measure``, e.g. calibration offsets); replays start
                       from it
=====================  =============================================================  ==========

``stage`` says where the effect acts. Effects whose stage is not ``"dynamics"`` leave the joint
motion under logged references unchanged, so the replay can reuse one dynamic rollout for them.
A user effect (loaded by ``package.module:Class``) that overrides a dynamics hook must say
``stage = "dynamics"`` (the default for subclasses that do not say otherwise).

Parameters are keyword arguments; values outside ``(lo, hi)`` raise ValueError.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES

STAGES = ("dynamics", "release", "payload", "flight", "measurement")


@dataclass(frozen=True)
class Param:
    """One effect parameter.

    Attributes:
        name: keyword name, with its unit as suffix where it has one (``_s``, ``_kg``...).
        unit: unit in words ("s", "1/s", "-", ...).
        nominal: the value at which the effect reproduces the nominal twin exactly.
        lo / hi: prior range (also the fit's bounds).
        doc: physical meaning.
        source: where the nominal value and range come from.
        stochastic: True for spreads (noise std, jitter): fitted from the spread of residuals,
            not from their mean.
    """

    name: str
    unit: str
    nominal: float
    lo: float
    hi: float
    doc: str
    source: str
    stochastic: bool = False

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("name", "unit", "nominal", "lo", "hi", "doc", "source", "stochastic")}


class Effect:
    """Base class of all effects. Subclasses set ``name``, ``params``, ``stage`` and hooks.

    Args:
        **values: parameter values by name; missing ones take their ``nominal``.

    Raises:
        ValueError: unknown parameter name, non-finite value or value outside (lo, hi).
    """

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    stage: ClassVar[str] = "dynamics"
    footprint: ClassVar[tuple[str, ...]] = ()
    """Channel groups the effect must show up in (active, passive, impact, release, payload);
    empty: by stage (:meth:`groups`). The diagnosis fits a candidate only where the gap is."""

    @classmethod
    def groups(cls) -> tuple[str, ...]:
        """The footprint, or by stage: dynamics and measurement -> active, passive; release,
        payload, flight -> impact, release, payload."""
        if cls.footprint:
            return cls.footprint
        return ("active", "passive") if cls.stage in ("dynamics", "measurement") else ("impact", "release", "payload")

    def __init__(self, **values: float):
        known = {p.name: p for p in self.params}
        unknown = set(values) - set(known)
        if unknown:
            raise ValueError(f"effect {self.name!r}: unknown parameters {sorted(unknown)} (has {sorted(known)})")
        self.values: dict[str, float] = {}
        for p in self.params:
            v = float(values.get(p.name, p.nominal))
            if not math.isfinite(v):
                raise ValueError(f"effect {self.name!r}: {p.name} must be finite, got {v}")
            if not (p.lo - 1e-12 <= v <= p.hi + 1e-12):
                raise ValueError(f"effect {self.name!r}: {p.name} = {v} {p.unit} outside its range [{p.lo}, {p.hi}]")
            self.values[p.name] = v

    def __getattr__(self, item: str) -> float:
        values = self.__dict__.get("values")
        if values is not None and item in values:
            return values[item]
        raise AttributeError(item)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v:.6g}' for k, v in self.values.items())})"

    @classmethod
    def describe(cls) -> dict:
        """JSON-able documentation of the effect (name, summary, stage, parameters)."""
        return {"name": cls.name, "summary": cls.summary, "stage": cls.stage, "params": [p.to_dict() for p in cls.params]}

    def to_dict(self) -> dict:
        """The profile entry that rebuilds this effect (see :func:`sim_twin.twin.effects.effect_from_dict`)."""
        return {"effect": self.spec(), "params": dict(self.values)}

    @classmethod
    def spec(cls) -> str:
        """Registry name for library effects, ``module:Class`` for user code."""
        from sim_twin.twin.effects import EFFECTS

        if EFFECTS.get(cls.name) is cls:
            return cls.name
        return f"{cls.__module__}:{cls.__qualname__}"

    # --- hooks (defaults: no change) --------------------------------------------------------
    def hydraulics(self, hp):
        return hp

    def setpoint(self, sp: np.ndarray, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        return sp

    def passive_friction(self, viscous_per_s: float, coulomb_rad_per_s2: float) -> tuple[float, float]:
        return viscous_per_s, coulomb_rad_per_s2

    def model(self, mj_model) -> None:
        return None

    def release_delay(self, mean_s: float, std_s: float) -> tuple[float, float]:
        return mean_s, std_s

    def grasp_offset(self) -> np.ndarray | None:
        return None

    def flight_accel(self, pos_m: np.ndarray, vel_mps: np.ndarray) -> np.ndarray | None:
        return None

    def measure(self, hist_q: np.ndarray, hist_qd: np.ndarray, dt_s: float, rng: np.random.Generator | None):
        """Measured (q, qd) (6,) from the histories (N, 6) of true (or earlier effects') states,
        newest first, every ``dt_s``. Read the histories; never write into them (EffectStack
        hands the first measuring effect the machine's own arrays)."""
        return hist_q[0], hist_qd[0]

    def measure_impact(self, hit_m: np.ndarray) -> np.ndarray:
        return hit_m

    def history_steps(self) -> int:
        """How many past true states ``measure`` needs (1 = only the current one)."""
        return 1

    def initial_state(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return q, qd


def joint_params(base: str, unit: str, nominal: float, lo: float, hi: float, doc: str, source: str,
                 joints: tuple[str, ...] = ACTIVE_JOINTS) -> tuple[Param, ...]:
    """One Param ``<base>_<joint>`` per joint of ``joints`` with the same prior."""
    return tuple(Param(f"{base}_{j}", unit, nominal, lo, hi, f"{doc}, {j}", source) for j in joints)


class PerJointEffect(Effect):
    """An effect with one parameter per joint of ``joints`` (default the four active ones);
    the keyword ``joint_base`` alone sets all of them alike (``ValveLag(lag_s=0.3)``).

    The diagnosis fits such an effect joint by joint from each joint's own channels when it
    is ``separable`` (a valve parameter of one joint shows in that joint's motion). An effect
    whose every joint acts on the same shared channels (an encoder offset moves the true arm
    pose: gripper swing, impact) says ``separable = False``: the diagnosis sweeps each joint
    over all its footprint channels and fits the joint that explains most
    (:meth:`sim_twin.diagnosis.select.Evaluator.sweep`).

    Raises:
        ValueError: as Effect, or the all-joint keyword given together with a per-joint one.
    """

    joint_base: ClassVar[str] = ""
    joints: ClassVar[tuple[str, ...]] = ACTIVE_JOINTS
    separable: ClassVar[bool] = True

    def __init__(self, **values: float):
        if self.joint_base in values:
            common = values.pop(self.joint_base)
            clash = [k for k in values if k.startswith(self.joint_base + "_")]
            if clash:
                raise ValueError(f"effect {self.name!r}: give {self.joint_base} (all joints) or {clash}, not both")
            values.update({f"{self.joint_base}_{j}": common for j in self.joints})
        super().__init__(**values)

    @classmethod
    def joint_param_names(cls) -> tuple[str, ...]:
        return tuple(f"{cls.joint_base}_{j}" for j in cls.joints)

    @classmethod
    def joint_indices(cls) -> tuple[int, ...]:
        """Indices of ``joints`` in JOINT_NAMES."""
        return tuple(JOINT_NAMES.index(j) for j in cls.joints)

    def per_joint_values(self) -> np.ndarray:
        """(len(joints),) parameter values in ``joints`` order."""
        return np.array([self.values[n] for n in self.joint_param_names()])


def _overrides(effect: Effect, hook: str) -> bool:
    return getattr(type(effect), hook) is not getattr(Effect, hook)


class EffectStack:
    """A profile's effects applied in order (each hook composes left to right).

    Args:
        effects: Effect instances.
    """

    def __init__(self, effects: list[Effect] | tuple[Effect, ...] = ()):
        self.effects = list(effects)
        for e in self.effects:
            if not isinstance(e, Effect):
                raise TypeError(f"{e!r} is not a sim_twin.twin.effects.Effect")

    def __bool__(self) -> bool:
        return bool(self.effects)

    def has(self, hook: str) -> bool:
        return any(_overrides(e, hook) for e in self.effects)

    def _measuring(self) -> tuple[Effect, ...]:
        """The effects that override ``measure``, in order (looked up again only when
        :attr:`effects` is replaced or changes length: measure runs every 10 ms step)."""
        key = (id(self.effects), len(self.effects))
        if self.__dict__.get("_measuring_key") != key:
            self._measuring_fx = tuple(e for e in self.effects if _overrides(e, "measure"))
            self._measuring_key = key
        return self._measuring_fx

    def hydraulics(self, hp):
        for e in self.effects:
            hp = e.hydraulics(hp)
        return hp

    def setpoint(self, sp, q, qd):
        for e in self.effects:
            sp = e.setpoint(sp, q, qd)
        return sp

    def passive_friction(self, viscous, coulomb):
        for e in self.effects:
            viscous, coulomb = e.passive_friction(viscous, coulomb)
        return viscous, coulomb

    def model(self, mj_model) -> None:
        for e in self.effects:
            e.model(mj_model)

    def release_delay(self, mean_s, std_s):
        for e in self.effects:
            mean_s, std_s = e.release_delay(mean_s, std_s)
        return mean_s, std_s

    def grasp_offset(self) -> np.ndarray | None:
        total = None
        for e in self.effects:
            off = e.grasp_offset()
            if off is not None:
                total = np.asarray(off, dtype=float) if total is None else total + off
        return total

    def flight_accel(self, pos, vel):
        total = None
        for e in self.effects:
            a = e.flight_accel(pos, vel)
            if a is not None:
                total = a if total is None else total + a
        return total

    def history_steps(self) -> int:
        return max([1] + [e.history_steps() for e in self.effects])

    def measure_impact(self, hit_m: np.ndarray) -> np.ndarray:
        """Measured landing spot(s) (..., 3) from the true one(s), effects applied in order."""
        for e in self.effects:
            hit_m = e.measure_impact(hit_m)
        return hit_m

    def initial_state(self, q, qd):
        """True state behind a measured one, measurement effects undone last-applied first."""
        for e in reversed(self.effects):
            q, qd = e.initial_state(q, qd)
        return q, qd

    def measure(self, hist_q, hist_qd, dt_s, rng):
        """Measured (q, qd): the first measuring effect reads the true history (the arrays given:
        effects read their histories, none writes into them); later ones see a copy with the
        current row replaced by the previous effect's output."""
        q, qd = hist_q[0], hist_qd[0]
        first = True
        for e in self._measuring():
            if first:
                q, qd = e.measure(hist_q, hist_qd, dt_s, rng)
                first = False
                continue
            hq, hqd = hist_q.copy(), hist_qd.copy()
            hq[0], hqd[0] = q, qd
            q, qd = e.measure(hq, hqd, dt_s, rng)
        return q, qd
