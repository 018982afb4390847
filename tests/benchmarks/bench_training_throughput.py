"""Throughput of the MJX throwing environment, Isaac-Lab style, per physics implementation.

Run on a GPU machine::

    python tests/benchmarks/bench_training_throughput.py --impls jax,warp --envs 4096,16384,65536 --out bench.json
    python tests/benchmarks/bench_training_throughput.py --envs 4096,16384 --reset-slots all,0.125 --out reset.json

For each MJX implementation (``jax``: MJX's JAX physics; ``warp``: MJX calling MuJoCo Warp) and
environment count it measures, in one process on one GPU:

* ``physics_steps_per_s``: bare ``mjx.step`` of the machine's MJCF, vmapped over the worlds,
  ``--physics-steps`` steps in one jitted loop (10 ms steps);
* ``env_steps_per_s``: the training environment's control step (8 physics steps with the
  hydraulic actuation, rewards, terminations, auto-reset; 80 ms) jitted, no PyTorch;
* ``step_infer_steps_per_s``: the rsl_rl rollout: actor inference (PyTorch) + environment step
  (DLPack hand-over) + rollout storage, 32 steps per iteration;
* ``learn_steps_per_s``: rsl_rl's full PPO iteration (rollout + update), and the seconds per
  iteration spent in the rollout and in the update.

``--unroll off,on`` compares the 8 physics substeps of a control step as a loop with the same
substeps unrolled (``ThrowEnvCore``'s ``unroll_substeps``); ``--xla-flags`` runs each given set of
XLA flags in its own process (``default`` for none), e.g. command buffers (CUDA graphs) that also
capture loops and conditionals, and joins the rows into one table. ``env_step_only_per_s`` and
``env_reset_only_per_s`` time the batch's control step without the auto-reset and the batch's
reset alone, so that the environment's time splits into physics, its own work and the reset.

``--joint-limits on,off`` compares the training model with and without the MJCF's joint-limit
constraints (``ThrowEnvCore``'s ``joint_limits``; training runs without them), ``--graph-mode``
MJX's CUDA-graph modes of the Warp call (``default``, ``WARP``, ``WARP_STAGED``, ``NONE``; each row
records the mode it ran with in ``graph_mode``), and ``--update fp32,tf32,bf16,bf16critic`` (each with
modifiers, see UPDATES: compiled, TF32, one GPU wait per rollout) the PPO update's arithmetic: float32 (the recipe's), TF32 matrix products (``torch.backends.cuda.matmul.allow_tf32``)
rsl_rl's bfloat16 autocast (``algorithm.use_mixed_precision``) and ``bf16critic``, that autocast with
the actor kept in float32 (sim_twin.training.models); every update setting of one
environment configuration shares its environment rates.

``--reset-slots`` compares the auto-reset of the whole batch at every step (``all``) with resetting
only the finished environments gathered into a fraction of the batch (``ThrowEnvCore``'s
``reset_slots``), side by side in one run.

All rates count control steps (one policy decision of one environment) except
``physics_steps_per_s`` (one 10 ms physics step of one world). Prints a table and writes JSON.
A configuration that fails (for instance an implementation that cannot run the environment)
is reported with its error and the others go on.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import tempfile
import time
import traceback

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


def physics_rate(impl: str, n: int, steps: int, joint_limits: bool = True) -> float:
    """Bare mjx.step of the MJCF (without its joint-limit constraints unless ``joint_limits``)
    over ``n`` worlds: physics steps per second."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from sim_twin.training.mjx_env import training_model

    m = training_model(joint_limits)
    mx = mjx.put_model(m, impl=impl)

    @jax.jit
    def init(q):
        d = jax.vmap(lambda qq: mjx.make_data(m, impl=impl).replace(qpos=qq))(q)
        return d

    q0 = jnp.tile(jnp.asarray(m.qpos0, jnp.float32), (n, 1))
    d = init(q0)
    ctrl = 0.1 * jnp.ones((n, m.nu), jnp.float32)

    @jax.jit
    def roll(d):
        def body(_, dd):
            return jax.vmap(lambda x: mjx.step(mx, x.replace(ctrl=x.ctrl * 0 + ctrl[0])))(dd)

        return jax.lax.fori_loop(0, steps, body, d)

    jax.block_until_ready(roll(d))
    t0 = time.perf_counter()
    jax.block_until_ready(roll(d))
    return n * steps / (time.perf_counter() - t0)


def _rate(fn, args, n: int, k: int = 32) -> float:
    """Control steps per second of ``k`` chained calls of the jitted ``fn`` (state first) over ``n`` environments."""
    import jax

    out = fn(*args)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(k):
        out = fn(out[0], *args[1:])
    jax.block_until_ready(out)
    return n * k / (time.perf_counter() - t0)


UPDATES = ("fp32", "tf32", "bf16", "bf16critic")
"""The PPO update's arithmetic settings ``--update`` compares (module docstring; ``bf16critic``: the
bfloat16 update with the actor kept in float32, sim_twin.training.models.Float32MLPModel). Modifiers
follow with ``+``, any of them together (e.g. ``bf16critic+compile+tf32+syncs``): ``+compile``
compiles actor and critic with ``torch.compile`` (rsl_rl's ``torch_compile_mode`` "default"),
``+autotune`` with "max-autotune-no-cudagraphs" (autotuned kernels; rsl_rl refuses the CUDA-graph
modes: its graph replay would overwrite an earlier call's output), ``+tf32`` turns on TF32 matrix
products for what stays float32 (the recipe's ``training.tf32_matmul``; ``tf32`` alone is ``fp32+tf32``)
and ``+syncs`` waits for the GPU once per rollout instead of at every step (the recipe's
``training.per_iteration_syncs``, sim_twin.training.runner.CallbackRunner change 4)."""
COMPILE_MODES = {"compile": "default", "autotune": "max-autotune-no-cudagraphs"}
"""An update setting's compile modifier -> rsl_rl's ``torch_compile_mode``."""
MODIFIERS = (*COMPILE_MODES, "tf32", "syncs")
"""The modifiers an update setting may carry after ``+`` (UPDATES)."""


def parse_update(setting: str) -> tuple[str, set[str]]:
    """``"bf16critic+compile+syncs"`` -> ("bf16critic", {"compile", "syncs"}).

    Raises:
        ValueError: an unknown update or modifier, or two compile modes.
    """
    update, *mods = setting.split("+")
    if update not in UPDATES or not set(mods) <= set(MODIFIERS) or len(set(mods) & set(COMPILE_MODES)) > 1:
        raise ValueError(f"unknown update setting {setting!r}; known: {UPDATES}, each with any of "
                         + ", ".join(f"+{k}" for k in MODIFIERS) + " (one compile mode at most)")
    return update, set(mods)


def measure(mode: str, impl: str, n: int, iterations: int, physics_steps: int, reset_slots: float | None = None,
            unroll: bool = False, xla_flags: str = "default", joint_limits: bool = False, graph_mode: str | None = None,
            updates: tuple[str, ...] = ("fp32",)) -> list[dict]:
    """One environment configuration: its rates, then rsl_rl's rollout and PPO iteration once per
    setting in ``updates`` (UPDATES); one row per update setting, the environment's rates in each."""
    import jax
    import torch

    from sim_twin.training.config import load_config
    from sim_twin.training.mjx_env import EnvConfig
    from sim_twin.training.vec_env import MjxThrowVecEnv

    row = {"mode": mode, "impl": impl, "num_envs": n, "reset_slots": reset_slots, "unroll": unroll, "xla_flags": xla_flags,
           "joint_limits": joint_limits}
    try:
        if physics_steps:
            row["physics_steps_per_s"] = physics_rate(impl, n, physics_steps, joint_limits)
    except Exception as e:  # noqa: BLE001 - reported, the benchmark goes on
        row["physics_error"] = f"{type(e).__name__}: {e}"[:400]
    try:
        cfg = load_config(mode, None)
        device = "cuda" if torch.cuda.is_available() else "cpu"
        t0 = time.perf_counter()
        env = MjxThrowVecEnv(EnvConfig.from_dict(cfg["env"]), n, seed=0, device=device, impl=impl, reset_slots=reset_slots,
                             unroll_substeps=unroll, joint_limits=joint_limits, graph_mode=graph_mode)
        gm = env.core.model.opt._impl.graph_mode if impl == "warp" else None
        if gm is not None:
            import warp as wp

            gm = wp.JaxCallableGraphMode(int(gm)).name
        row["graph_mode"] = gm
        a = jax.numpy.zeros((n, env.num_actions), jax.numpy.float32)
        out = env._step(env.state, a)
        jax.block_until_ready(out)
        row["env_compile_s"] = time.perf_counter() - t0
        row["env_steps_per_s"] = _rate(env._step, (out[0], a), n)
        row["env_step_only_per_s"] = _rate(jax.jit(jax.vmap(env.core.step)), (out[0], a), n)
        keys = jax.random.split(jax.random.PRNGKey(1), n)
        reset = jax.jit(jax.vmap(env.core.reset))
        row["env_reset_only_per_s"] = _rate(lambda _s, k: (reset(k)[0],), (None, keys), n)
    except Exception as e:  # noqa: BLE001
        row["error"] = f"{type(e).__name__}: {e}"[:400]
        traceback.print_exc()
        return [row]
    rows = []
    for update in updates:
        rows.append(_learn_rates({**row, "update": update}, env, cfg, device, iterations))
    del env
    return rows


def _learn_rates(row: dict, env, cfg: dict, device: str, iterations: int) -> dict:
    """rsl_rl's rollout (inference + environment + storage) and whole PPO iterations on ``env``
    with the update setting ``row["update"]``: the rates into ``row``."""
    import torch

    from sim_twin.training.runner import CallbackRunner

    update, mods = parse_update(row["update"])
    runner_cfg = copy.deepcopy(cfg["runner"])
    runner_cfg["algorithm"]["use_mixed_precision"] = update in ("bf16", "bf16critic")
    if update == "bf16critic":
        from sim_twin.training.models import FLOAT32_ACTOR

        runner_cfg["actor"]["class_name"] = FLOAT32_ACTOR
    runner_cfg["torch_compile_mode"] = next((COMPILE_MODES[m] for m in mods if m in COMPILE_MODES), None)
    row["tf32"], row["per_iteration_syncs"] = update == "tf32" or "tf32" in mods, "syncs" in mods
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = row["tf32"]
    # rsl_rl's loop (CallbackRunner without callbacks; change 4 only with +syncs). Its logger keeps
    # episode statistics (and waits for the GPU at every step for them) only with a log writer, as in
    # training: a throwaway TensorBoard folder. (Rows before 2026-11-27 ran without one.)
    tb = tempfile.mkdtemp(prefix="bench_tb_")
    try:
        runner = CallbackRunner(env, runner_cfg, log_dir=tb, device=device, save_interval=0,
                                checkpoint_dir=tb, per_iteration_syncs=row["per_iteration_syncs"])
        T = cfg["runner"]["num_steps_per_env"]
        n = env.num_envs
        alg = runner.alg

        def rollout():
            obs = env.get_observations()
            with torch.inference_mode():
                for _ in range(T):
                    act = alg.act(obs)
                    obs, rew, dones, extras = env.step(act)
                    alg.process_env_step(obs, rew, dones, extras)
                alg.compute_returns(obs)
            torch.cuda.synchronize() if device == "cuda" else None

        rollout()
        alg.storage.clear()
        t0 = time.perf_counter()
        for _ in range(iterations):
            rollout()
            alg.storage.clear()
        row["step_infer_steps_per_s"] = n * T * iterations / (time.perf_counter() - t0)
        runner.learn(num_learning_iterations=1)
        torch.cuda.synchronize() if device == "cuda" else None
        t0 = time.perf_counter()
        runner.learn(num_learning_iterations=iterations)
        torch.cuda.synchronize() if device == "cuda" else None
        wall = time.perf_counter() - t0
        row["learn_steps_per_s"] = n * T * iterations / wall
        row["iteration_s"] = wall / iterations
        row["rollout_s"] = n * T / row["step_infer_steps_per_s"]
        row["update_s"] = row["iteration_s"] - row["rollout_s"]
        row["device"] = torch.cuda.get_device_name(0) if device == "cuda" else "cpu"
        del runner
    except Exception as e:  # noqa: BLE001
        row["error"] = f"{type(e).__name__}: {e}"[:400]
        traceback.print_exc()
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
        shutil.rmtree(tb, ignore_errors=True)
    return row


def _f(x, scale=1e6, fmt="{:8.2f}"):
    return fmt.format(x / scale) if isinstance(x, (int, float)) else f"{'-':>8}"


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--mode", default="2d")
    p.add_argument("--impls", default="jax")
    p.add_argument("--envs", default="4096,16384,65536")
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--physics-steps", type=int, default=200)
    p.add_argument("--reset-slots", default="all", help="comma-separated: 'all' and/or fractions in (0, 1)")
    p.add_argument("--unroll", default="off", help="comma-separated: off and/or on (unrolled physics substeps)")
    p.add_argument("--joint-limits", default="off", help="comma-separated: off (training's model) and/or on (the MJCF's limits)")
    p.add_argument("--graph-mode", default="default",
                   help="comma-separated MJX graph modes of the Warp call: default, WARP, WARP_STAGED, NONE (warp rows only)")
    p.add_argument("--update", default="fp32", help=f"comma-separated PPO update settings: {', '.join(UPDATES)}, each with any of "
                   + ", ".join(f"+{m}" for m in MODIFIERS) + " (UPDATES)")
    p.add_argument("--xla-flags", default="default",
                   help="';'-separated sets of XLA flags, one process each ('default': none)")
    p.add_argument("--out", default=None)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args()
    for setting in a.update.split(","):
        try:
            parse_update(setting)
        except ValueError as e:
            p.error(str(e))
    flag_sets = a.xla_flags.split(";")
    rows = []
    if len(flag_sets) > 1 and not a.child:
        for fs in flag_sets:  # XLA reads its flags once per process
            rows += _child(fs)
            _save(a.out, rows)
    else:
        rows = _measure_all(a, flag_sets[0])
    if a.child:
        print("ROWS " + json.dumps(rows), flush=True)
        return
    print("impl   envs  reset unroll limits graph        update                         physics M/s  env M/s  step-only  reset-only  step+infer M/s  +PPO M/s  "
          "rollout s  update s  XLA flags")
    for r in rows:
        reset = "all" if r["reset_slots"] is None else f"{r['reset_slots']:g}"
        graph = r.get("graph_mode") or "-"
        print(f"{r['impl']:5} {r['num_envs']:6} {reset:>6} {'on' if r.get('unroll') else 'off':>6} "
              f"{'on' if r.get('joint_limits') else 'off':>6} {graph:12} {r.get('update', '-'):30} {_f(r.get('physics_steps_per_s'))}     "
              f"{_f(r.get('env_steps_per_s'))} {_f(r.get('env_step_only_per_s'))}  {_f(r.get('env_reset_only_per_s'))}   "
              f"{_f(r.get('step_infer_steps_per_s'))}       {_f(r.get('learn_steps_per_s'))}  {_f(r.get('rollout_s'), 1)}  "
              f"{_f(r.get('update_s'), 1)}  {r.get('xla_flags', '')} {r.get('error', '') or r.get('physics_error', '')}")


def _measure_all(a, xla_flags: str) -> list[dict]:
    """Every implementation x environment count x joint limits x graph mode x reset x unroll of
    the arguments (each with every update setting), in this process."""
    slots = [None if x == "all" else float(x) for x in a.reset_slots.split(",")]
    unrolls = [u == "on" for u in a.unroll.split(",")]
    limits = [x == "on" for x in a.joint_limits.split(",")]
    updates = tuple(a.update.split(","))
    rows: list[dict] = []
    for impl in a.impls.split(","):
        modes = [None if g == "default" else g for g in a.graph_mode.split(",")] if impl == "warp" else [None]
        for n in a.envs.split(","):
            for lim in limits:
                first = True  # the bare physics rate depends on the limits only: once per limit setting
                for gm in modes:
                    for sl in slots:
                        for un in unrolls:
                            new = measure(a.mode, impl, int(n), a.iterations, a.physics_steps if first else 0, sl, un, xla_flags,
                                          lim, gm, updates)
                            first = False
                            rows += new
                            for r in new:
                                print(json.dumps(r), flush=True)
                            _save(a.out, rows)
    return rows


def _save(out: str | None, rows: list[dict]) -> None:
    """Write the rows so far to ``out`` (if given) after each measurement, so that a run stopped
    at a time limit keeps what it measured."""
    if out:
        with open(out, "w") as f:
            json.dump(rows, f, indent=2)


def _child(flags: str) -> list[dict]:
    """Run this benchmark with one set of XLA flags in a new process; its rows."""
    import subprocess
    import sys

    env = dict(os.environ)
    if flags != "default":
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flags).strip()
    args, skip = [], False
    for x in sys.argv[1:]:  # the parent's arguments but its flag sets and output file
        if skip or x.startswith(("--xla-flags=", "--out=")):
            skip = False
            continue
        if x in ("--xla-flags", "--out"):
            skip = True
            continue
        args.append(x)
    proc = subprocess.run([sys.executable, __file__, *args, "--child", f"--xla-flags={flags}"], env=env,
                          capture_output=True, text=True)
    sys.stderr.write(proc.stderr[-4000:])
    for line in proc.stdout.splitlines():
        if line.startswith("ROWS "):
            return json.loads(line[5:])
        print(line, flush=True)
    return [{"xla_flags": flags, "impl": "-", "num_envs": 0, "reset_slots": None, "error": f"child exited {proc.returncode}"}]


if __name__ == "__main__":
    main()
