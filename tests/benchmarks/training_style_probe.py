"""Read a 2D run's far-target throw style from its checkpoint, without the site-matrix gate.

``python -m tests.benchmarks.training_style_probe RUN ... --out reports/<name>`` loads each run's
``checkpoint.pt`` and ``config.json`` (a directory or ``REV:PATH``, as
tests/benchmarks/training_throw_style.py reads them), exports its actor to ONNX
(sim_twin.training.export) and throws it at one target distance in the MJX training environment
(sim_twin.training.mjx_env, on the CPU here), twice:

* **nominal**: the randomisation narrowed to the nominal simulated machine (``nominal_randomization``:
  the valve model's nominal dead band, delay and lag, full-open speed ×1, friction and gripper mass
  ×1, no encoder latency, the nominal gripper-IMU latency and sensing noise), the machine the site
  matrix's ``nominal`` profile throws on;
* **training**: the run's own randomisation.

Per run and case it records the mean landing time (start to landing, what the site matrix calls
``mean_duration_s``), the mean time of the release command, the signed downrange landing error's
mean (bias) and standard deviation (σ). The nominal landing time gives the style as
tests/benchmarks/training_throw_style.py reads it from a gate matrix (long ≥ ``LONG_STYLE_S``), so a
run trained with ``--no-gate`` (a short run that only asks which style a recipe takes) gets a style
too, and a kept run's reading can be compared with its gate's. Writes ``<name>.json``, ``<name>.md``
and ``<name>.png`` (the nominal landing time of every run, grouped by recipe).

Forced release is off in the probe (the matrix has none); every throw starts from the environment's
own random start pose (``--envs`` of them, the same keys for every run).
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from tests.benchmarks.training_throw_style import FAR_TARGET_M, LONG_STYLE_S, RunSource, kept_rows, run_style, style_of

PROBE_KEY = 7
"""PRNG key of the probe's episodes (start poses, release delays, noise): the same for every run."""


def nominal_randomization(rand: dict) -> dict:
    """``rand`` (a config's ``env.randomization``) narrowed to the nominal simulated machine.

    The machine's nominal values are sim_twin.training.mjx_env.nominal_machine's (the twin's
    nominal valve, ×1 speed, friction and gripper mass, 20 ms IMU latency), the sensing noise
    sim_twin.twin.profile.SensorParams' defaults (encoder and gripper-IMU); the release delay keeps its
    per-throw jitter (``release_delay_std_s``) without the episode shift. Every joint gets the same
    valve (``valve_spread`` 0), full-open speed ×1 and no velocity-reference noise.
    """
    from sim_twin.training.mjx_env import nominal_machine
    from sim_twin.twin.profile import SensorParams

    s, nom = SensorParams(), nominal_machine()
    out = copy.deepcopy(rand)
    out.update({k: [nom[k]] * 2 for k in ("dead_band", "valve_delay_s", "lag_s", "velocity_scale", "friction_scale",
                                          "gripper_mass_scale", "encoder_latency_s", "imu_latency_s")})
    out.update(velocity_noise=0.0, release_delay_shift_s=nom["release_delay_shift_s"], valve_spread=0.0,
               obs_noise={"q_active": s.encoder_noise_rad, "qd_active": s.encoder_rate_noise_radps,
                          "q_passive": s.imu_angle_noise_rad, "qd_passive": s.imu_rate_noise_radps})
    return out


def play(onnx_path: Path, env_cfg: dict, envs: int, key: int, action_std: float = 0.0):
    """One episode in each of ``envs`` MJX training environments (sim_twin.training.mjx_env, ``env_cfg``
    as given) driven by the exported actor, reset with PRNG key ``key``.

    ``action_std`` 0 (the default) plays the actor's mean, as the site matrix, the validation and the
    machine do; above 0 it adds Gaussian noise of that std to every action entry (numpy generator
    seeded with ``key``), as PPO's sampled actor does in training (its learned std, 0.05 at the floor).

    Yields, per control step k (0-based): ``(k, before, after, info, live)``: the batch's
    EnvState before and after the step, the step's info (with ``action_mean`` (envs, actions), the
    actor's output, and ``action`` (envs, actions), what was played) and ``live`` (envs,) bool, the
    environments whose episode had not ended before this step. Stops once every episode has ended,
    or at the episode's step limit.
    """
    import jax
    import jax.numpy as jnp
    import onnxruntime as ort

    from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore

    core = ThrowEnvCore(EnvConfig.from_dict(env_cfg))
    s, obs = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(key), envs))
    yield from rollout(jax.jit(jax.vmap(core.step)), ort.InferenceSession(str(onnx_path)), s, obs, core.cfg.max_steps,
                       key, action_std)


def rollout(step, session, s, obs, max_steps: int, key: int = 0, action_std: float = 0.0):
    """The episodes of a reset batch (EnvState ``s``, observations ``obs`` (envs, observation_size))
    played by the exported actor (onnxruntime ``session``) through ``step`` (the jitted, vmapped
    ThrowEnvCore.step) until every episode has ended or ``max_steps`` control steps; ``key`` and
    ``action_std`` as :func:`play`'s, whose yields these are."""
    import jax.numpy as jnp

    name = session.get_inputs()[0].name
    done = np.zeros(len(obs), bool)
    rng = np.random.default_rng(key)
    for k in range(max_steps):
        before = s
        mean = session.run(None, {name: np.asarray(obs, np.float32)})[0]
        act = (mean + action_std * rng.standard_normal(mean.shape)).astype(np.float32) if action_std > 0 else mean
        s, obs, _, term, tout, info = step(s, jnp.asarray(act))
        yield k, before, s, {**info, "action_mean": mean, "action": act}, ~done
        done |= np.asarray(term) | np.asarray(tout)
        if done.all():
            return


def without_forced_release(env_cfg: dict) -> dict:
    """A copy of a training config's ``env`` mapping with training's forced release off (paper
    Sec. III-D), as the site matrix, the validation and the machine play: they have none."""
    cfg = copy.deepcopy(env_cfg)
    cfg["forced_release"] = {**cfg.get("forced_release", {}), "probability": 0.0}
    return cfg


def throw_at(onnx_path: Path, env_cfg: dict, target_m: float, envs: int) -> dict:
    """Throw the exported actor ``envs`` times at ``target_m`` in the MJX training environment.

    Args:
        onnx_path: the actor (sim_twin.training.export), input (1 or N, observation_size) float32.
        env_cfg: the ``env`` mapping of a training config (its randomisation is used as given).
        target_m: target distance from the machine [m] (the arm's plane, 2D).
        envs: number of throws.

    Returns:
        {"landed": fraction of throws that landed without failure, "landing_s" / "release_cmd_s":
        mean time of the landing / first release command from the episode start [s], "bias_m" /
        "sigma_m": mean and standard deviation of the signed downrange error (the landing's offset
        from the target along the target's direction, positive long, as the site matrix takes it:
        runtime.throw_geometry.impact_errors) [m]}.
    """
    import jax
    import jax.numpy as jnp

    from runtime.observation import CONTROL_PERIOD_S
    from runtime.throw_geometry import impact_errors
    from sim_twin.twin.physics import ballistic_position

    cfg = {**without_forced_release(env_cfg), "target_range_m": [target_m, target_m]}
    impact_of = jax.jit(jax.vmap(lambda p, v, t: ballistic_position(jnp, p, v, t)))
    signed, t_land, t_rel = (np.full(envs, np.nan) for _ in range(3))
    for k, before, s, info, live in play(onnx_path, cfg, envs, PROBE_KEY):
        t = (k + 1) * CONTROL_PERIOD_S
        t_rel[np.asarray(s.release_cmd) & ~np.asarray(before.release_cmd) & live] = t
        landed = np.asarray(info["landed"]) & live
        if landed.any():
            imp, tgt = np.asarray(impact_of(s.ball_p0, s.ball_v0, s.t_flight)), np.asarray(s.target)
            for i in np.flatnonzero(landed):  # the site matrix's downrange error: along the target direction
                signed[i] = impact_errors(tgt[i], imp[i])[0]
            t_land[landed] = t
    ok = ~np.isnan(signed)
    if not ok.any():
        return {"landed": 0.0, "landing_s": float("nan"), "release_cmd_s": float("nan"), "bias_m": float("nan"), "sigma_m": float("nan")}
    return {"landed": float(ok.mean()), "landing_s": float(np.nanmean(t_land)), "release_cmd_s": float(np.nanmean(t_rel)),
            "bias_m": float(np.nanmean(signed)), "sigma_m": float(np.nanstd(signed))}


def recipe_of(cfg: dict) -> str:
    """What a run's recipe changes against the committed 2D recipe (sim_twin/configs/throw_2d.json), in words."""
    from sim_twin.training.config import CONFIG_DIR
    from sim_twin.training.mjx_env import EnvConfig
    from sim_twin.training.models import FLOAT32_ACTOR

    base = json.loads((CONFIG_DIR / "throw_2d.json").read_text())
    words = []
    g, g0 = cfg["runner"]["algorithm"].get("gamma"), base["runner"]["algorithm"]["gamma"]
    if g != g0:
        words.append(f"γ {g}")
    far = EnvConfig.from_dict(cfg["env"]).far_targets  # its defaults where the config leaves an entry out
    if far.fraction:
        words.append(f"{far.fraction:.0%} far targets {far.range_m[0]:g}-{far.range_m[1]:g} m")
    if cfg["env"]["rewards"].get("release_slope"):
        words.append(f"release_slope {cfg['env']['rewards']['release_slope']}")
    if cfg.get("training", {}).get("release_bias_init") is not None:
        words.append(f"release bias {cfg['training']['release_bias_init']}")
    if cfg["runner"]["algorithm"].get("use_mixed_precision"):
        words.append("bf16" + ("+compile" if cfg["runner"].get("torch_compile_mode") else ""))
    if cfg["runner"]["actor"].get("class_name") == FLOAT32_ACTOR:
        words.append("float32 actor")
    words += _reward_words(cfg["env"], base["env"])
    stage = cfg.get("training", {}).get("curriculum_stage") or cfg.get("training", {}).get("randomization_stage")
    if stage:
        changed = {**stage.get("randomization", {}), **stage.get("rewards", {})}
        words.append(f"from it {stage['iteration']}: " + " ".join(f"{k} {v}" for k, v in changed.items()))
    return ", ".join(words) or "committed"


def _reward_words(env: dict, base: dict) -> list[str]:
    """The forced release, ``err_3d`` and hold cost of ``env`` where they differ from ``base``'s, in words."""
    words = []
    forced, forced0 = env.get("forced_release", {}).get("probability"), base.get("forced_release", {}).get("probability")
    if forced != forced0:
        words.append("no forced release" if not forced else f"forced release {forced}")
    rewards, rewards0 = env.get("rewards", {}), base.get("rewards", {})
    if rewards.get("err_3d") != rewards0.get("err_3d"):
        words.append(f"err_3d {rewards.get('err_3d')}")
    if rewards.get("hold"):
        after = rewards.get("hold_after_s")
        words.append(f"hold {rewards['hold']}" + (f" after {after:g} s" if after else ""))
    return words


def probe_actor(src: RunSource, cfg: dict, workdir: Path) -> tuple[Path, int]:
    """The actor of a 2D run as ONNX in ``workdir``, and its iteration: the run's ``checkpoint.pt``
    (its last iteration) exported (sim_twin.training.export) or, where the run kept none, its
    exported ``throw2d.onnx`` (the iteration its model card names).

    Raises:
        FileNotFoundError: neither a checkpoint.pt nor an exported policy with its model card.
        ValueError: ``cfg`` is a 3D run's.
    """
    import torch

    from sim_twin.training.export import export_checkpoint

    if cfg["env"].get("mode", "2d") != "2d":
        raise ValueError(f"{src.spec}: a {cfg['env']['mode']} run; the probe reads 2D runs")
    onnx_path, ckpt = workdir / f"{src.name}.onnx", workdir / f"{src.name}.pt"
    try:
        ckpt.write_bytes(src.read_bytes("checkpoint.pt"))
    except FileNotFoundError:  # a run that kept only its exported policy (the checkpoint that met the bars)
        try:
            onnx_path.write_bytes(src.read_bytes("throw2d.onnx"))
            return onnx_path, int(json.loads(src.read("throw2d.card.json"))["iteration"])
        except FileNotFoundError:
            raise FileNotFoundError(f"{src.spec}: neither a checkpoint.pt nor an exported throw2d.onnx with its model card") from None
    iteration = int(torch.load(ckpt, map_location="cpu", weights_only=False).get("iter", -1))
    export_checkpoint(ckpt, cfg, onnx_path, src.name)
    return onnx_path, iteration


def probe_run(src: RunSource, target_m: float, envs: int, workdir: Path) -> dict:
    """One run's row: its recipe, training seed and checkpoint iteration, the nominal and training
    throws at ``target_m`` (:func:`throw_at`), the style the nominal landing time gives, and the
    gate's style reading and outcome where the run kept its gate (training_throw_style.run_style).

    The actor is the run's ``checkpoint.pt`` (its last iteration) or, where the run kept none, its
    exported ``throw2d.onnx`` (the iteration its model card names).

    Raises:
        FileNotFoundError: the run has no config.json, or neither a checkpoint.pt nor an exported policy.
        ValueError: a 3D run.
    """
    cfg = json.loads(src.read("config.json"))
    onnx_path, iteration = probe_actor(src, cfg, workdir)
    nominal_env = dict(cfg["env"], randomization=nominal_randomization(cfg["env"]["randomization"]))
    row = {"run": src.name, "source": src.spec, "recipe": recipe_of(cfg), "training_seed": cfg.get("training", {}).get("seed"),
           "iteration": iteration, "target_m": target_m, "envs": envs,
           "nominal": throw_at(onnx_path, nominal_env, target_m, envs),
           "training": throw_at(onnx_path, cfg["env"], target_m, envs)}
    row["style"] = style_of(row["nominal"]["landing_s"])
    try:
        gate = run_style(src)
        row["gate"] = {"style": gate["style"], "far_duration_s": gate["far_duration_s"], "style_iteration": gate["style_iteration"],
                       "outcome": gate["outcome"]}
    except (FileNotFoundError, ValueError, KeyError, StopIteration):
        row["gate"] = None
    return row


def plot(rows: list[dict], path: Path) -> None:
    """The nominal landing time of every run, grouped by recipe, with the style threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recipes = list(dict.fromkeys(r["recipe"] for r in rows))
    fig, ax = plt.subplots(figsize=(8, 0.6 * len(recipes) + 1.8))
    for i, rec in enumerate(recipes):
        pts = [r for r in rows if r["recipe"] == rec]
        x = [r["nominal"]["landing_s"] for r in pts]
        ax.scatter(x, [i] * len(x), s=60, c=["tab:blue" if r["style"] == "long" else "tab:red" for r in pts], zorder=3)
        for r, xx in zip(pts, x):
            ax.annotate(r["run"].replace("throw2d-scratch-", "-"), (xx, i), textcoords="offset points", xytext=(0, 7),
                        ha="center", fontsize=7)
    ax.axvline(LONG_STYLE_S, color="grey", ls="--", lw=1)
    ax.set_yticks(range(len(recipes)), recipes)
    ax.set_ylim(-0.7, len(recipes) - 0.3)
    ax.set_xlabel(f"nominal {rows[0]['target_m']:g} m throw, start to landing [s] (long ≥ {LONG_STYLE_S} s, blue)")
    ax.set_title("2D runs from scratch: far-target style by recipe (MJX environment, nominal machine)", fontsize=9, loc="right")
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(c: dict) -> str:
    return f"{c['landing_s']:.2f} s | {c['release_cmd_s']:.2f} s | {c['bias_m']:+.3f} | {c['sigma_m']:.3f}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories or REV:PATH")
    p.add_argument("--out", type=Path, required=True, help="report stem (writes .json, .md and .png)")
    p.add_argument("--target-m", type=float, default=FAR_TARGET_M)
    p.add_argument("--envs", type=int, default=128, help="throws per run and case")
    p.add_argument("--keep-rows-of", type=Path, default=None,
                   help="an earlier report (.json) of the same --target-m and --envs whose rows of other runs stay "
                        "in the new one, before the runs probed now (each run takes minutes on a CPU)")
    args = p.parse_args()
    settings = {"target_m": args.target_m, "envs": args.envs, "probe_key": PROBE_KEY}
    rows = kept_rows(args.keep_rows_of, settings, args.runs, "runs") if args.keep_rows_of else []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.runs:
            rows.append(probe_run(RunSource(spec), args.target_m, args.envs, Path(tmp)))
            r = rows[-1]
            print(f"{r['run']}: {r['recipe']}, seed {r['training_seed']}, it {r['iteration']}: nominal {_fmt(r['nominal'])}, "
                  f"training {_fmt(r['training'])} -> {r['style']}", flush=True)
    from sim_twin.provenance import git_commit

    commit = git_commit()
    report = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit, "long_style_s": LONG_STYLE_S,
              "target_m": args.target_m, "envs": args.envs, "probe_key": PROBE_KEY, "runs": rows}
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    plot(rows, args.out.with_suffix(".png"))
    md = [f"# 2D runs: far-target throw style read from the checkpoint ({args.target_m:g} m)\n",
          f"Date {report['date']}, commit `{commit}`. {args.envs} throws per run and case in the MJX training environment "
          f"(CPU), the same start poses for every run; style long when the nominal throw lands ≥ {LONG_STYLE_S} s after the start. "
          "Bias and σ: signed downrange error [m].\n",
          "| run | recipe | training seed | iteration | nominal: landing | release cmd | bias | σ | "
          "training: landing | release cmd | bias | σ | style | gate's style (it) | gate's outcome |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g = r["gate"]
        gate_style = f"{g['style']} ({g['far_duration_s']} s, it {g['style_iteration']})" if g else "no gate"
        outcome = "-" if not g else ("met at " + f"{g['outcome']['train_wall_min']} min" if g["outcome"]["met"]
                                     else f"not met by {g['outcome']['last_train_wall_min']} min")
        md.append(f"| `{r['run']}` | {r['recipe']} | {r['training_seed']} | {r['iteration']} | {_fmt(r['nominal'])} | "
                  f"{_fmt(r['training'])} | **{r['style']}** | {gate_style} | {outcome} |")
    md.append(f"\n![style by recipe]({args.out.with_suffix('.png').name})")
    args.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
