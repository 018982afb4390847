"""PPO training of the throwing policy (rsl_rl's OnPolicyRunner on the MJX environment).

``slinger train --mode 2d`` runs on the GPU when there is one (JAX and PyTorch both on it), on
the CPU otherwise (use tiny settings there). Training runs in chunks; after every chunk the
checkpoint (policy, critic, optimiser state, iteration) is written to ``<log-dir>/checkpoint.pt``
together with the resolved config and the training curve, so a run stopped at any moment resumes
exactly with ``--resume <log-dir>/checkpoint.pt``. ``--max-minutes`` stops cleanly before a
time limit. Progress is printed by rsl_rl every iteration; TensorBoard logs go to the log dir.

The actor sees the ``policy`` group only (config ``runner.obs_groups.actor``, checked); the
critic the groups in ``runner.obs_groups.critic``: ["policy"] or, for the asymmetric
actor-critic, ["policy", "privileged"] (sim_twin.privileged). Resuming a checkpoint whose critic
had fewer inputs widens it without changing its values (sim_twin.critic_surgery).
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import statistics
import time
from pathlib import Path

from runtime.entrypoint import module_main

log = logging.getLogger(__name__)

CONFIG_DIR = Path(__file__).parent / "configs"


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=["2d", "3d"], default="2d")
    parser.add_argument("--config", type=Path, default=None, help="default: sim_twin/configs/throw_<mode>.json")
    parser.add_argument("--num-envs", type=int, default=None, help="override the config's num_envs")
    parser.add_argument("--iterations", type=int, default=1000, help="PPO iterations to run in this call")
    parser.add_argument("--chunk", type=int, default=25, help="iterations between checkpoints")
    parser.add_argument("--max-minutes", type=float, default=None, help="stop after the chunk that passes this")
    parser.add_argument("--log-dir", type=Path, default=Path("runs/throw_2d"))
    parser.add_argument("--tb-dir", type=Path, default=None, help="TensorBoard dir (default <log-dir>/tb)")
    parser.add_argument("--resume", type=Path, default=None, help="checkpoint.pt to resume from")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--keep-every", type=int, default=0, help="also keep checkpoint_<iter>.pt every N iterations")
    parser.add_argument("--export", type=Path, default=None, help="write ONNX + manifest here at the end")
    parser.add_argument("--name", default=None, help="policy version name for the export")


def load_config(mode: str, path: Path | None) -> dict:
    """The training config (env + runner + num_envs) as a dict."""
    return json.loads((path or CONFIG_DIR / f"throw_{mode}.json").read_text())


def run(args: argparse.Namespace) -> int:
    """Train; returns 0. Raises on configuration errors."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    import torch
    from rsl_rl.runners import OnPolicyRunner

    from sim_twin import critic_surgery
    from sim_twin.mjx_env import EnvConfig
    from sim_twin.training_curve import TrainingCurve
    from sim_twin.vec_env import MjxThrowVecEnv

    cfg = load_config(args.mode, args.config)
    if args.num_envs:
        cfg["num_envs"] = args.num_envs
    env_cfg = EnvConfig.from_dict(cfg["env"])
    if env_cfg.mode != args.mode:
        raise ValueError(f"config is for mode {env_cfg.mode}, asked for {args.mode}")
    actor_groups = cfg["runner"].get("obs_groups", {}).get("actor", ["policy"])
    if actor_groups != ["policy"]:
        raise ValueError(f"runner.obs_groups.actor must be ['policy'] (the exported policy's input), not {actor_groups}")
    device = "cuda" if torch.cuda.is_available() else "cpu"
    log.info("training %s on %s with %d envs", args.mode, device, cfg["num_envs"])
    args.log_dir.mkdir(parents=True, exist_ok=True)
    (args.log_dir / "config.json").write_text(json.dumps(cfg, indent=2))

    env = MjxThrowVecEnv(env_cfg, cfg["num_envs"], seed=args.seed, device=device)
    runner_cfg = copy.deepcopy(cfg["runner"])
    runner = OnPolicyRunner(env, runner_cfg, log_dir=str(args.tb_dir or args.log_dir / "tb"), device=device)
    curve = TrainingCurve.load_or_new(args.log_dir / "curve.csv")
    wall_offset = curve.last_wall_s()
    if args.resume:
        critic_surgery.resume(runner, args.resume, device)  # widens an older critic (privileged inputs)
        runner.current_learning_iteration += 1
        log.info("resumed from %s at iteration %d", args.resume, runner.current_learning_iteration)

    start = time.time()
    done_iters = 0
    while done_iters < args.iterations:
        n = min(args.chunk, args.iterations - done_iters)
        env.reset_stats()
        runner.learn(num_learning_iterations=n)
        runner.current_learning_iteration += 1
        done_iters += n
        buf = runner.logger.rewbuffer
        stats = env.read_stats()
        curve.append(
            iteration=runner.current_learning_iteration,
            wall_s=wall_offset + time.time() - start,
            mean_reward=statistics.mean(buf) if buf else float("nan"),
            mean_episode_length=statistics.mean(runner.logger.lenbuffer) if runner.logger.lenbuffer else float("nan"),
            **stats,
        )
        runner.save(str(args.log_dir / "checkpoint.pt"))
        it = runner.current_learning_iteration
        if args.keep_every and it % args.keep_every == 0:
            runner.save(str(args.log_dir / f"checkpoint_{it}.pt"))
        curve.save()
        log.info("checkpoint at iteration %d: %s", runner.current_learning_iteration, stats)
        if args.max_minutes and (time.time() - start) / 60.0 > args.max_minutes:
            log.info("time budget of %.1f min reached", args.max_minutes)
            break
    curve.plot(args.log_dir / "training_curve.png", title=f"PPO, {args.mode}, {cfg['num_envs']} envs")
    if args.export:
        from sim_twin.export import export_checkpoint

        export_checkpoint(args.log_dir / "checkpoint.pt", cfg, args.export, name=args.name or args.export.stem)
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main('slinger train', __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
