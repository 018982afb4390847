"""Does a 2D policy land where training thinks it lands? The same throws in the MJX training
environment and in the twin the site matrix throws in, compared throw by throw.

    python -m tests.benchmarks.training_twin_bias [--policy policies/throw2d.onnx] [--config CONFIG.json] \
        [--targets 7.5 9 10] [--throws 30] [--env-delay env twin twin-ceil] [--noiseless] \
        [--training-dist] [--env-set FIELD=VALUE[,FIELD=VALUE]] ... [--json OUT.json]

For every target distance (2D, on the arm's plane: sim_twin.evaluation.evaluate.target_on_axis)
and every start-pose seed of the site matrix's seed 0 (sim_twin.evaluation.evaluate.throw_seeds)
the policy throws twice from the SAME start pose:

* **twin**: sim_twin.evaluation.evaluate.throw_batch on the nominal profile, as the site matrix
  throws (the runtime's executor with its release check, PID + feed-forward controller, the CPU
  MuJoCo twin with its valve model, sensing and release-delay jitter); its landed rows carry the
  release as the twin flew it (``release_pos_m``, ``release_vel_mps``, ``flight_s``) and the
  measured impact (downrange error, with the nominal 2 cm impact-measurement noise);
* **env**: the MJX training environment (sim_twin.training.mjx_env.ThrowEnvCore, on the CPU), the
  config after its curriculum stage narrowed to the nominal machine in still air
  (tests.benchmarks.training_style_probe.nominal_randomization: nominal valves, friction and gripper
  mass x1, nominal sensing, release delay 258 ms with its 15 ms jitter), forced release off, reset to the twin's start pose and target; the ONNX policy
  (onnxruntime, its mean action) acts on the environment's observations. The landing is the
  environment's own: drag-free flight from the payload's state at the opening (runtime.ballistics).

The release delay of the env side (``--env-delay``, one rollout per choice):

* ``env``: the environment's own draw, rounded to whole 10 ms physics steps (as in training);
* ``twin``: each throw gets the delay the twin draws for its seed, rounded as the environment rounds;
* ``twin-ceil``: the twin's draw, the gripper opening at the first physics step at or after it
  (as the twin opens: sim_twin.twin.simulated_machine.MachineReadout._after_physics).

Printed per target and side: throws landed, mean signed downrange error (positive = long) and its
standard error; then the paired differences twin - env over the throws that landed in both, of the
landing and of the release: release-command time and opening time after the swing's start, the
opening delay, the payload's speed, elevation, height and downrange position at the opening, and
the flight time. A "flight check" flies each side's release again with runtime.ballistics.ground_impact
(float64): what remains between the sides is not the flight model's. ``--noiseless`` switches the
sensing noise, IMU latency, impact noise and release-delay jitter off on both sides (a twin profile
with SensorParams.ideal and delay std 0; env obs noise 0, IMU latency 0, delay std 0), so paired
throws are deterministic.

Two further env rollouts, for where the policy's bias comes from rather than the chain's:
``--training-dist`` throws the same starts with the config's own randomisation (the distribution the
policy was trained on: after the config's curriculum stage, :func:`trained_env`; where it draws a
wind, each landing moved by the episode's wind as the environment moves it, ``wind_downrange_m``),
``--env-set`` (repeatable) on the nominal machine with per-episode parameters of the EnvState set
after the reset (e.g. ``fric=2.0``, ``valve_delay=14`` steps, ``tau=0.2``, ``gripper_scale=1.15``,
``sensor_lag=[1,2]``). Their paired lines compare them with the
twin all the same (different machines: differences there are the machine's, not the chain's).

``--json`` writes the summaries and every throw's row. One process on the CPU: about 0.1 s per twin
throw, half a minute of JAX compilation per environment configuration, about 10 s per env rollout
of 120 throws (a 2-core host).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import re
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEFAULT_POLICY = REPO / "policies" / "throw2d.onnx"
DEFAULT_CONFIG = REPO / "sim_twin" / "configs" / "throw_2d.json"
DELAY_CHOICES = ("env", "twin", "twin-ceil")
MATRIX_TARGETS = (7.5, 8.0, 8.5, 9.0, 9.5, 10.0)
"""The 2D site matrix's targets: a target's index here gives its start-pose seeds (throw_seeds)."""


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- start poses -------------------------------------------------------------------------------
def twin_profile(noiseless: bool):
    """The nominal reality profile, or with ``noiseless`` the same without sensing noise, impact
    noise, IMU latency and release-delay jitter."""
    from sim_twin.twin.profile import RealityProfile, SensorParams

    if not noiseless:
        return RealityProfile()
    return RealityProfile(name="nominal-noiseless", release_delay_std_s=0.0, sensing=SensorParams.ideal())


def twin_start(seed: int, profile) -> tuple[np.ndarray, float]:
    """The start pose (6,) of the twin's throw with ``seed`` and the opening delay [s] the twin
    will draw at its release command: the machine made and reset as throw_batch makes it (the
    machine's generator draws the pose, then nothing until the release command's delay)."""
    from sim_twin.twin.engines import make_machine

    sim = make_machine("mujoco", profile, seed=seed)
    q = sim.reset(cabin_turn=0.0)
    delay = max(0.0, float(copy.deepcopy(sim.rng).normal(profile.release_delay_mean_s, profile.release_delay_std_s)))
    return np.asarray(q, float), delay


# --- release features, common to both sides ------------------------------------------------------
def release_row(target_xyz, p0, v0, flight_s: float) -> dict:
    """Speed [m/s], elevation [deg], height [m], downrange position [m] (along the target's
    direction) of the payload at the opening, the flight time [s], and where that release lands
    in float64 drag-free flight (runtime.ballistics.ground_impact): its downrange error [m]."""
    from runtime.ballistics import ground_impact
    from runtime.throw_geometry import impact_errors
    from tests.benchmarks.release_flight import release_state

    p0, v0 = np.asarray(p0, float), np.asarray(v0, float)
    u = np.asarray(target_xyz[:2], float) / np.hypot(*target_xyz[:2])
    hit, _ = ground_impact(p0, v0)
    return {**release_state(p0, v0), "release_downrange_m": float(p0[:2] @ u), "flight_s": float(flight_s),
            "ballistic_downrange_m": impact_errors(target_xyz, hit)[0]}


def mean_wind_shift(target_xyz, p0, v0, flight_s: float, wind_mps: float, wind_fraction: float = 1.0,
                    speeds: int = 20, directions: int = 72) -> float:
    """The mean downrange shift [m] (+ long) of a release's landing over the training environment's
    winds (sim_twin.training.mjx_env.ThrowEnvCore._sample_wind: direction uniform, speed uniform in
    [0, ``wind_mps``] m/s, in the share ``wind_fraction`` of the episodes, still air in the others):
    sim_twin.twin.effects.site.wind_landing_shift averaged by the midpoint rule over ``speeds`` x
    ``directions`` winds, times ``wind_fraction``. The release: ``p0`` (3,) m, ``v0`` (3,) m/s machine
    frame, ``flight_s`` its drag-free flight time; ``target_xyz`` (3,) sets the downrange direction.
    Quadratic drag makes it negative: on average a wind takes from a throw."""
    from sim_twin.twin.effects.site import wind_landing_shift

    u = np.asarray(target_xyz[:2], float) / np.hypot(*target_xyz[:2])
    speed = (np.arange(speeds) + 0.5) / speeds * wind_mps
    az = (np.arange(directions) + 0.5) / directions * 2.0 * np.pi - np.pi
    shifts = [wind_landing_shift(np, np.asarray(p0, float), np.asarray(v0, float), flight_s, w * np.array([np.cos(a), np.sin(a)]))
              for w in speed for a in az]
    return wind_fraction * float(np.mean(np.asarray(shifts) @ u))


# --- twin side -----------------------------------------------------------------------------------
def twin_throws(policy: Path, distance_m: float, seeds: list[int], profile_path: str | None) -> list[dict]:
    """The twin's throws (sim_twin.evaluation.evaluate.throw_batch, as the site matrix) as rows:
    seed, landed, downrange_m (measured impact), release_cmd_s / opening_s (after the swing's
    start), held_releases and :func:`release_row`'s features."""
    from sim_twin.evaluation.evaluate import target_on_axis, throw_batch

    target = target_on_axis("2d", distance_m)
    rows = []
    for r in throw_batch(policy, "2d", distance_m, seeds, profile_path):
        row = {"seed": r["seed"], "landed": r["status"] == "landed" and "release_pos_m" in r,
               "status": r["status"], "held_releases": r.get("held_releases", 0)}
        if row["landed"]:
            row.update(downrange_m=float(r["downrange_error_m"]), release_cmd_s=float(r["release_after_s"]),
                       opening_s=float(r["duration_s"] - r["flight_s"]),
                       **release_row(target, r["release_pos_m"], r["release_vel_mps"], r["flight_s"]))
        rows.append(row)
    return rows


# --- training-environment side -------------------------------------------------------------------
def trained_env(config: dict) -> dict:
    """The config's ``env`` mapping as its policies finished training in it: with the curriculum
    stage applied (``training.curriculum_stage`` or its older spelling; sim_twin.training.config.
    CurriculumStage.env_dicts, the mapping the training switches to), else as configured. A policy
    judged here is one trained past the stage (the recipes' stages are at iteration 300).

    Raises:
        ValueError: the config's training section or its merged stage is refused (the training's
            own checks)."""
    from sim_twin.training.config import TrainingSection

    return TrainingSection.from_dict(config.get("training", {})).env_dicts(config["env"])[1]


def nominal_env_config(config_path: Path, noiseless: bool, nominal: bool = True) -> dict:
    """The ``env`` mapping of a training config (:func:`trained_env`: after its curriculum stage)
    narrowed to the nominal machine (training_style_probe.nominal_randomization, in still air),
    forced release off; ``noiseless`` also drops the observation noise, the IMU latency and the
    release-delay jitter. With ``nominal`` False the config's own randomisation after the stage stays
    (the training distribution the policy finished in, its wind included), forced release still off."""
    from tests.benchmarks.training_style_probe import nominal_randomization, without_forced_release

    env = without_forced_release(trained_env(json.loads(Path(config_path).read_text())))
    if not nominal:
        return env
    rand = nominal_randomization(env["randomization"])
    if rand.get("wind_mps"):
        rand["wind_mps"] = 0.0  # the nominal machine throws in still air (the twin's nominal profile)
    if noiseless:
        rand.update(release_delay_std_s=0.0, imu_latency_s=[0.0, 0.0],
                    obs_noise={"q_active": 0.0, "qd_active": 0.0, "q_passive": 0.0, "qd_passive": 0.0})
    env["randomization"] = rand
    return env


def fixed_start_env(env_cfg: dict):
    """A ThrowEnvCore whose ``reset_at(key, q, target)`` starts an episode from the pose ``q`` (6,)
    with the target ``target`` (3,) instead of its own draws; everything else is ``reset``'s."""
    from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore

    class FixedStartEnv(ThrowEnvCore):
        _start = None

        def reset_at(self, key, q, target):
            self._start = (q, target)  # read by the two draws below while reset is traced
            try:
                return self.reset(key)
            finally:
                self._start = None

        def _sample_pose(self, key):
            return self._start[0]

        def _sample_target(self, key, cabin_turn):
            return self._start[1]

    return FixedStartEnv(EnvConfig.from_dict(env_cfg))


class EnvSide:
    """The training environment with the policy, compiled once for a batch of fixed starts."""

    def __init__(self, policy: Path, env_cfg: dict):
        import jax
        import onnxruntime as ort

        self.core = fixed_start_env(env_cfg)
        self.sess = ort.InferenceSession(str(policy), providers=["CPUExecutionProvider"])
        self.reset = jax.jit(jax.vmap(self.core.reset_at))
        self.step = jax.jit(jax.vmap(self.core.step))

    def throws(self, targets: np.ndarray, poses: np.ndarray, seeds: list[int], delay_s: np.ndarray | None = None,
               rounding: str = "round", key: int = 0, overrides: dict | None = None) -> list[dict]:
        """One episode per (target (3,), pose (6,)) pair, the policy's mean action at every step.

        Args:
            targets, poses: (n, 3) and (n, 6) machine frame, m and rad.
            seeds: (n,) the twin seeds of the starts (carried into the rows).
            delay_s: (n,) opening delays [s] to impose, or None for the environment's own draw.
            rounding: how an imposed delay becomes physics steps: "round" (the environment's
                rule, mjx_env.ThrowEnvCore.reset) or "ceil" (the first step at or after it, the twin's).
            key: PRNG key of the episodes' noise (and of the environment's own delays).
            overrides: EnvState fields set after the reset, {field: value} (a per-episode
                parameter such as ``fric``, ``gripper_scale``, ``tau``, ``valve_delay``, broadcast
                to the field's shape and dtype).

        Returns:
            Rows as :func:`twin_throws`' (downrange_m: the environment's own landing, its wind's
            shift included where the config draws one; then ``wind_downrange_m`` is that shift's
            downrange part [m], + long: sim_twin.twin.effects.site.wind_landing_shift, and
            ``wind_mean_downrange_m`` its mean over the config's winds for the same release,
            :func:`mean_wind_shift`).
        """
        import jax
        import jax.numpy as jnp

        from runtime.ballistics import ballistic_position
        from runtime.observation import CONTROL_PERIOD_S, PHYSICS_PERIOD_S
        from runtime.throw_geometry import impact_errors
        from sim_twin.twin.effects.site import wind_landing_shift
        from tests.benchmarks.training_style_probe import rollout

        n = len(poses)
        s, obs = self.reset(jax.random.split(jax.random.PRNGKey(key), n), jnp.asarray(poses, jnp.float32),
                            jnp.asarray(targets, jnp.float32))
        if delay_s is not None:
            steps = np.asarray(delay_s) / PHYSICS_PERIOD_S
            steps = np.ceil(steps - 1e-6) if rounding == "ceil" else np.round(steps)
            s = s.replace(delay_steps=jnp.asarray(np.maximum(1, steps), jnp.int32))
        for name, value in (overrides or {}).items():
            old = getattr(s, name)
            s = s.replace(**{name: jnp.broadcast_to(jnp.asarray(value, old.dtype), old.shape)})
        delay_steps = np.asarray(s.delay_steps)
        cmd_step = np.full(n, -1)
        rows: list[dict] = [{"seed": int(seeds[i]), "landed": False, "status": "no end"} for i in range(n)]
        for k, before, s, info, live in rollout(self.step, self.sess, s, obs, self.core.cfg.max_steps, key):
            cmd_step[live & np.asarray(s.release_cmd) & ~np.asarray(before.release_cmd)] = k
            landed, failed = np.asarray(info["landed"]) & live, np.asarray(info["failed"]) & live
            for i in np.flatnonzero(failed):
                rows[i]["status"] = "failed"
            for i in np.flatnonzero(landed):
                p0, v0, t_f = (np.asarray(a[i], float) for a in (s.ball_p0, s.ball_v0, s.t_flight))
                t_cmd = cmd_step[i] * CONTROL_PERIOD_S
                hit = ballistic_position(np, p0, v0, float(t_f))
                calm = impact_errors(targets[i], hit)[0]
                wind = {}
                if self.core.rand.wind_mps > 0.0:  # the environment's landing: the drag-free one moved by the wind
                    hit = hit + np.concatenate([wind_landing_shift(np, p0, v0, float(t_f), np.asarray(s.wind[i], float)), [0.0]])
                    wind = {"wind_downrange_m": impact_errors(targets[i], hit)[0] - calm,
                            "wind_mean_downrange_m": mean_wind_shift(targets[i], p0, v0, float(t_f), self.core.rand.wind_mps,
                                                                     self.core.rand.wind_fraction)}
                rows[i].update(landed=True, status="landed", held_releases=0,
                               downrange_m=impact_errors(targets[i], hit)[0], **wind,
                               release_cmd_s=t_cmd, opening_s=t_cmd + int(delay_steps[i]) * PHYSICS_PERIOD_S,
                               **release_row(targets[i], p0, v0, float(t_f)))
        return rows


# --- statistics ----------------------------------------------------------------------------------
def mean_se(x) -> tuple[float, float, int]:
    """Mean, its standard error and the count of the finite values of ``x`` (nan, nan, 0 if none)."""
    x = np.asarray([v for v in x if v is not None and math.isfinite(v)], float)
    if not x.size:
        return math.nan, math.nan, 0
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else math.nan, int(x.size)


PAIRED = (("downrange_m", "landing downrange error [m]", 1.0),
          ("ballistic_downrange_m", "  same, release re-flown in float64 [m]", 1.0),
          ("release_cmd_s", "release command after swing start [ms]", 1e3),
          ("opening_s", "gripper opening after swing start [ms]", 1e3),
          ("delay_s", "opening delay (opening - command) [ms]", 1e3),
          ("speed_mps", "release speed [m/s]", 1.0),
          ("elevation_deg", "release elevation [deg]", 1.0),
          ("height_m", "release height [m]", 1.0),
          ("release_downrange_m", "release downrange position [m]", 1.0),
          ("flight_s", "flight time [ms]", 1e3))


def paired(twin: list[dict], env: list[dict]) -> dict:
    """Paired differences twin - env (per quantity: mean, standard error, pairs) over the seeds
    that landed on both sides, and the share of them whose release command came at the same step."""
    def value(r: dict, key: str) -> float:
        return r["opening_s"] - r["release_cmd_s"] if key == "delay_s" else r[key]

    e_by = {r["seed"]: r for r in env if r["landed"]}
    pairs = [(t, e_by[t["seed"]]) for t in twin if t["landed"] and t["seed"] in e_by]
    out = {key: mean_se([value(t, key) - value(e, key) for t, e in pairs]) for key, _, _ in PAIRED}
    out["same_release_step"] = (sum(abs(t["release_cmd_s"] - e["release_cmd_s"]) < 1e-6 for t, e in pairs) / len(pairs)
                                if pairs else math.nan)
    out["pairs"] = len(pairs)
    return out


def side_summary(rows: list[dict]) -> dict:
    """Throws, landed, mean downrange error with its standard error, held releases."""
    m, se, n = mean_se([r["downrange_m"] for r in rows if r["landed"]])
    return {"throws": len(rows), "landed": n, "bias_m": m, "se_m": se,
            "held": sum(1 for r in rows if r.get("held_releases"))}


def print_target(distance_m: float, twin: list[dict], envs: dict[str, list[dict]]) -> dict:
    """Print one target's table; return its summary."""
    out = {"target_m": distance_m, "twin": side_summary(twin)}
    t = out["twin"]
    print(f"\n=== target {distance_m:g} m ===")
    print(f"{'side':<18}{'throws':>7}{'landed':>7}{'bias [m]':>11}{'SE [m]':>9}")
    print(f"{'twin (nominal)':<18}{t['throws']:>7}{t['landed']:>7}{t['bias_m']:>+11.4f}{t['se_m']:>9.4f}"
          + (f"   ({t['held']} throws with a held release)" if t["held"] else ""))
    for name, rows in envs.items():
        e = side_summary(rows)
        print(f"{'env ' + name:<18}{e['throws']:>7}{e['landed']:>7}{e['bias_m']:>+11.4f}{e['se_m']:>9.4f}")
        out[f"env_{name}"] = e
    for name, rows in envs.items():
        p = paired(twin, rows)
        out[f"paired_{name}"] = p
        print(f"-- paired twin - env[{name}]: {p['pairs']} pairs, release command at the same control step in "
              f"{100 * p['same_release_step']:.0f} %")
        for key, label, scale in PAIRED:
            m, se, _ = p[key]
            print(f"   {label:<44}{scale * m:>+10.4f} ± {scale * se:.4f}")
    return out


def parse_env_set(spec: str) -> dict:
    """``"fric=2.0,sensor_lag=[1,2]"`` -> {"fric": 2.0, "sensor_lag": [1, 2]} (values JSON).

    Raises:
        ValueError: no FIELD=VALUE in ``spec``, or a value that is not JSON.
    """
    items = re.findall(r"(\w+)=(\[[^\]]*\]|[^,]+)", spec)
    if not items:
        raise ValueError(f"--env-set {spec!r}: expected FIELD=VALUE[,FIELD=VALUE]")
    return {k: json.loads(v) for k, v in items}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="See the module docstring (python -m pydoc tests.benchmarks.training_twin_bias).")
    ap.add_argument("--policy", type=Path, default=DEFAULT_POLICY, help="2D ONNX policy (default %(default)s)")
    ap.add_argument("--targets", type=float, nargs="+", default=[7.5, 9.0, 10.0],
                    help="target distances [m] (default %(default)s); a site-matrix target gets that cell's start poses")
    ap.add_argument("--throws", type=int, default=30, help="throws per target and side (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="site-matrix seed of the start poses (default %(default)s)")
    ap.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                    help="training config whose env mapping is narrowed to the nominal machine (default %(default)s)")
    ap.add_argument("--env-delay", nargs="+", choices=DELAY_CHOICES, default=list(DELAY_CHOICES),
                    help="the env side's opening delay, one rollout each (default: all; see the docstring)")
    ap.add_argument("--noiseless", action="store_true",
                    help="no sensing/impact noise, IMU latency or delay jitter on either side (deterministic pairs)")
    ap.add_argument("--training-dist", action="store_true",
                    help="also throw in the env with the config's own randomisation (the training distribution; "
                         "its own delays), to see the policy's bias where it was trained")
    ap.add_argument("--env-set", action="append", default=[], metavar="FIELD=VALUE[,FIELD=VALUE]",
                    help="an extra env rollout on the nominal machine (its own delays) with EnvState fields set after "
                         "the reset, e.g. fric=2.0 or tau=0.2,valve_delay=14 (repeatable; no recompilation)")
    ap.add_argument("--json", type=Path, help="write the summaries and every throw's row here")
    args = ap.parse_args(argv)

    from sim_twin.evaluation.evaluate import target_on_axis, throw_seeds

    env_sets = {spec: parse_env_set(spec) for spec in args.env_set}
    t0 = time.time()
    profile = twin_profile(args.noiseless)
    seeds_of = {d: throw_seeds(args.seed, MATRIX_TARGETS.index(d) if d in MATRIX_TARGETS else 10 + k, args.throws)
                for k, d in enumerate(args.targets)}
    starts = {d: [twin_start(s, profile) for s in seeds_of[d]] for d in args.targets}
    log(f"policy {args.policy}, targets {args.targets} m, {args.throws} throws each, profile {profile.name}")

    twin: dict[float, list[dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        prof_path = None
        if args.noiseless:
            prof_path = str(Path(tmp) / "profile.json")
            Path(prof_path).write_text(json.dumps(profile.to_dict()))
        for d in args.targets:
            twin[d] = twin_throws(args.policy, d, seeds_of[d], prof_path)
            log(f"twin {d:g} m: {sum(r['landed'] for r in twin[d])}/{len(twin[d])} landed ({time.time() - t0:.0f} s)")

    log("compiling the training environment (JAX, CPU) ...")
    side = EnvSide(args.policy, nominal_env_config(args.config, args.noiseless))
    seeds = [s for d in args.targets for s in seeds_of[d]]
    targets = np.array([target_on_axis("2d", d) for d in args.targets for _ in seeds_of[d]])
    poses = np.array([q for d in args.targets for q, _ in starts[d]])
    delays = np.array([dl for d in args.targets for _, dl in starts[d]])
    env: dict[str, dict[float, list[dict]]] = {}
    for name in args.env_delay:
        rows = side.throws(targets, poses, seeds, None if name == "env" else delays, "ceil" if name == "twin-ceil" else "round")
        env[name] = {d: rows[i * args.throws:(i + 1) * args.throws] for i, d in enumerate(args.targets)}
        log(f"env [{name}]: {sum(r['landed'] for r in rows)}/{len(rows)} landed ({time.time() - t0:.0f} s)")
    for spec, overrides in env_sets.items():
        rows = side.throws(targets, poses, seeds, overrides=overrides)
        env[spec] = {d: rows[i * args.throws:(i + 1) * args.throws] for i, d in enumerate(args.targets)}
        log(f"env [{spec}]: {sum(r['landed'] for r in rows)}/{len(rows)} landed ({time.time() - t0:.0f} s)")
    if args.training_dist:
        log("compiling the training environment with the training randomisation ...")
        rows = EnvSide(args.policy, nominal_env_config(args.config, False, nominal=False)).throws(targets, poses, seeds)
        env["training-dist"] = {d: rows[i * args.throws:(i + 1) * args.throws] for i, d in enumerate(args.targets)}
        log(f"env [training-dist]: {sum(r['landed'] for r in rows)}/{len(rows)} landed ({time.time() - t0:.0f} s)")

    print(f"\npolicy {args.policy}; twin profile {profile.name}; env config {args.config} narrowed to the nominal "
          f"machine; positive = long; SE = standard error of the mean")
    summary = [print_target(d, twin[d], {n: env[n][d] for n in env}) for d in args.targets]
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                         "twin": {str(d): twin[d] for d in twin},
                                         "env": {n: {str(d): env[n][d] for d in env[n]} for n in env}}, indent=1, default=float))
        log(f"wrote {args.json}")
    log(f"done in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
