"""Privileged observations for the asymmetric actor-critic (critic only; the actor never sees them).

Asymmetric actor-critic (Pinto et al. 2018, "Asymmetric Actor Critic for Image-Based Robot
Learning"; Rudin et al. 2022 for legged robots): the critic is only needed in training, so it may
see what the machine never measures -- here the episode's randomised dynamics parameters and the
true (latency- and noise-free) passive joint state. The actor, the exported ONNX policy and the
runtime keep the ``policy`` observation of runtime.observation unchanged.

Layout of the ``privileged`` group (float32, per environment; ``PRIVILEGED_SIZE`` = 31 in both
modes; ``PRIVILEGED_LAYOUT`` lists (name, size)):

    ==================  ====  ===============================================================
    name                size  value
    ==================  ====  ===============================================================
    valve_delay         4     valve transport delay per active joint (whole 10 ms steps, s),
                              normalised over ``valve_delay_s``; 0 unless hydraulic
    valve_lag           4     valve / velocity lag time constant tau per active joint, s,
                              normalised over ``lag_s`` (used by both actuation models)
    dead_band           4     valve dead band per active joint, over ``dead_band``; 0 unless
                              hydraulic
    velocity_scale      4     full-open speed factor per active joint, over
                              ``velocity_scale``; 0 unless hydraulic
    gain                4     velocity gain factor per active joint, over 1 +- ``gain_error``;
                              0 when hydraulic (the lag model's only)
    friction_scale      1     passive friction factor, over ``friction_scale`` (its logarithm
                              over the range's logarithms when ``friction_sampling`` is
                              "log_uniform")
    gripper_mass_scale  1     gripper mass / inertia factor, over ``gripper_mass_scale``
    release_delay       1     the episode's release delay (whole steps, s): (x - mean) /
                              (shift + 2 std) of ``release_delay_*``
    sensor_latency      2     encoder, IMU latency (whole steps, s), over
                              ``encoder_latency_s``, ``imu_latency_s``
    passive_q           2     true passive joint angles now, rad / pi
    passive_qd          2     true passive joint rates now, (rad/s) / 4
    grasp_offset        2     the payload's offset from the gripper centre along the gripper's
                              x and z axes, m, over ``grasp_forward_m``, ``grasp_up_m``
    ==================  ====  ===============================================================

Active joints in ACTIVE_JOINTS order (cabin turn, boom, stick, tilt). "Normalised over [lo, hi]"
is (x - (lo + hi) / 2) / ((hi - lo) / 2), in [-1, 1] for values drawn in the range (a little
beyond after rounding to whole steps, at most ~1.25 for the committed configs); a parameter whose
range is empty (not randomised in the config, or unused by the actuation model) reads 0. The
scaling is fixed rather than learned because rsl_rl's empirical normaliser, resumed with a sample
count of ~1e9, barely moves for newly added inputs (sim_twin.training.critic_surgery starts them at mean 0,
std 1).

The config's ``env.randomization`` mapping is checked and typed once, into :class:`Randomization`
(ranges not given take the defaults of ``RANDOMIZATION_DEFAULTS``), which the environment's reset
draws from and this module normalises over (one table for both).

The normalisation ranges are those the critic was *trained* with, which are not always the ranges
the episode is drawn from: fine-tuning on a site (sim_twin.adaptation.adapt.finetune_config) narrows the
site's parameters to [v, v], where every input would read 0 (mid of an empty range) instead of
where v sits in the range the resumed critic learned. Such a config keeps the base ranges under
``env.privileged_ranges`` (entries named and shaped as in ``env.randomization``, for the keys of
``PRIVILEGED_RANGE_KEYS``); :func:`normalisation_ranges` takes each key from there when present,
else from the randomisation. Configs without it (normal training) are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp

from runtime.observation import PHYSICS_PERIOD_S

if TYPE_CHECKING:  # mjx_env imports this module
    from sim_twin.training.mjx_env import EnvState

RANDOMIZATION_DEFAULTS: dict[str, tuple[float, float]] = {
    "lag_s": (0.03, 0.2),
    "friction_scale": (0.7, 1.3),
    "dead_band": (0.05, 0.05),
    "valve_delay_s": (0.04, 0.04),
    "velocity_scale": (1.0, 1.0),
    "encoder_latency_s": (0.0, 0.0),
    "imu_latency_s": (0.0, 0.0),
    "gripper_mass_scale": (1.0, 1.0),
    "grasp_forward_m": (0.0, 0.0),
    "grasp_up_m": (0.0, 0.0),
}
"""Ranges [lo, hi] the environment draws from when the config's ``randomization`` lacks them."""

RELEASE_DELAY_DEFAULTS = {"release_delay_mean_s": 0.258, "release_delay_std_s": 0.015, "release_delay_shift_s": 0.0}
GAIN_ERROR_DEFAULT = 0.1
VELOCITY_NOISE_DEFAULT = 0.02
PASSIVE_ANGLE_SCALE_RAD = math.pi
PASSIVE_RATE_SCALE_RADPS = 4.0

PRIVILEGED_LAYOUT: tuple[tuple[str, int], ...] = (
    ("valve_delay", 4),
    ("valve_lag", 4),
    ("dead_band", 4),
    ("velocity_scale", 4),
    ("gain", 4),
    ("friction_scale", 1),
    ("gripper_mass_scale", 1),
    ("release_delay", 1),
    ("sensor_latency", 2),
    ("passive_q", 2),
    ("passive_qd", 2),
    ("grasp_offset", 2),
)
PRIVILEGED_SIZE = sum(n for _, n in PRIVILEGED_LAYOUT)

PRIVILEGED_RANGE_KEYS: tuple[str, ...] = (
    *RANDOMIZATION_DEFAULTS,
    "gain_error",
    *RELEASE_DELAY_DEFAULTS,
    "friction_sampling",
)
"""The ``randomization`` entries :func:`privileged_observation` normalises over (with
``friction_sampling``, whether the friction factor is read on a linear or a log scale)."""

OTHER_RANDOMIZATION_KEYS = ("actuation", "obs_noise", "velocity_noise", "valve_spread", "valve_coupling", "wind_mps",
                            "wind_fraction", "nominal_fraction")
"""The ``randomization`` entries the environment reads besides ``PRIVILEGED_RANGE_KEYS``
(sim_twin.training.mjx_env: actuation "lag" or "hydraulic", observation-noise stds, velocity-reference
noise, machine-wide valve slowness spread, which valve parameters that slowness sets, the largest
wind speed and the share of windy episodes, the share of nominal machines; the wind is not among the
critic's inputs)."""

VALVE_COUPLINGS = ("delay_lag", "all")
"""Which hydraulic parameters the machine-wide slowness g ~ U(0, 1) sets (with ``valve_spread``
per joint around it): "delay_lag" the valve delay and lag only (dead band and full-open speed drawn
independently), "all" also the dead band (at fraction g of its range) and the full-open speed (at
fraction 1 - g: a slow machine is also a weak one). "all" puts episodes in the range's corners,
where the site matrix's slow- and fast-hydraulics profiles lie (all four parameters near their
slow or fast ends); independent draws seldom go there."""

FRICTION_SAMPLINGS = ("uniform", "log_uniform")
"""How ``friction_scale`` is drawn: uniformly, or uniformly in its logarithm (a range spanning
more than a decade, e.g. a worn gripper's tenfold viscous friction, without most episodes at
its top)."""


@dataclass(frozen=True)
class ObsNoise:
    """Standard deviations of the white noise on the sensed joint state (sim_twin.training.mjx_env's
    ``_measure``): angles [rad] and rates [rad/s] of the active and the passive joints. CHOSEN
    values in configs/*.json (about twice the nominal sensing of sim_twin/twin/profile.py SensorParams)."""

    q_active: float = 0.0
    qd_active: float = 0.0
    q_passive: float = 0.0
    qd_passive: float = 0.0


OBS_NOISE_KEYS = tuple(f.name for f in fields(ObsNoise))
"""The entries of ``randomization.obs_noise`` (the fields of :class:`ObsNoise`)."""


def check_randomization(rand: dict, where: str = "env.randomization", keys: tuple[str, ...] | None = None) -> None:
    """Refuse a ``randomization`` mapping (or ``privileged_ranges`` with ``keys``) that the
    environment would read wrongly: a key it does not know (a typo would otherwise fall back to a
    default silently), a range that is not [lo, hi] with lo <= hi, a negative std or spread, an
    unknown actuation or observation-noise entry, ``valve_coupling`` "all" without the machine-wide
    slowness it acts through (``valve_spread`` < 1).

    Raises:
        ValueError: naming the entry and what is wrong.
    """
    known = keys if keys is not None else (*PRIVILEGED_RANGE_KEYS, *OTHER_RANDOMIZATION_KEYS)
    unknown = sorted(set(rand) - set(known))
    if unknown:
        raise ValueError(f"{where}: unknown entries {unknown} (known: {sorted(known)})")
    for name in RANDOMIZATION_DEFAULTS:
        if name in rand:
            r = rand[name]
            if not (isinstance(r, (list, tuple)) and len(r) == 2 and all(isinstance(x, (int, float)) for x in r) and r[0] <= r[1]):
                raise ValueError(f"{where}.{name} must be a range [lo, hi] with lo <= hi, not {r!r}")
    for name in ("gain_error", *RELEASE_DELAY_DEFAULTS, "velocity_noise", "valve_spread", "wind_mps"):
        if name in rand and not (isinstance(rand[name], (int, float)) and rand[name] >= 0):
            raise ValueError(f"{where}.{name} must be a number >= 0, not {rand[name]!r}")
    for name, default in (("nominal_fraction", 0.0), ("wind_fraction", 1.0)):
        frac = rand.get(name, default)
        if isinstance(frac, bool) or not (isinstance(frac, (int, float)) and 0.0 <= frac <= 1.0):
            raise ValueError(f"{where}.{name} must be a number in [0, 1], not {frac!r}")
    if rand.get("friction_sampling", "uniform") not in FRICTION_SAMPLINGS:
        raise ValueError(f"{where}.friction_sampling must be one of {list(FRICTION_SAMPLINGS)}, not {rand['friction_sampling']!r}")
    if rand.get("friction_sampling") == "log_uniform" and rand.get("friction_scale", RANDOMIZATION_DEFAULTS["friction_scale"])[0] <= 0:
        raise ValueError(f"{where}.friction_scale must be > 0 to be drawn log-uniformly, not {rand.get('friction_scale')!r}")
    if rand.get("valve_coupling", "delay_lag") not in VALVE_COUPLINGS:
        raise ValueError(f"{where}.valve_coupling must be one of {list(VALVE_COUPLINGS)}, not {rand['valve_coupling']!r}")
    if rand.get("valve_coupling") == "all" and rand.get("valve_spread", 1.0) >= 1.0:
        raise ValueError(f"{where}.valve_coupling 'all' couples the valves through the machine-wide slowness, which "
                         f"valve_spread >= 1 turns off (valve_spread {rand.get('valve_spread', 1.0)!r}): set valve_spread < 1")
    if rand.get("actuation", "lag") not in ("lag", "hydraulic"):
        raise ValueError(f"{where}.actuation must be 'lag' or 'hydraulic', not {rand['actuation']!r}")
    noise = rand.get("obs_noise", {})
    if not isinstance(noise, dict) or set(noise) - set(OBS_NOISE_KEYS):
        raise ValueError(f"{where}.obs_noise must map {list(OBS_NOISE_KEYS)} to stds, not {noise!r}")


Range = tuple[float, float]


@dataclass(frozen=True)
class Randomization:
    """The per-episode domain randomisation of the training environment (config ``env.randomization``),
    checked and typed: every entry the environment reads, with its default where the config lacks it.

    Ranges are [lo, hi] drawn uniformly per episode (per active joint where the privileged layout
    has 4 values): ``lag_s`` valve / velocity lag time constant [s], ``valve_delay_s`` valve
    transport delay [s], ``dead_band`` valve dead band [fraction of full opening],
    ``velocity_scale`` full-open speed factor, ``friction_scale`` passive friction factor,
    ``gripper_mass_scale`` gripper mass and inertia factor, ``encoder_latency_s`` and
    ``imu_latency_s`` sensor latencies [s], ``grasp_forward_m`` and ``grasp_up_m`` the payload's
    offset from the gripper centre along the gripper's x and z axes [m] (the CPU twin's
    ``grasp_offset`` effect, sim_twin.twin.effects.payload.GraspOffset); ``friction_sampling`` "log_uniform" draws the friction
    factor uniformly in its logarithm instead (FRICTION_SAMPLINGS). Scalars: ``actuation`` "lag" (first-order velocity lag
    with gain error ±``gain_error``) or "hydraulic" (the runtime's PID + FF law on the valve model);
    the release delay [s] ~ N(``release_delay_mean_s``, ``release_delay_std_s``) plus a uniform
    episode shift of ±``release_delay_shift_s`` (mean 258 ms: machine-spec.md); ``velocity_noise``
    std of the velocity-reference noise [fraction of the joint's velocity limit]; ``valve_spread``
    per-joint spread of the valve speed around one machine-wide slowness (1: independent per joint);
    ``valve_coupling`` which valve parameters that slowness sets (VALVE_COUPLINGS);
    ``wind_mps`` the largest speed [m/s] of a steady horizontal wind drawn per episode (direction
    uniform, speed uniform in [0, wind_mps]; 0: no wind, nothing computed) whose share of the
    payload's drag moves the landing (sim_twin.twin.effects.site.wind_landing_shift), in the share
    ``wind_fraction`` [0, 1] of the episodes (default 1: every episode; the others in still air);
    ``nominal_fraction`` the share of episodes [0, 1] whose machine is the nominal one instead of a
    draw from the ranges (:func:`sim_twin.training.mjx_env.nominal_machine`: the twin's nominal
    valves, friction and gripper mass ×1, no encoder latency, the nominal IMU latency, no grasp
    offset, no gain error, no episode shift of the release delay; 0: none, nothing drawn);
    ``obs_noise`` (:class:`ObsNoise`). Defaults: ``RANDOMIZATION_DEFAULTS``,
    ``RELEASE_DELAY_DEFAULTS``, ``GAIN_ERROR_DEFAULT``, ``VELOCITY_NOISE_DEFAULT`` (CHOSEN).
    """

    actuation: str = "lag"
    lag_s: Range = RANDOMIZATION_DEFAULTS["lag_s"]
    friction_scale: Range = RANDOMIZATION_DEFAULTS["friction_scale"]
    dead_band: Range = RANDOMIZATION_DEFAULTS["dead_band"]
    valve_delay_s: Range = RANDOMIZATION_DEFAULTS["valve_delay_s"]
    velocity_scale: Range = RANDOMIZATION_DEFAULTS["velocity_scale"]
    encoder_latency_s: Range = RANDOMIZATION_DEFAULTS["encoder_latency_s"]
    imu_latency_s: Range = RANDOMIZATION_DEFAULTS["imu_latency_s"]
    gripper_mass_scale: Range = RANDOMIZATION_DEFAULTS["gripper_mass_scale"]
    grasp_forward_m: Range = RANDOMIZATION_DEFAULTS["grasp_forward_m"]
    grasp_up_m: Range = RANDOMIZATION_DEFAULTS["grasp_up_m"]
    gain_error: float = GAIN_ERROR_DEFAULT
    release_delay_mean_s: float = RELEASE_DELAY_DEFAULTS["release_delay_mean_s"]
    release_delay_std_s: float = RELEASE_DELAY_DEFAULTS["release_delay_std_s"]
    release_delay_shift_s: float = RELEASE_DELAY_DEFAULTS["release_delay_shift_s"]
    velocity_noise: float = VELOCITY_NOISE_DEFAULT
    valve_spread: float = 1.0
    friction_sampling: str = "uniform"
    valve_coupling: str = "delay_lag"
    wind_mps: float = 0.0
    wind_fraction: float = 1.0
    nominal_fraction: float = 0.0
    obs_noise: ObsNoise = field(default_factory=ObsNoise)

    @classmethod
    def from_dict(cls, rand: dict, where: str = "env.randomization") -> Randomization:
        """From a config's ``randomization`` mapping, checked by :func:`check_randomization`.

        Raises:
            ValueError: an unknown entry, a range that is not [lo, hi], a negative std or spread,
                an unknown actuation or observation-noise entry.
        """
        check_randomization(rand, where)
        return cls(**_typed_entries(rand))

    @property
    def hydraulic(self) -> bool:
        """The actuation model is the runtime's controller on the valve model (else the lag model)."""
        return self.actuation == "hydraulic"

    def range(self, name: str) -> Range:
        """The [lo, hi] range of randomisation ``name`` (a key of ``RANDOMIZATION_DEFAULTS``)."""
        if name not in RANDOMIZATION_DEFAULTS:
            raise KeyError(f"{name!r} is not a randomisation range (known: {sorted(RANDOMIZATION_DEFAULTS)})")
        return getattr(self, name)

    def with_ranges(self, privileged_ranges: dict | None) -> Randomization:
        """This randomisation with the entries of a config's ``env.privileged_ranges`` (keys of
        ``PRIVILEGED_RANGE_KEYS``) in place of its own: the ranges the critic's privileged inputs
        are normalised over (see the module docstring); itself when there are none.

        Raises:
            ValueError: an entry that :func:`check_randomization` refuses for ``privileged_ranges``.
        """
        if not privileged_ranges:
            return self
        check_randomization(privileged_ranges, "env.privileged_ranges", PRIVILEGED_RANGE_KEYS)
        return replace(self, **_typed_entries(privileged_ranges))


def _typed_entries(rand: dict) -> dict:
    """A checked ``randomization`` mapping's entries as :class:`Randomization` field values."""
    out: dict[str, Any] = {}
    for name, value in rand.items():
        if name in RANDOMIZATION_DEFAULTS:
            out[name] = (float(value[0]), float(value[1]))
        elif name == "obs_noise":
            out[name] = ObsNoise(**{k: float(v) for k, v in value.items()})
        elif name in ("actuation", "friction_sampling", "valve_coupling"):
            out[name] = value
        else:
            out[name] = float(value)
    return out


def trained_ranges(rand: dict) -> dict:
    """The entries of ``rand`` (a config's ``randomization``) that the privileged normalisation
    reads (``PRIVILEGED_RANGE_KEYS``), copied (lists as new lists): what a derived config stores
    as ``env.privileged_ranges`` so that its critic inputs stay on the base training's scale."""
    return {k: list(rand[k]) if isinstance(rand[k], (list, tuple)) else rand[k] for k in PRIVILEGED_RANGE_KEYS if k in rand}


def _normalise(x, lo: float, hi: float, used: bool = True):
    """(x - mid) / half_range; zeros where the range is empty or the parameter unused."""
    if not used or hi <= lo:
        return jnp.zeros_like(jnp.asarray(x, dtype=jnp.float32))
    return (x - 0.5 * (lo + hi)) / (0.5 * (hi - lo))


def _friction_input(rand: Randomization, fric):
    """The friction factor's privileged input: normalised over ``friction_scale``, in log space
    when it is drawn log-uniformly (so that the input is uniform in [-1, 1] either way)."""
    lo, hi = rand.range("friction_scale")
    if rand.friction_sampling == "log_uniform" and lo > 0:
        return _normalise(jnp.log(fric), math.log(lo), math.log(hi))
    return _normalise(fric, lo, hi)


def privileged_observation(rand: Randomization, hydraulic: bool, s: EnvState) -> jnp.ndarray:
    """The privileged vector of one environment (layout in the module docstring).

    Args:
        rand: the ranges to normalise over: the config's randomisation, or
            ``randomization.with_ranges(privileged_ranges)`` when the config has ``privileged_ranges``.
        hydraulic: the actuation model is "hydraulic" (else the first-order lag model).
        s: the state of one environment (sim_twin.training.mjx_env.EnvState).

    Returns:
        (PRIVILEGED_SIZE,) float32.
    """
    dt = PHYSICS_PERIOD_S
    g = rand.gain_error
    mean = rand.release_delay_mean_s
    half = 2.0 * rand.release_delay_std_s + rand.release_delay_shift_s
    rng = rand.range
    lat = s.sensor_lag * dt
    parts = [
        _normalise(s.valve_delay * dt, *rng("valve_delay_s"), used=hydraulic),
        _normalise(s.tau, *rng("lag_s")),
        _normalise(s.dead_band, *rng("dead_band"), used=hydraulic),
        _normalise(s.vscale, *rng("velocity_scale"), used=hydraulic),
        _normalise(s.gain, 1.0 - g, 1.0 + g, used=not hydraulic),
        _friction_input(rand, s.fric)[None],
        _normalise(s.gripper_scale, *rng("gripper_mass_scale"))[None],
        _normalise(s.delay_steps * dt, mean - half, mean + half)[None],
        _normalise(lat[0], *rng("encoder_latency_s"))[None],
        _normalise(lat[1], *rng("imu_latency_s"))[None],
        s.data.qpos[4:6] / PASSIVE_ANGLE_SCALE_RAD,
        s.data.qvel[4:6] / PASSIVE_RATE_SCALE_RADPS,
        _normalise(s.grasp[0], *rng("grasp_forward_m"))[None],
        _normalise(s.grasp[2], *rng("grasp_up_m"))[None],
    ]
    return jnp.concatenate([jnp.reshape(jnp.asarray(p, dtype=jnp.float32), (-1,)) for p in parts])
