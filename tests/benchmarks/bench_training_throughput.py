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
import time
import traceback

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


def physics_rate(impl: str, n: int, steps: int) -> float:
    """Bare mjx.step of the MJCF over ``n`` worlds: physics steps per second."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from sim_twin.model import load_model

    m = load_model()
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


def measure(mode: str, impl: str, n: int, iterations: int, physics_steps: int, reset_slots: float | None = None) -> dict:
    import jax
    import torch
    from rsl_rl.runners import OnPolicyRunner

    from sim_twin.mjx_env import EnvConfig
    from sim_twin.train import load_config
    from sim_twin.vec_env import MjxThrowVecEnv

    row = {"mode": mode, "impl": impl, "num_envs": n, "reset_slots": reset_slots}
    try:
        if physics_steps:
            row["physics_steps_per_s"] = physics_rate(impl, n, physics_steps)
    except Exception as e:  # noqa: BLE001 - reported, the benchmark goes on
        row["physics_error"] = f"{type(e).__name__}: {e}"[:400]
    try:
        cfg = load_config(mode, None)
        device = "cuda" if torch.cuda.is_available() else "cpu"
        t0 = time.perf_counter()
        env = MjxThrowVecEnv(EnvConfig.from_dict(cfg["env"]), n, seed=0, device=device, impl=impl, reset_slots=reset_slots)
        a = jax.numpy.zeros((n, env.num_actions), jax.numpy.float32)
        out = env._step(env.state, a)
        jax.block_until_ready(out)
        row["env_compile_s"] = time.perf_counter() - t0
        st = out[0]
        k = 32
        t0 = time.perf_counter()
        for _ in range(k):
            out = env._step(st, a)
            st = out[0]
        jax.block_until_ready(out)
        row["env_steps_per_s"] = n * k / (time.perf_counter() - t0)

        runner = OnPolicyRunner(env, copy.deepcopy(cfg["runner"]), log_dir=None, device=device)
        T = cfg["runner"]["num_steps_per_env"]
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
        del runner, env
    except Exception as e:  # noqa: BLE001
        row["error"] = f"{type(e).__name__}: {e}"[:400]
        traceback.print_exc()
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
    p.add_argument("--out", default=None)
    a = p.parse_args()
    slots = [None if x == "all" else float(x) for x in a.reset_slots.split(",")]
    rows = []
    for impl in a.impls.split(","):
        for n in a.envs.split(","):
            for i, sl in enumerate(slots):  # the bare physics rate does not depend on the reset: once
                rows.append(measure(a.mode, impl, int(n), a.iterations, a.physics_steps if i == 0 else 0, sl))
                print(json.dumps(rows[-1]), flush=True)
                if a.out:
                    with open(a.out, "w") as f:
                        json.dump(rows, f, indent=2)
    print("impl   envs  reset  physics M/s  env M/s  step+infer M/s  +PPO M/s  rollout s  update s")
    for r in rows:
        reset = "all" if r["reset_slots"] is None else f"{r['reset_slots']:g}"
        print(f"{r['impl']:5} {r['num_envs']:6} {reset:>6} {_f(r.get('physics_steps_per_s'))}     {_f(r.get('env_steps_per_s'))} "
              f"{_f(r.get('step_infer_steps_per_s'))}       {_f(r.get('learn_steps_per_s'))}  {_f(r.get('rollout_s'), 1)}  "
              f"{_f(r.get('update_s'), 1)}  {r.get('error', '') or r.get('physics_error', '')}")


if __name__ == "__main__":
    main()
