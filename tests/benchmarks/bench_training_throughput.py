"""Training throughput of the MJX throwing environment with PPO learning included.

Run on a GPU machine (``python tests/benchmarks/bench_training_throughput.py --out bench.json``).
For each environment count it builds the MJX environment and rsl_rl's OnPolicyRunner, runs two
warm-up iterations (JIT compilation), then times ``--iterations`` PPO iterations (rollout of 32
control steps per environment + the PPO update) and prints control steps per second, i.e.
num_envs * 32 * iterations / wall time. All counts are measured side by side in one process.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import time

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


def measure(mode: str, num_envs: int, iterations: int) -> dict:
    import torch
    from rsl_rl.runners import OnPolicyRunner

    from sim_twin.mjx_env import EnvConfig
    from sim_twin.train import load_config
    from sim_twin.vec_env import MjxThrowVecEnv

    cfg = load_config(mode, None)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    env = MjxThrowVecEnv(EnvConfig.from_dict(cfg["env"]), num_envs, seed=0, device=device)
    runner = OnPolicyRunner(env, copy.deepcopy(cfg["runner"]), log_dir=None, device=device)
    t0 = time.perf_counter()
    runner.learn(num_learning_iterations=2)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    runner.learn(num_learning_iterations=iterations)
    if device == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    steps = num_envs * cfg["runner"]["num_steps_per_env"] * iterations
    return {"mode": mode, "num_envs": num_envs, "iterations": iterations, "wall_s": wall,
            "control_steps_per_s": steps / wall, "warmup_s": warm, "device": device}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--mode", default="2d")
    p.add_argument("--envs", default="4096,8192,16384")
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    rows = [measure(a.mode, int(n), a.iterations) for n in a.envs.split(",")]
    for r in rows:
        print(f"{r['mode']} {r['num_envs']:>6} envs: {r['control_steps_per_s']:>10.0f} control steps/s "
              f"(learning included, {r['iterations']} iterations in {r['wall_s']:.1f} s, warm-up {r['warmup_s']:.1f} s, {r['device']})")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
