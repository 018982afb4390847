"""MJX training environment for the throwing task (paper Sec. III-B to III-F).

Physics is MuJoCo's (MJX) on the same MJCF as the CPU twin, without its joint-limit constraints
(``ThrowEnvCore``'s ``joint_limits`` says why). The observation and the action decoding are
runtime.observation's, the kinematics and terminations runtime.machine's, the passive friction and
ballistics sim_twin.twin.physics': one definition shared with the machine.

Per control step (12.5 Hz) the policy's action is decoded into joint-velocity references and the
release flag; 8 physics steps (100 Hz) follow, in each of which the *training joint-velocity
controller* drives the stiff velocity servos of the MJCF: a first-order lag with per-episode
random time constant, gain error and velocity-command noise (the paper's "artificial velocity
command randomization", Sec. III-B), or, with ``randomization.actuation = "hydraulic"``, the
runtime's own PID + feed-forward law (runtime.controller.pid_ff_law) feeding a valve model with
per-episode random dead band, transport delay, lag and full-open speed (sim_twin.twin.hydraulics),
plus velocity-command noise. Either way the servo setpoint passes the hydraulic cylinders
(sim_twin.twin.hydraulics.cylinder_step: closed valves hold the load, joint ends are hard stops) as in
the simulated machine. Evaluation still runs the runtime's controller object on the
simulated machine, at the nominal parameters.

Sensing (paper Sec. IV: "random noises added to the observation vector"): the policy observes
the joints as the machine measures them, per episode ``encoder_latency_s`` / ``imu_latency_s``
old (whole 10 ms steps, active joints / passive joints) plus white noise of the std's in
``obs_noise`` (q_active, qd_active, q_passive, qd_passive); rewards and terminations use the true
state. Per episode the gripper's mass and inertia are scaled by ``gripper_mass_scale``
(sim_twin.twin.effects.machine.HangingMass does the same on the CPU twin) and the passive friction by
``friction_scale`` (uniformly, or log-uniformly with ``friction_sampling``); the valve parameters
are drawn per joint, delay and lag around one machine-wide slowness (``valve_spread``), with
``valve_coupling`` "all" the dead band and full-open speed too (sim_twin.training.privileged.VALVE_COUPLINGS).
``privileged(state)`` gives the critic those per-episode parameters and the true passive joint state (asymmetric actor-critic; layout in sim_twin.training.privileged).

Payload (paper Sec. III-B): held at the gripper centre, or, with ``randomization.grasp_forward_m``
/ ``grasp_up_m``, at a per-episode random offset from it along the gripper's x and z axes (the CPU
twin's ``grasp_offset`` effect; a payload gripped off-centre); the release command opens the
gripper after the release delay (sampled per episode around the identified 258 ms); the payload
then leaves from where it is held with that point's velocity and flies ballistically (analytic)
until it reaches the ground, which ends the episode with the positive terminal reward. With
``randomization.wind_mps`` a steady horizontal wind drawn per episode (in the share
``wind_fraction`` of the episodes) moves the landing by its share of the payload's drag, to first
order (sim_twin.twin.effects.site.wind_landing_shift; the CPU twin's ``wind`` effect integrates it).

Machine (per episode): valve delay, lag, dead band and speed, passive friction, gripper mass, gain
error and sensor latencies are drawn from ``randomization``'s ranges; with
``randomization.nominal_fraction`` that share of the episodes gets the nominal machine instead
(:func:`nominal_machine`), at the fast, light end of most ranges, where a policy right on average
over them throws long (docs/training.md, "Four more seeds, and the far-target overshoot").

Rewards (paper Sec. III-E): one function per term in sim_twin.training.rewards, weights in the config's
``env.rewards`` (typed: sim_twin.training.rewards.RewardScales); ``step`` returns every scaled term in
``info["reward_terms"]`` and the reward is their sum. Choices the paper leaves open are marked
CHOSEN in configs/throw_2d.json.

Physics runs on MJX's JAX implementation by default; ``ThrowEnvCore(cfg, impl="warp")`` asks MJX
for its MuJoCo Warp implementation instead (needs warp-lang and a CUDA GPU).

Everything below works on one environment and is vmapped over ``num_envs``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from runtime.controller import ControllerGains, pid_ff_law
from runtime.machine import ACTIVE_VELOCITY_LIMITS, JOINT_LOWER, JOINT_UPPER, NUM_ACTIVE, clearance_violations, forward_kinematics
from runtime.observation import (
    HISTORY_STEPS,
    MAX_HISTORY_STEPS,
    PHYSICS_PERIOD_S,
    SUBSTEPS,
    build_observation,
    decode_action,
    num_actions,
    observation_size,
)
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from sim_twin.training.privileged import PRIVILEGED_RANGE_KEYS, Randomization, check_randomization, privileged_observation
from sim_twin.training.rewards import RewardInputs, RewardScales, reward_terms, total_reward
from sim_twin.twin.effects.payload import GRIPPER_CENTRE_LOCAL_M, gripper_frame_point
from sim_twin.twin.effects.site import wind_landing_shift
from sim_twin.twin.hydraulics import NOMINAL_DEAD_BAND, NOMINAL_DELAY_S, NOMINAL_LAG_S, cylinder_step, dead_band_flow, lag_step
from sim_twin.twin.initial_pose import pose_from_uniform, pose_is_valid
from sim_twin.twin.model import PAYLOAD_RADIUS_M, load_model, passive_inertia
from sim_twin.twin.physics import ballistic_impact_time, ballistic_position, passive_friction_force
from sim_twin.twin.profile import SensorParams

MAX_VALVE_DELAY_STEPS = 30  # longest valve transport delay the training env can model (0.30 s)
MAX_SENSOR_LAG_STEPS = 5  # longest sensor latency the training env can model (0.05 s)
GRIPPER_BODY = "gripper"  # body whose mass and inertia are randomised (sim_twin.twin.effects.machine)
POSE_CANDIDATES = 16  # rejection sampling without loops: first valid of 16 (P(all bad) ~ 2e-3)
FALLBACK_POSE_U = np.array([0.45, 0.45, 0.5])  # a known valid pose if all candidates fail


@dataclass(frozen=True)
class ForcedRelease:
    """Forced release (paper Sec. III-D): with ``probability`` per control step the gripper is
    opened when it is within ``radius_m`` (horizontal) of the target and slower than ``speed_mps``
    (CHOSEN values in configs/*.json)."""

    probability: float = 0.05
    radius_m: float = 1.5
    speed_mps: float = 0.5


@dataclass(frozen=True)
class FarTargets:
    """Target-distance weighting: a ``fraction`` of episodes draws its target distance from
    ``range_m`` [m] instead of the whole ``target_range_m`` (CHOSEN values in configs/*.json). The
    far end of the range is where a from-scratch policy's spread stays largest longest, so more of
    the samples go there; 0 keeps the uniform draw."""

    fraction: float = 0.0
    range_m: tuple[float, float] = (9.0, 10.7)


def _typed(cls, d: dict, what: str):
    """``cls(**d)`` with a clear error for unknown keys (a typo would otherwise be ignored)."""
    names = {f.name for f in fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ValueError(f"unknown {what} settings {sorted(unknown)}; known: {sorted(names)}")
    return cls(**d)


@dataclass(frozen=True)
class EnvConfig:
    """Task, reward and randomisation settings (see configs/*.json).

    ``rewards``, ``forced_release``, ``far_targets`` and ``randomization`` are typed
    (RewardScales, ForcedRelease, FarTargets, sim_twin.training.privileged.Randomization).
    ``privileged_ranges`` stays the config's (checked) partial mapping: the entries that override
    the randomisation's ranges where the critic's privileged inputs are normalised
    (``randomization.with_ranges(privileged_ranges)``).
    """

    mode: str = "2d"
    episode_length_s: float = 10.0
    target_range_m: tuple[float, float] = (5.0, 10.7)
    rewards: RewardScales = field(default_factory=lambda: RewardScales(
        delta_err=1.0, err_3d=0.05, b1=0.1, act_diff=0.01, act=0.002, failure=-5.0, landing=10.0, b2=0.5))
    forced_release: ForcedRelease = field(default_factory=ForcedRelease)
    far_targets: FarTargets = field(default_factory=FarTargets)
    randomization: Randomization = field(default_factory=Randomization)
    history_steps: int = HISTORY_STEPS
    """Control steps of joint positions and velocities in the actor's observation (runtime.observation;
    the paper's four by default); the exported manifest's observation_layout declares it."""
    privileged_ranges: dict[str, Any] = field(default_factory=dict)
    """Ranges the critic's privileged inputs are normalised over where they differ from
    ``randomization`` (a fine-tuning config's base ranges; see sim_twin.training.privileged)."""

    @property
    def max_steps(self) -> int:
        return int(round(self.episode_length_s / (PHYSICS_PERIOD_S * SUBSTEPS)))

    @classmethod
    def from_dict(cls, d: dict) -> EnvConfig:
        """From the config file's ``env`` mapping.

        Raises:
            ValueError: unknown keys (randomisation entries included:
                sim_twin.training.privileged.check_randomization), a missing reward weight, a mode
                other than 2d / 3d, or a ``history_steps`` outside 1..MAX_HISTORY_STEPS.
        """
        d = dict(d)
        if d.get("mode", "2d") not in ("2d", "3d"):
            raise ValueError(f"env.mode must be '2d' or '3d', not {d['mode']!r}")
        if "target_range_m" in d:
            d["target_range_m"] = tuple(float(x) for x in d["target_range_m"])
        if "rewards" in d:
            d["rewards"] = RewardScales.from_dict(d["rewards"])
        if "forced_release" in d:
            d["forced_release"] = _typed(ForcedRelease, d["forced_release"], "forced_release")
        if "randomization" in d:
            d["randomization"] = Randomization.from_dict(d["randomization"])
        check_randomization(d.get("privileged_ranges", {}), "env.privileged_ranges", PRIVILEGED_RANGE_KEYS)
        if "history_steps" in d:
            steps = d["history_steps"]
            if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_HISTORY_STEPS:
                raise ValueError(f"env.history_steps must be a whole number in 1..{MAX_HISTORY_STEPS}, not {steps!r}")
        if "far_targets" in d:
            far = dict(d["far_targets"])
            if "range_m" in far:
                far["range_m"] = tuple(float(x) for x in far["range_m"])
            d["far_targets"] = _typed(FarTargets, far, "far_targets")
            if not 0.0 <= d["far_targets"].fraction <= 1.0:
                raise ValueError(f"far_targets.fraction must be in [0, 1], not {d['far_targets'].fraction}")
        return _typed(cls, d, "env")

    def as_dict(self) -> dict:
        """The config as plain JSON-able data (the ``env`` mapping of a config file)."""
        return asdict(self)


def training_model(joint_limits: bool = False) -> mujoco.MjModel:
    """The MJCF the training physics runs (sim_twin.twin.model.load_model), without its joint-limit
    constraints unless ``joint_limits`` (``ThrowEnvCore``'s ``joint_limits`` says why)."""
    m = load_model()
    if not joint_limits:
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT
    return m


def _graph_mode_arg(impl: str, graph_mode: str | None) -> dict:
    """``{"graph_mode": warp.JaxCallableGraphMode.<graph_mode>}`` for mjx.put_model, or {} (MJX's
    default; always for ``impl="jax"``).

    Raises:
        ValueError: an unknown mode name.
    """
    if impl != "warp" or graph_mode is None:
        return {}
    from mujoco.mjx.warp import types as mjxw_types

    modes: Any = mjxw_types.GraphMode  # warp.JaxCallableGraphMode where warp-lang is installed, else int
    names = [] if modes is int else [m.name for m in modes]
    if graph_mode not in names:
        raise ValueError(f"unknown graph_mode {graph_mode!r}; known: {names or 'none (warp-lang is not installed)'}")
    return {"graph_mode": modes[graph_mode]}


def nominal_machine() -> dict[str, float]:
    """The nominal simulated machine in the training environment's per-episode terms, which
    ``env.randomization.nominal_fraction`` of the episodes get instead of a draw from the ranges:
    the twin's nominal valve (sim_twin.twin.hydraulics ``NOMINAL_DEAD_BAND``, ``NOMINAL_DELAY_S`` [s],
    ``NOMINAL_LAG_S`` [s]), full-open speed, passive friction and gripper mass ×1, no gain error,
    no encoder latency, the nominal gripper-IMU latency (sim_twin.twin.profile.SensorParams
    ``imu_latency_s`` [s]), no grasp offset [m] and no episode shift of the release delay (its
    per-throw jitter stays)."""
    return {"dead_band": NOMINAL_DEAD_BAND, "valve_delay_s": NOMINAL_DELAY_S, "lag_s": NOMINAL_LAG_S, "velocity_scale": 1.0,
            "friction_scale": 1.0, "gripper_mass_scale": 1.0, "gain": 1.0, "encoder_latency_s": 0.0,
            "imu_latency_s": SensorParams().imu_latency_s, "grasp_m": 0.0, "release_delay_shift_s": 0.0}


def _landing_xy(p: jax.Array, v: jax.Array, t: jax.Array | None = None) -> jax.Array:
    """Where (x, y) (2,) a payload freed at ``p`` (3,) with ``v`` (3,) lands, m, machine frame:
    drag-free flight to the height of its centre at touch-down (runtime.ballistics), taking ``t``
    s (its flight time, computed when None)."""
    if t is None:
        t = ballistic_impact_time(jnp, p, v, PAYLOAD_RADIUS_M)
    return ballistic_position(jnp, p, v, t)[:2]


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class EnvState:
    """State of one throwing environment between control steps: a JAX pytree (every field a leaf
    or, ``data``, a pytree), so it passes through ``jit``, ``vmap`` and ``lax`` loops; a batch of
    ``num_envs`` environments is one EnvState whose leaves carry a leading (num_envs,) axis.
    :meth:`replace` returns a copy with some fields changed (the state is immutable).

    Shapes below are of one environment; angles rad, lengths m, times s, machine frame.
    ``A`` = NUM_ACTIVE (4) active joints, ``num_act`` = num_actions(mode).

    Attributes:
        data: mjx.Data of the physics (qpos, qvel (6,): 4 active then 2 passive joints).
        q_hist, qd_hist: (H, 6) the last H (``EnvConfig.history_steps``) measured joint positions /
            velocities, newest first (what the observation is built from).
        prev_action: (num_act,) the previous action.
        target: (3,) ground target.
        step: () int32 control steps taken in this episode.
        release_cmd: () bool the release was commanded (by the policy or forced).
        countdown: () int32 physics steps until the gripper opens (-1: no release pending).
        opened: () bool the gripper has opened.
        ball_p0, ball_v0: (3,) payload position and velocity at the opening, m and m/s.
        t_open: () time since the opening, s.
        t_flight: () ballistic flight time from the opening to the ground, s.
        err2_min, err3_min: () smallest horizontal / 3-D distance of payload to target so far, m.
        lag_v: (4,) the actuation lag's output (fraction of full speed, or rad/s for the lag model).
        sensor_lag: (2,) int32 sensor latency, physics steps (active joints, passive joints).
        phys_q, phys_qd: (MAX_SENSOR_LAG_STEPS + 1, 6) true joint positions / velocities of the
            last physics steps, newest first (the latency buffer).
        gripper_scale: () gripper mass and inertia factor.
        x_ref: (A,) the cylinders' held joint positions (sim_twin.twin.hydraulics.cylinder_step).
        tau: (4,) actuation lag time constants, s.
        gain: (4,) velocity-command gain factors (lag model).
        delay_steps: () int32 release delay, physics steps.
        fric: () passive-joint friction factor.
        grasp: (3,) payload offset from the gripper centre in the gripper frame (x, 0, z).
        key: (2,) uint32 PRNG key of this environment.
        integral, prev_err: (4,) the PID's integral and previous error (hydraulic model).
        peaks: (2, 4) the feed-forward law's peak memory (runtime.controller.pid_ff_law).
        valve_buf: (MAX_VALVE_DELAY_STEPS + 1, 4) valve flows of the last physics steps, newest
            first (the transport delay's buffer).
        valve_delay: (4,) int32 valve transport delay, physics steps.
        dead_band: (4,) valve dead band (fraction of full flow).
        vscale: (4,) valve full-open speed factor.
        held_impact: (2,) where the held payload would land (x, y) if it were freed now, as of the
            last physics step, m (drag-free flight, runtime.ballistics).
        release_slope: () how fast that landing point moved at the physics step the gripper
            opened, m/s (0 before the opening): the landing's sensitivity to the opening time.
            Both are tracked only when the recipe weighs ``rewards.release_slope`` (else 0).
        wind: (2,) the episode's steady horizontal wind, m/s (zero unless
            ``randomization.wind_mps`` > 0).
    """

    data: mjx.Data
    q_hist: jax.Array
    qd_hist: jax.Array
    prev_action: jax.Array
    target: jax.Array
    step: jax.Array
    release_cmd: jax.Array
    countdown: jax.Array
    opened: jax.Array
    ball_p0: jax.Array
    ball_v0: jax.Array
    t_open: jax.Array
    t_flight: jax.Array
    err2_min: jax.Array
    err3_min: jax.Array
    lag_v: jax.Array
    sensor_lag: jax.Array
    phys_q: jax.Array
    phys_qd: jax.Array
    gripper_scale: jax.Array
    x_ref: jax.Array
    tau: jax.Array
    gain: jax.Array
    delay_steps: jax.Array
    fric: jax.Array
    grasp: jax.Array
    key: jax.Array
    integral: jax.Array
    prev_err: jax.Array
    peaks: jax.Array
    valve_buf: jax.Array
    valve_delay: jax.Array
    dead_band: jax.Array
    vscale: jax.Array
    held_impact: jax.Array
    release_slope: jax.Array
    wind: jax.Array

    def replace(self, **changes: Any) -> EnvState:
        """A copy with the fields named in ``changes`` replaced. Raises TypeError on an unknown field."""
        return dataclasses.replace(self, **changes)


class ThrowEnvCore:
    """Pure-JAX throwing environment (one env; vmap for many).

    Args:
        cfg: EnvConfig.
        impl: MJX implementation, "jax" or "warp".
        unroll_substeps: unroll the 8 physics substeps of a control step into straight-line code
            (``jax.lax.fori_loop(..., unroll=True)``) instead of a loop; the same arithmetic.
        joint_limits: keep the MJCF's joint-limit constraints (boom, dipper, telescope). Off by
            default: a training episode fails when one of these joints comes within 1 mrad / 1 mm of
            its range (runtime.machine.clearance_violations) and the cylinders stop at the same
            ends (sim_twin.twin.hydraulics.cylinder_step), so a limit constraint could act only
            where a joint overshoots an end, which ends the episode as failed unless the joint is
            back more than 1 mrad / 1 mm inside by the end of that control step (the parity test
            finds no such case); without them a physics step has no
            constraint rows and MJX skips the constraint solver (the same trajectories:
            tests/test_mjx_parity.py; the speed: tests/benchmarks/bench_training_throughput.py
            ``--joint-limits``).
        graph_mode: MJX's CUDA-graph mode for ``impl="warp"`` (a name of
            ``warp.JaxCallableGraphMode``: "WARP", MJX's default on a GPU, captures each MuJoCo
            Warp call's kernels into a CUDA graph and replays it; "WARP_STAGED" also stages the
            call's buffers so that one graph serves every call; "NONE" launches the kernels one
            by one); None: MJX's default. Ignored for ``impl="jax"``.
        reset_slots: None (default) resets the whole batch in every
            :meth:`step_autoreset_batch` and keeps the fresh state where an episode ended; a
            fraction in (0, 1) resets only the environments that finished, gathered into that
            fraction of the batch (falling back to the whole batch on a step where more finish).
            Both give the same states (a reset depends only on its key).

    Methods ``reset(key)`` and ``step(state, action)`` are jit/vmap friendly.
    Shapes: action (num_actions(mode),); observation (observation_size(mode, cfg.history_steps),).

    Raises:
        ValueError: ``reset_slots`` outside (0, 1).
    """

    def __init__(self, cfg: EnvConfig, impl: str = "jax", reset_slots: float | None = None, unroll_substeps: bool = False,
                 joint_limits: bool = False, graph_mode: str | None = None):
        if reset_slots is not None and not 0.0 < reset_slots < 1.0:
            raise ValueError(f"reset_slots must be a fraction in (0, 1) or None, got {reset_slots!r}")
        self.cfg = cfg
        self.impl = impl
        self.reset_slots = reset_slots
        self.unroll_substeps = unroll_substeps
        self.joint_limits = joint_limits
        self.graph_mode = graph_mode
        self.mode = cfg.mode
        self.num_obs = observation_size(cfg.mode, cfg.history_steps)
        self.num_act = num_actions(cfg.mode)
        mj_model = training_model(joint_limits)
        self.model = mjx.put_model(mj_model, impl=impl, **_graph_mode_arg(impl, graph_mode))
        self.gripper_id = mj_model.body(GRIPPER_BODY).id
        self.data0 = mjx.make_data(mj_model, impl=impl)
        self.inertia = jnp.asarray(passive_inertia(), dtype=jnp.float32)
        self.vmax = jnp.asarray(ACTIVE_VELOCITY_LIMITS, dtype=jnp.float32)
        self.w = cfg.rewards
        self.rand = cfg.randomization
        self.priv_ranges = cfg.randomization.with_ranges(cfg.privileged_ranges)
        self.forced = cfg.forced_release
        self.hydraulic = self.rand.hydraulic
        self.gains = ControllerGains()
        self.lower = jnp.asarray(JOINT_LOWER[:NUM_ACTIVE], dtype=jnp.float32)
        self.upper = jnp.asarray(JOINT_UPPER[:NUM_ACTIVE], dtype=jnp.float32)
        # a config constant: without an offset range the payload leaves from the gripper centre
        # as forward_kinematics gives it, the same arithmetic as before the option existed
        self.grasp_on = self.rand.grasp_forward_m != (0.0, 0.0) or self.rand.grasp_up_m != (0.0, 0.0)

    # --- reset ------------------------------------------------------------------------------
    def _sample_pose(self, key):
        k1, k2 = jax.random.split(key)
        u = jax.random.uniform(k1, (POSE_CANDIDATES, 3))
        if self.mode == "3d":
            yaw = jax.random.uniform(k2, (POSE_CANDIDATES,), minval=-jnp.pi, maxval=jnp.pi)
        else:
            yaw = jnp.zeros(POSE_CANDIDATES)
        qs = jax.vmap(lambda uu, y: pose_from_uniform(jnp, uu, y))(u, yaw)
        ok = jax.vmap(lambda q: pose_is_valid(jnp, q))(qs)
        fallback = pose_from_uniform(jnp, jnp.asarray(FALLBACK_POSE_U, dtype=jnp.float32), yaw[0])
        idx = jnp.argmax(ok)
        return jnp.where(jnp.any(ok), qs[idx], fallback)

    def _sample_target(self, key, cabin_turn):
        k1, k2 = jax.random.split(key)
        lo, hi = self.cfg.target_range_m
        dist = jax.random.uniform(k1, (), minval=lo, maxval=hi)
        far = self.cfg.far_targets
        if far.fraction > 0:  # a config constant: with the option off the draw is the uniform one, key for key
            k3, k4 = jax.random.split(jax.random.fold_in(key, 1))
            dist = jnp.where(jax.random.uniform(k3) < far.fraction,
                             jax.random.uniform(k4, (), minval=far.range_m[0], maxval=far.range_m[1]), dist)
        if self.mode == "2d":  # on the arm's plane in the cabin frame, then into the machine frame
            x_c = jnp.sqrt(dist**2 - ARM_PLANE_OFFSET_M**2)
            c, s = jnp.cos(cabin_turn), jnp.sin(cabin_turn)
            return jnp.stack([c * x_c - s * ARM_PLANE_OFFSET_M, s * x_c + c * ARM_PLANE_OFFSET_M, 0.0])
        az = jax.random.uniform(k2, (), minval=-jnp.pi, maxval=jnp.pi)
        return jnp.stack([dist * jnp.cos(az), dist * jnp.sin(az), 0.0])

    def reset(self, key) -> tuple[EnvState, jnp.ndarray]:
        """A fresh episode: random collision-free pose at rest with the gripper hanging plumb,
        a random ground target, fresh randomised parameters. Returns (state, observation)."""
        ks = jax.random.split(key, 8)
        q = self._sample_pose(ks[0])
        target = self._sample_target(ks[1], q[0])
        rd = self.rand
        delay_s = rd.release_delay_mean_s + rd.release_delay_std_s * jax.random.normal(ks[2])
        shift_s = jax.random.uniform(ks[7], (), minval=-1.0, maxval=1.0) * rd.release_delay_shift_s
        lg = rd.lag_s
        gain = 1.0 + jax.random.uniform(ks[4], (4,), minval=-rd.gain_error, maxval=rd.gain_error)
        fr = rd.friction_scale
        if rd.friction_sampling == "log_uniform":
            fric = jnp.exp(jax.random.uniform(ks[5], (), minval=jnp.log(fr[0]), maxval=jnp.log(fr[1])))
        else:
            fric = jax.random.uniform(ks[5], (), minval=fr[0], maxval=fr[1])
        kh = jax.random.split(ks[6], 8)
        db, dl, vs = rd.dead_band, rd.valve_delay_s, rd.velocity_scale
        # valve speed: independent per joint, or (valve_spread < 1) one machine-wide slowness
        # g ~ U(0, 1) (one pump and pilot circuit) with per-joint spread around it, for delay and lag alike
        spread = rd.valve_spread
        g = jax.random.uniform(kh[7], ())

        def fraction(k, centre, coupled: bool):
            """Per-joint fractions (4,) of a valve range: within ``spread`` of ``centre`` (clipped to
            [0, 1]) where coupled to the machine-wide slowness, else independent U(0, 1)."""
            if coupled:
                return jnp.clip(centre + spread * jax.random.uniform(k, (4,), minval=-1.0, maxval=1.0), 0.0, 1.0)
            return jax.random.uniform(k, (4,))

        coupled = spread < 1.0
        frac_d, frac_l = fraction(kh[1], g, coupled), fraction(ks[3], g, coupled)
        tau = lg[0] + frac_l * (lg[1] - lg[0])
        valve_delay = jnp.round((dl[0] + frac_d * (dl[1] - dl[0])) / PHYSICS_PERIOD_S)
        all_four = coupled and rd.valve_coupling == "all"  # the slowness also sets dead band and (inversely) speed
        frac_b, frac_v = fraction(kh[2], g, all_four), fraction(kh[3], 1.0 - g, all_four)
        lat = [rd.encoder_latency_s, rd.imu_latency_s]
        sensor_lag = jnp.stack([jax.random.uniform(k, (), minval=lo, maxval=hi) for k, (lo, hi) in zip(kh[4:6], lat)])
        sensor_lag = jnp.clip(jnp.round(sensor_lag / PHYSICS_PERIOD_S), 0, MAX_SENSOR_LAG_STEPS).astype(jnp.int32)
        gm = rd.gripper_mass_scale
        kg = jax.random.split(jax.random.fold_in(key, 2))
        grasp = jnp.stack([jax.random.uniform(kg[0], (), minval=rd.grasp_forward_m[0], maxval=rd.grasp_forward_m[1]), 0.0,
                           jax.random.uniform(kg[1], (), minval=rd.grasp_up_m[0], maxval=rd.grasp_up_m[1])])
        gripper_scale = jax.random.uniform(kh[6], (), minval=gm[0], maxval=gm[1])
        dead_band, vscale = db[0] + frac_b * (db[1] - db[0]), vs[0] + frac_v * (vs[1] - vs[0])
        if rd.nominal_fraction > 0.0:  # a config constant: with the option off nothing is drawn, key for key
            nom = nominal_machine()
            on = jax.random.uniform(jax.random.fold_in(key, 4)) < rd.nominal_fraction

            def pick(nominal, drawn):
                return jnp.where(on, jnp.asarray(nominal, jnp.asarray(drawn).dtype), drawn)

            fric, gripper_scale, gain = pick(nom["friction_scale"], fric), pick(nom["gripper_mass_scale"], gripper_scale), pick(nom["gain"], gain)
            tau, dead_band, vscale = pick(nom["lag_s"], tau), pick(nom["dead_band"], dead_band), pick(nom["velocity_scale"], vscale)
            valve_delay = pick(round(nom["valve_delay_s"] / PHYSICS_PERIOD_S), valve_delay)
            nominal_lag = [round(nom[k] / PHYSICS_PERIOD_S) for k in ("encoder_latency_s", "imu_latency_s")]
            sensor_lag = pick(jnp.asarray(nominal_lag, jnp.int32), sensor_lag)
            grasp, shift_s = pick(nom["grasp_m"], grasp), pick(nom["release_delay_shift_s"], shift_s)
        delay_s = delay_s + shift_s
        zeros6 = jnp.zeros(6)
        data = self.data0.replace(qpos=q, qvel=zeros6, ctrl=jnp.zeros(4), qfrc_applied=zeros6, time=jnp.zeros(()))
        pts = forward_kinematics(jnp, q, zeros6)
        err = target - pts.gripper_centre
        e2 = jnp.sqrt(err[0] ** 2 + err[1] ** 2)
        state = EnvState(
            data=data,
            q_hist=jnp.tile(q, (self.cfg.history_steps, 1)),
            qd_hist=jnp.zeros((self.cfg.history_steps, 6)),
            prev_action=jnp.zeros(self.num_act),
            target=target,
            step=jnp.zeros((), jnp.int32),
            release_cmd=jnp.zeros((), bool),
            countdown=jnp.full((), -1, jnp.int32),
            opened=jnp.zeros((), bool),
            ball_p0=jnp.zeros(3),
            ball_v0=jnp.zeros(3),
            t_open=jnp.zeros(()),
            t_flight=jnp.ones(()),
            err2_min=e2,
            err3_min=jnp.sqrt(e2**2 + err[2] ** 2),
            lag_v=jnp.zeros(4),
            sensor_lag=sensor_lag,
            phys_q=jnp.tile(q, (MAX_SENSOR_LAG_STEPS + 1, 1)),
            phys_qd=jnp.zeros((MAX_SENSOR_LAG_STEPS + 1, 6)),
            gripper_scale=gripper_scale,
            x_ref=jnp.clip(q[:NUM_ACTIVE], self.lower, self.upper),
            tau=tau,
            gain=gain,
            delay_steps=jnp.maximum(1, jnp.round(delay_s / PHYSICS_PERIOD_S)).astype(jnp.int32),
            fric=fric,
            grasp=grasp,
            key=kh[0],
            integral=jnp.zeros(4),
            prev_err=jnp.zeros(4),
            peaks=jnp.zeros((2, 4)),
            valve_buf=jnp.zeros((MAX_VALVE_DELAY_STEPS + 1, 4)),
            valve_delay=jnp.clip(valve_delay, 0, MAX_VALVE_DELAY_STEPS).astype(jnp.int32),
            dead_band=dead_band,
            vscale=vscale,
            held_impact=_landing_xy(*self._held_payload(q, zeros6, grasp)) if self.w.release_slope else jnp.zeros(2),
            release_slope=jnp.zeros(()),
            wind=self._sample_wind(jax.random.fold_in(key, 3)),
        )
        return state, self.observe(state)

    def _sample_wind(self, key) -> jnp.ndarray:
        """The episode's wind (2,) m/s: direction uniform, speed uniform in [0, ``wind_mps``], in
        the share ``wind_fraction`` of the episodes (still air in the others); zeros (and no draw)
        when the recipe has none."""
        w = self.rand.wind_mps
        if w <= 0.0:  # a config constant: without wind the other draws are unchanged, key for key
            return jnp.zeros(2)
        k1, k2 = jax.random.split(key)
        speed = jax.random.uniform(k1, (), minval=0.0, maxval=w)
        if self.rand.wind_fraction < 1.0:  # a config constant: every episode windy draws nothing more
            speed = jnp.where(jax.random.uniform(jax.random.fold_in(key, 1)) < self.rand.wind_fraction, speed, 0.0)
        az = jax.random.uniform(k2, (), minval=-jnp.pi, maxval=jnp.pi)
        return speed * jnp.stack([jnp.cos(az), jnp.sin(az)])

    def observe(self, s: EnvState) -> jnp.ndarray:
        return build_observation(jnp, self.mode, s.q_hist, s.qd_hist, s.prev_action, s.target, s.opened)

    def privileged(self, s: EnvState) -> jnp.ndarray:
        """The critic's privileged observation (PRIVILEGED_SIZE,), layout in sim_twin.training.privileged,
        normalised over ``cfg.privileged_ranges`` where given, else the randomisation ranges."""
        return privileged_observation(self.priv_ranges, self.hydraulic, s)

    def privileged_batch(self, s: EnvState) -> jnp.ndarray:
        """privileged() of a batch of states: (num_envs, PRIVILEGED_SIZE)."""
        return jax.vmap(self.privileged)(s)

    # --- step -------------------------------------------------------------------------------
    def _actuate(self, s: EnvState, target_v) -> tuple[EnvState, jnp.ndarray]:
        """Training joint-velocity controller: new state and the servo setpoints (4,)."""
        dt = PHYSICS_PERIOD_S
        if not self.hydraulic:
            lag_v = jnp.clip(lag_step(s.lag_v, target_v, s.tau, dt), -self.vmax, self.vmax)
            return s.replace(lag_v=lag_v), lag_v
        data = s.data
        u, _, integral, err, peaks = pid_ff_law(
            jnp, self.gains, self.vmax, dt, target_v, data.qpos[:4], data.qvel[:4], s.integral, s.prev_err, s.peaks
        )
        buf = jnp.concatenate([dead_band_flow(jnp, u, s.dead_band)[None], s.valve_buf[:-1]])
        delayed = buf[s.valve_delay, jnp.arange(4)]
        lag_v = lag_step(s.lag_v, delayed, s.tau, dt)
        vmax = self.vmax * s.vscale
        setpoint = jnp.clip(lag_v * vmax, -vmax, vmax)
        return s.replace(lag_v=lag_v, integral=integral, prev_err=err, peaks=peaks, valve_buf=buf), setpoint

    def _substep(self, s: EnvState, target_v) -> EnvState:
        dt = PHYSICS_PERIOD_S
        s, flow = self._actuate(s, target_v)
        data = s.data
        x_ref, setpoint = cylinder_step(jnp, s.x_ref, flow, data.qpos[:NUM_ACTIVE], self.lower, self.upper, dt)
        s = s.replace(x_ref=x_ref)
        fric = passive_friction_force(jnp, data.qvel[4:6], self.inertia * s.fric)
        data = data.replace(ctrl=setpoint, qfrc_applied=jnp.zeros(6).at[4:6].set(fric))
        g, scale = self.gripper_id, s.gripper_scale
        model = self.model.replace(
            body_mass=self.model.body_mass.at[g].multiply(scale), body_inertia=self.model.body_inertia.at[g].multiply(scale)
        )
        data = mjx.step(model, data)
        countdown = s.countdown
        open_now = (countdown == 1) & ~s.opened
        countdown = jnp.where(countdown > 0, countdown - 1, countdown)
        p_held, v_held = self._held_payload(data.qpos, data.qvel, s.grasp)
        p0 = jnp.where(open_now, p_held, s.ball_p0)
        v0 = jnp.where(open_now, v_held, s.ball_v0)
        t_held = ballistic_impact_time(jnp, p_held, v_held, PAYLOAD_RADIUS_M)
        t_flight = jnp.where(open_now, t_held, s.t_flight)
        t_open = jnp.where(s.opened, s.t_open + dt, s.t_open)
        if self.w.release_slope:  # the recipe's constant: a run without the term computes none of it
            held_impact = _landing_xy(p_held, v_held, t_held)
            slope = jnp.sqrt(jnp.sum((held_impact - s.held_impact) ** 2)) / dt
            s = s.replace(held_impact=held_impact, release_slope=jnp.where(open_now, slope, s.release_slope))
        return s.replace(
            data=data, countdown=countdown, opened=s.opened | open_now,
            ball_p0=p0, ball_v0=v0, t_flight=t_flight, t_open=t_open,
            phys_q=jnp.concatenate([data.qpos[None], s.phys_q[:-1]]),
            phys_qd=jnp.concatenate([data.qvel[None], s.phys_qd[:-1]]),
        )

    def _held_payload(self, q, qd, grasp) -> tuple[jnp.ndarray, jnp.ndarray]:
        """Position (3,) and velocity (3,) of the held payload, machine frame, m and m/s: the
        gripper centre, or the point ``grasp`` (3,) m from it in the gripper frame when the config
        randomises the grasp offset (velocity by forward-mode differentiation along ``qd``)."""
        if not self.grasp_on:
            pts = forward_kinematics(jnp, q, qd)
            return pts.gripper_centre, pts.gripper_centre_vel
        local = jnp.asarray(GRIPPER_CENTRE_LOCAL_M, dtype=q.dtype) + grasp.astype(q.dtype)
        return jax.jvp(lambda qq: gripper_frame_point(jnp, qq, local), (q,), (qd,))

    def _measure(self, s: EnvState, key) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(q (6,), qd (6,)) as the sensors give them: latency per joint group, white noise."""
        lag = jnp.concatenate([jnp.full(4, s.sensor_lag[0]), jnp.full(2, s.sensor_lag[1])])
        cols = jnp.arange(6)
        q, qd = s.phys_q[lag, cols], s.phys_qd[lag, cols]
        n = self.rand.obs_noise
        q_std = jnp.asarray([n.q_active] * 4 + [n.q_passive] * 2)
        qd_std = jnp.asarray([n.qd_active] * 4 + [n.qd_passive] * 2)
        k1, k2 = jax.random.split(key)
        return q + q_std * jax.random.normal(k1, (6,)), qd + qd_std * jax.random.normal(k2, (6,))

    def step(self, s: EnvState, action):
        """One control step. Returns (state, obs, reward, terminated, time_out, info); ``info``
        holds ``landed``, ``failed``, ``impact_err_m``, ``released`` and ``reward_terms`` (the
        scaled terms of sim_twin.training.rewards, whose sum is ``reward``)."""
        w = self.w
        key, k_force, k_noise, k_obs = jax.random.split(s.key, 4)
        qd_ref, release = decode_action(jnp, self.mode, action)
        # forced release (paper Sec. III-D): near the target at low speed, 5 % of the time
        pts0 = forward_kinematics(jnp, s.data.qpos, s.data.qvel)
        d0 = s.target - pts0.gripper_centre
        near = jnp.sqrt(d0[0] ** 2 + d0[1] ** 2) < self.forced.radius_m
        slow = jnp.linalg.norm(pts0.gripper_centre_vel) < self.forced.speed_mps
        forced = near & slow & (jax.random.uniform(k_force) < self.forced.probability)
        do_release = (release | forced) & ~s.release_cmd
        s = s.replace(
            key=key,
            countdown=jnp.where(do_release, s.delay_steps, s.countdown),
            release_cmd=s.release_cmd | do_release,
        )
        noise = jax.random.normal(k_noise, (4,)) * self.rand.velocity_noise * self.vmax
        target_v = (qd_ref if self.hydraulic else qd_ref * s.gain) + noise
        s = jax.lax.fori_loop(0, SUBSTEPS, lambda _, st: self._substep(st, target_v), s, unroll=self.unroll_substeps)

        data = s.data
        pts = forward_kinematics(jnp, data.qpos, data.qvel)
        t_ball = jnp.minimum(s.t_open, s.t_flight)
        ball_free = ballistic_position(jnp, s.ball_p0, s.ball_v0, t_ball)
        # the wind's landing shift (a config constant: without wind nothing is computed), grown
        # along the flight as (t / T)^2, the displacement of a steady perturbing acceleration
        air = wind_landing_shift(jnp, s.ball_p0, s.ball_v0, s.t_flight, s.wind) if self.rand.wind_mps > 0.0 else None
        if air is not None:
            ball_free = ball_free.at[:2].add(air * (t_ball / s.t_flight) ** 2)
        ball = jnp.where(s.opened, ball_free, pts.gripper_centre)
        landed = s.opened & (s.t_open >= s.t_flight)
        err = s.target - ball
        err2 = jnp.sqrt(err[0] ** 2 + err[1] ** 2)
        err3 = jnp.sqrt(err2**2 + err[2] ** 2)
        ground, cabin, limit = clearance_violations(jnp, data.qpos, pts)
        failed = ground | cabin | limit | ~jnp.all(jnp.isfinite(data.qpos))
        impact = ballistic_position(jnp, s.ball_p0, s.ball_v0, s.t_flight)
        if air is not None:
            impact = impact.at[:2].add(air)
        impact_err = jnp.sqrt(jnp.sum((impact[:2] - s.target[:2]) ** 2))
        step = s.step + 1
        at_limit = (step >= self.cfg.max_steps) & ~failed & ~landed
        unreleased = at_limit & ~s.release_cmd
        terms = reward_terms(
            RewardInputs(err2, err3, s.err2_min, s.err3_min, action, s.prev_action, s.opened, failed, landed,
                         impact_err, unreleased, s.release_slope, s.release_cmd,
                         step * (PHYSICS_PERIOD_S * SUBSTEPS)),
            w,
        )
        reward = total_reward(terms, w.failure)
        # an episode that never released ends as a failure when the recipe punishes it (no bootstrap)
        terminated = failed | landed | (unreleased if w.no_release else jnp.zeros_like(unreleased))
        time_out = at_limit & ~terminated
        q_meas, qd_meas = self._measure(s, k_obs)
        q_hist = jnp.concatenate([q_meas[None], s.q_hist[:-1]])
        qd_hist = jnp.concatenate([qd_meas[None], s.qd_hist[:-1]])
        s = s.replace(
            step=step, err2_min=jnp.minimum(s.err2_min, err2), err3_min=jnp.minimum(s.err3_min, err3),
            q_hist=q_hist, qd_hist=qd_hist, prev_action=action,
        )
        info = {
            "landed": landed & ~failed,
            "failed": failed,
            "impact_err_m": impact_err,
            "released": s.release_cmd,
            "reward_terms": terms,
        }
        return s, self.observe(s), reward, terminated, time_out, info

    def step_autoreset_batch(self, s: EnvState, action):
        """:meth:`step` over a batch, then finished episodes replaced by fresh ones (observation
        of the new episode): (N, ...) states and (N, num_act) actions. Each environment's key
        splits into its next key and its reset key.

        The step and the reset are two vmaps joined by a selection over the batch (not a reset
        nested in a vmapped per-environment step): MJX's MuJoCo Warp implementation
        (``impl="warp"``) cannot trace a reset nested in the step's vmap (JAX reports a leaked
        tracer), and batch-level selection works for both implementations. State leaves that are
        not batched (Warp's empty contact buffers) are kept as they are.
        """
        s1, obs, rew, term, tout, info = jax.vmap(self.step)(s, action)
        done = term | tout
        keys = jax.vmap(jax.random.split)(s1.key)
        s1 = s1.replace(key=keys[:, 0])
        n = done.shape[0]

        def batched(leaf) -> bool:
            return leaf.ndim > 0 and leaf.shape[:1] == done.shape

        def full_reset():
            s_new, obs_new = jax.vmap(self.reset)(keys[:, 1])

            def pick(new, old):
                if new.shape != old.shape or not batched(new):
                    return old
                return jnp.where(done.reshape(done.shape + (1,) * (new.ndim - 1)), new, old)

            return jax.tree_util.tree_map(pick, s_new, s1), pick(obs_new, obs)

        slots = 0 if self.reset_slots is None else max(1, int(n * self.reset_slots))
        if not slots:
            s_out, obs_out = full_reset()
            return s_out, obs_out, rew, done, tout, info

        def partial_reset():
            # the finished environments' indices, padded with n (out of range: dropped by the scatter)
            idx = jnp.nonzero(done, size=slots, fill_value=n)[0]
            s_new, obs_new = jax.vmap(self.reset)(keys[jnp.minimum(idx, n - 1), 1])

            def put(new, old):
                if not batched(old) or new.shape[1:] != old.shape[1:]:
                    return old
                return old.at[idx].set(new, mode="drop")

            return jax.tree_util.tree_map(put, s_new, s1), put(obs_new, obs)

        s_out, obs_out = jax.lax.cond(jnp.sum(done) <= slots, partial_reset, full_reset)
        return s_out, obs_out, rew, done, tout, info
