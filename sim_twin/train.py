"""PPO training of the throwing policy (rsl_rl's OnPolicyRunner on the MJX environment).

``slinger train --mode 2d`` trains from scratch on the GPU (JAX and PyTorch both on it; the CPU
when there is none: use tiny settings there) and, with ``--gate`` (the default), runs the site
matrix of its newest checkpoint on the CPU cores beside it (sim_twin.matrix_gate) and stops at the
first checkpoint that meets every site-matrix bar on every ``--gate-seeds`` seed. That checkpoint
is exported to ONNX (``--export``, default ``<log-dir>/throw<mode>.onnx``) with its model card
(sim_twin.model_card: command, config hash, GPU, wall time, matrices). If no checkpoint met the bars
when ``--iterations`` or ``--max-minutes`` run out, nothing is exported unless ``--export`` is given
(then the last checkpoint, its card saying the bars were not met). With ``--no-stop-at-bars`` the
training runs on to ``--iterations`` / ``--max-minutes``, the gate judging newer checkpoints, and the
newest checkpoint that met every bar is exported (its matrices feed the deploy comparison,
sim_twin.matrix_compare).

Training runs in chunks of ``--chunk`` iterations; after every chunk the checkpoint (policy,
critic, optimiser state, iteration) is written to ``<log-dir>/checkpoint.pt`` with the resolved
config, the training curve (``curve.csv``, per-term reward means included) and the gate's state,
so a run stopped at any moment resumes with ``--resume <log-dir>/checkpoint.pt``. rsl_rl writes
every iteration's losses, action std and per-term reward means (``Reward/<term>``) to TensorBoard
(``<log-dir>/tb``).

Exploration: the config's ``training.std_schedule`` caps the actor's learned action std at a
value that falls from ``start`` to ``end`` over ``iterations`` (exponentially), applied at every
chunk boundary; below the cap the std is learned (rsl_rl's GaussianDistribution).

Curriculum over the randomisation width: the config's ``training.randomization_stage`` (see
:class:`RandomizationStage`) widens ``env.randomization`` once, at the first chunk boundary at or
after its ``iteration``; the critic's privileged inputs are normalised over the widened ranges from
the start (``env.privileged_ranges``), so their scale does not change at the switch.
``training.gate_from_iteration`` (default 0) offers the gate only checkpoints from that iteration
on (a recipe that widens its randomisation judges the policies trained on the wide ranges).

Several GPUs: ``--gpus N`` re-launches the command under torchrun (one process per GPU, each with
``--num-envs`` environments, rsl_rl's multi-GPU mode: gradients all-reduced, rank 0 logs,
checkpoints and runs the gate; the stop decision is broadcast to every rank).

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
import math
import os
import shlex
import statistics
import sys
import time
from dataclasses import dataclass, fields
from pathlib import Path

from runtime.entrypoint import module_main

log = logging.getLogger(__name__)

CONFIG_DIR = Path(__file__).parent / "configs"


def _check_integer(value, name: str, at_least: int | None = None) -> None:
    """Raises ValueError unless ``value`` is an int (not a bool) and, with ``at_least``, >= it; the
    message names the config entry ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or (at_least is not None and value < at_least):
        bound = f" >= {at_least}" if at_least is not None else ""
        raise ValueError(f"{name} must be an integer{bound}, not {value!r}")


@dataclass(frozen=True)
class StdSchedule:
    """Cap on the actor's action std: ``start`` -> ``end`` exponentially over ``iterations``,
    ``end`` after (config ``training.std_schedule``; CHOSEN values in configs/*.json).

    ``release_floor`` (0: none) is a lower bound on the std of the release flag (the last action):
    with a learned std the flag's std can shrink before the release is timed, after which the flag
    never crosses its 0.9 threshold and the policy stops throwing (seen from scratch in 3D)."""

    start: float
    end: float
    iterations: int
    release_floor: float = 0.0

    def cap(self, iteration: int) -> float:
        """The cap at ``iteration`` (>= 0)."""
        f = min(max(iteration, 0) / max(self.iterations, 1), 1.0)
        return float(self.start * (self.end / self.start) ** f)

    @classmethod
    def from_dict(cls, d: dict) -> StdSchedule:
        """Raises ValueError on unknown keys or non-positive values."""
        unknown = set(d) - {"start", "end", "iterations", "release_floor"}
        if unknown:
            raise ValueError(f"unknown std_schedule settings {sorted(unknown)}")
        s = cls(float(d["start"]), float(d["end"]), int(d["iterations"]), float(d.get("release_floor", 0.0)))
        if s.start <= 0 or s.end <= 0 or s.iterations < 1:
            raise ValueError(f"std_schedule needs start, end > 0 and iterations >= 1, got {d}")
        if not 0.0 <= s.release_floor <= s.end:
            raise ValueError(f"std_schedule.release_floor must be in [0, end], got {s.release_floor}")
        return s


@dataclass(frozen=True)
class RandomizationStage:
    """A widening of the domain randomisation during training (config
    ``training.randomization_stage``): from ``iteration`` on, new episodes draw from
    ``env.randomization`` with the entries of ``randomization`` in place of its own (CHOSEN values
    in configs/*.json). A curriculum over randomisation width: the policy first learns to throw on
    the narrower ranges, then becomes robust on the wider ones.

    Raises (from_dict):
        ValueError: unknown keys, a negative iteration, or widened entries that
            sim_twin.privileged.check_randomization refuses.
    """

    iteration: int
    randomization: dict

    @classmethod
    def from_dict(cls, d: dict) -> RandomizationStage:
        from sim_twin.privileged import check_randomization

        unknown = set(d) - {"iteration", "randomization"}
        if unknown or "iteration" not in d or "randomization" not in d:
            raise ValueError(f"training.randomization_stage needs exactly 'iteration' and 'randomization', got {sorted(d)}")
        _check_integer(d["iteration"], "training.randomization_stage.iteration", at_least=0)
        check_randomization(d["randomization"], "training.randomization_stage.randomization")
        return cls(d["iteration"], dict(d["randomization"]))

    def env_dicts(self, env: dict) -> tuple[dict, dict]:
        """(before, after): the ``env`` mappings of the config before and after the widening. Both
        normalise the critic's privileged inputs over the widened ranges (``privileged_ranges``,
        an explicit entry of the config kept), so the critic's inputs keep their scale.

        Raises:
            ValueError: the merged randomisation is refused (sim_twin.privileged.Randomization).
        """
        from sim_twin.privileged import Randomization, trained_ranges

        wide = {**env.get("randomization", {}), **self.randomization}
        Randomization.from_dict(wide, "training.randomization_stage (merged)")
        priv = {**trained_ranges(wide), **env.get("privileged_ranges", {})}
        before = {**env, "privileged_ranges": priv}
        return before, {**before, "randomization": wide}


@dataclass(frozen=True)
class TrainingSection:
    """The config's ``training`` section, typed: what the run does beside the environment and PPO.

    ``seed`` (int or None: then ``--seed`` must give one, :func:`training_seed`), ``std_schedule``
    (:class:`StdSchedule` or None: the learned std is only clamped by rsl_rl),
    ``randomization_stage`` (:class:`RandomizationStage` or None: no widening) and
    ``gate_from_iteration`` (int >= 0, default 0: the first iteration whose checkpoint the site-matrix
    gate judges).

    Raises (from_dict):
        ValueError: an unknown key (a misspelt setting would otherwise be ignored), a seed or
            ``gate_from_iteration`` that is not an integer (>= 0), or what StdSchedule.from_dict and
            RandomizationStage.from_dict refuse.
    """

    seed: int | None = None
    std_schedule: StdSchedule | None = None
    randomization_stage: RandomizationStage | None = None
    gate_from_iteration: int = 0

    @classmethod
    def from_dict(cls, d: dict) -> TrainingSection:
        known = [f.name for f in fields(cls)]
        unknown = set(d) - set(known)
        if unknown:
            raise ValueError(f"unknown training settings {sorted(unknown)}; known: {known}")
        seed = d.get("seed")
        if seed is not None:
            _check_integer(seed, "training.seed")
        gate_from = d.get("gate_from_iteration", 0)
        _check_integer(gate_from, "training.gate_from_iteration", at_least=0)
        schedule = StdSchedule.from_dict(d["std_schedule"]) if "std_schedule" in d else None
        stage = RandomizationStage.from_dict(d["randomization_stage"]) if "randomization_stage" in d else None
        return cls(seed, schedule, stage, gate_from)


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=["2d", "3d"], default="2d")
    parser.add_argument("--config", type=Path, default=None, help="default: sim_twin/configs/throw_<mode>.json")
    parser.add_argument("--num-envs", type=int, default=None, help="override the config's num_envs (per GPU)")
    parser.add_argument("--iterations", type=int, default=5000, help="most PPO iterations to run in this call")
    parser.add_argument("--chunk", type=int, default=25, help="iterations between checkpoints")
    parser.add_argument("--max-minutes", type=float, default=None, help="stop after the chunk that passes this")
    parser.add_argument("--log-dir", type=Path, default=None, help="default runs/throw_<mode>")
    parser.add_argument("--tb-dir", type=Path, default=None, help="TensorBoard dir (default <log-dir>/tb)")
    parser.add_argument("--resume", type=Path, default=None, help="checkpoint.pt to resume from")
    parser.add_argument("--seed", type=int, default=None,
                        help="training seed (default: the recipe's training.seed, that of the run its docs quote)")
    parser.add_argument("--keep-every", type=int, default=0, help="also keep checkpoint_<iter>.pt every N iterations")
    parser.add_argument("--export", type=Path, default=None,
                        help="ONNX to write (default with the gate: <log-dir>/throw<mode>.onnx once the bars are met)")
    parser.add_argument("--name", default=None, help="policy version name for the export")
    parser.add_argument("--gate", action=argparse.BooleanOptionalAction, default=True,
                        help="site matrix of new checkpoints on the CPU beside the training; stop at the first that meets every bar")
    parser.add_argument("--gate-seeds", default="0,1", help="start-pose seeds every bar must be met on")
    parser.add_argument("--gate-throws", type=int, default=100, help="throws per site-matrix cell")
    parser.add_argument("--gate-targets", default=None, help="matrix targets (default the matrix's)")
    parser.add_argument("--gate-workers", type=int, default=None, help="matrix processes (default cores - 3)")
    parser.add_argument("--gate-every", type=int, default=1, help="offer every N-th checkpoint to the gate")
    parser.add_argument("--stop-at-bars", action=argparse.BooleanOptionalAction, default=True,
                        help="stop at the first checkpoint that meets every bar (default); with --no-stop-at-bars "
                             "train on to --iterations / --max-minutes, the gate judging newer checkpoints, and "
                             "export the newest one that met every bar")
    parser.add_argument("--gate-wait-minutes", type=float, default=0.0,
                        help="at the end, wait this long for a running matrix")
    parser.add_argument("--physics", choices=["jax", "warp"], default="jax", help="MJX implementation")
    parser.add_argument("--gpus", type=int, default=1, help="GPUs of this host to train on (torchrun, one process each)")


def load_config(mode: str, path: Path | None) -> dict:
    """The training config (env + runner + num_envs [+ training]) as a dict."""
    return json.loads((path or CONFIG_DIR / f"throw_{mode}.json").read_text())


def training_seed(cfg: dict, override: int | None) -> int:
    """The run's training seed (it seeds the environments' start poses and randomisation; rank r of a
    multi-GPU run adds 1000 r): ``override`` (``--seed``) where given, else the recipe's
    ``training.seed``. It is written into ``cfg["training"]["seed"]`` so that the run's config.json
    and model card record the seed actually used. Raises ValueError when neither gives one, when the
    seed is not an integer, or on what :meth:`TrainingSection.from_dict` refuses in the section."""
    training = cfg.setdefault("training", {})
    seed = TrainingSection.from_dict({**training, "seed": override if override is not None else training.get("seed")}).seed
    if seed is None:
        raise ValueError("the config has no training.seed: pass --seed")
    training["seed"] = seed
    return seed


def apply_std_cap(runner, cap: float, release_floor: float = 0.0) -> None:
    """Cap the actor's action std at ``cap``: the learned parameter is clamped in place (so its
    gradient lives again below the cap) and so is the distribution's upper clamp. With
    ``release_floor`` > 0 the release flag's (last action's) std is raised to at least that."""
    import torch

    dist = runner.alg.actor.distribution
    with torch.no_grad():
        if getattr(dist, "std_type", "scalar") == "log":
            dist.log_std_param.clamp_(max=math.log(cap))
            dist.log_std_range[1] = math.log(cap)
            if release_floor > 0:
                dist.log_std_param[-1].clamp_(min=math.log(release_floor))
        else:
            dist.std_param.clamp_(max=cap)
            if release_floor > 0:
                dist.std_param[-1].clamp_(min=release_floor)
        dist.std_range[1] = cap


def current_std(runner) -> float:
    """Mean over actions of the actor's action std (after its clamp)."""
    import torch

    dist = runner.alg.actor.distribution
    with torch.no_grad():
        if getattr(dist, "std_type", "scalar") == "log":
            return float(dist.log_std_param.clamp(*dist.log_std_range).exp().mean())
        return float(dist.std_param.clamp(*dist.std_range).mean())


def _launch_torchrun(args: argparse.Namespace, argv: list[str]) -> int:
    """Re-run this command under torchrun with one process per GPU."""
    import subprocess

    # The workers get the same arguments, --gpus included (a torchrun worker does not re-launch), so
    # that the model card names the command as it was given.
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.gpus}", "-m", "sim_twin.train", *argv]
    log.info("launching %s", shlex.join(cmd))
    return subprocess.call(cmd)


def run(args: argparse.Namespace) -> int:
    """Train; returns 0. Raises on configuration errors."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    import jax
    import torch
    from rsl_rl.runners import OnPolicyRunner

    from sim_twin import critic_surgery
    from sim_twin.matrix_gate import MatrixGate
    from sim_twin.mjx_env import EnvConfig
    from sim_twin.training_curve import TrainingCurve
    from sim_twin.vec_env import MjxThrowVecEnv

    gate_on = getattr(args, "gate", False)
    stop_at_bars = getattr(args, "stop_at_bars", True)
    log_dir = args.log_dir or Path("runs") / f"throw_{args.mode}"
    cfg = load_config(args.mode, args.config)
    if args.num_envs:
        cfg["num_envs"] = args.num_envs
    seed = training_seed(cfg, args.seed)
    training = TrainingSection.from_dict(cfg["training"])
    stage, schedule, gate_from = training.randomization_stage, training.std_schedule, training.gate_from_iteration
    env_before, env_after = stage.env_dicts(cfg["env"]) if stage else (cfg["env"], cfg["env"])
    env_cfg = EnvConfig.from_dict(env_before)
    if env_cfg.mode != args.mode:
        raise ValueError(f"config is for mode {env_cfg.mode}, asked for {args.mode}")
    actor_groups = cfg["runner"].get("obs_groups", {}).get("actor", ["policy"])
    if actor_groups != ["policy"]:
        raise ValueError(f"runner.obs_groups.actor must be ['policy'] (the exported policy's input), not {actor_groups}")
    if torch.cuda.is_available():
        device = f"cuda:{local_rank}" if world > 1 else "cuda"
        if world > 1:  # JAX on this process's GPU too (DLPack hands arrays over without a copy)
            jax.config.update("jax_default_device", jax.devices("gpu")[local_rank])
    else:
        if world > 1:
            raise ValueError("more than one process needs CUDA GPUs")
        device = "cpu"
    main_rank = rank == 0
    if main_rank:
        log.info("training %s on %s: %d process(es) x %d envs, physics %s", args.mode, device, world, cfg["num_envs"],
                 getattr(args, "physics", "jax"))
        log_dir.mkdir(parents=True, exist_ok=True)
        (log_dir / "config.json").write_text(json.dumps(cfg, indent=2))

    env = MjxThrowVecEnv(env_cfg, cfg["num_envs"], seed=seed + 1000 * rank, device=device,
                         impl=getattr(args, "physics", "jax"))
    runner_cfg = copy.deepcopy(cfg["runner"])
    tb_dir = (args.tb_dir or log_dir / "tb") if main_rank else None
    runner = OnPolicyRunner(env, runner_cfg, log_dir=str(tb_dir) if tb_dir else None, device=device)
    curve = TrainingCurve.load_or_new(log_dir / "curve.csv")
    wall_offset = curve.last_wall_s()
    if args.resume:
        critic_surgery.resume(runner, args.resume, device)  # widens an older critic (privileged inputs)
        runner.current_learning_iteration += 1
        log.info("resumed from %s at iteration %d", args.resume, runner.current_learning_iteration)

    start = time.time()
    clock = lambda: wall_offset + time.time() - start  # noqa: E731
    gate = None
    if gate_on and main_rank:
        gate = MatrixGate(log_dir / "matrices", args.mode, [int(s) for s in str(args.gate_seeds).split(",")],
                          throws=args.gate_throws, targets=args.gate_targets, workers=args.gate_workers, clock=clock,
                          judge_after_pass=not stop_at_bars)
        gate.watch()  # verdicts are recorded when each matrix ends, not at the next checkpoint
    done_iters, chunks = 0, 0
    stop_reason = "iterations"
    passed = gate.passed if gate else None
    widened = False
    while done_iters < args.iterations and not (passed and stop_at_bars):
        if stage and not widened and runner.current_learning_iteration >= stage.iteration:
            env.reconfigure(EnvConfig.from_dict(env_after))
            widened = True
            log.info("randomisation widened at iteration %d: %s", runner.current_learning_iteration, stage.randomization)
        if schedule:
            apply_std_cap(runner, schedule.cap(runner.current_learning_iteration), schedule.release_floor)
        n = min(args.chunk, args.iterations - done_iters)
        env.reset_stats()
        t_chunk = time.time()
        runner.learn(num_learning_iterations=n)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        chunk_s = time.time() - t_chunk
        runner.current_learning_iteration += 1
        done_iters += n
        chunks += 1
        it = runner.current_learning_iteration
        stop = torch.zeros(1, device=device)
        if main_rank:
            buf = runner.logger.rewbuffer
            stats = env.read_stats()
            std = current_std(runner)
            curve.append(
                iteration=it,
                wall_s=clock(),
                mean_reward=statistics.mean(buf) if buf else float("nan"),
                mean_episode_length=statistics.mean(runner.logger.lenbuffer) if runner.logger.lenbuffer else float("nan"),
                action_std=std,
                control_steps_per_s=cfg["num_envs"] * world * cfg["runner"]["num_steps_per_env"] * n / chunk_s,
                **stats,
                **env.read_term_means(),
            )
            runner.save(str(log_dir / "checkpoint.pt"))
            for stale in (Path(tb_dir).glob("model_*.pt") if tb_dir else ()):  # rsl_rl saves one per learn() call; checkpoint.pt is ours
                stale.unlink()
            if args.keep_every and it % args.keep_every == 0:
                runner.save(str(log_dir / f"checkpoint_{it}.pt"))
            curve.save()
            log.info("checkpoint at iteration %d (%.1f min): %s, std %.3f", it, clock() / 60, stats, std)
            if gate:
                passed = gate.poll()
                if not (passed and stop_at_bars) and not gate.busy and chunks % max(args.gate_every, 1) == 0 and it >= gate_from:
                    cand = log_dir / "candidates" / f"checkpoint_{it}.pt"
                    cand.parent.mkdir(exist_ok=True)
                    runner.save(str(cand))
                    onnx = _export(cand, cfg, cand.with_suffix(".onnx"), f"throw{args.mode}-it{it}")
                    gate.submit(it, onnx, clock())
            if passed and stop_at_bars:
                stop_reason = "bars met"
            elif args.max_minutes and (time.time() - start) / 60.0 > args.max_minutes:
                stop_reason = "time budget"
            stop[0] = 1.0 if stop_reason != "iterations" else 0.0
        if world > 1:
            torch.distributed.broadcast(stop, src=0)
        if stop[0] > 0:
            break
    if world > 1:
        torch.distributed.destroy_process_group()  # rsl_rl's runner made it; NCCL warns at exit otherwise
    if not main_rank:
        return 0
    if gate and not (passed and stop_at_bars) and args.gate_wait_minutes > 0:
        log.info("waiting up to %.1f min for the running site matrix", args.gate_wait_minutes)
        passed = gate.wait(args.gate_wait_minutes * 60)
    if gate:
        gate.stop()
        passed = gate.passes[-1] if gate.passes and not stop_at_bars else passed  # the newest that met every bar
    log.info("training stopped (%s) at iteration %d after %.1f min", "bars met" if passed and stop_at_bars else stop_reason,
             runner.current_learning_iteration, clock() / 60)
    curve.plot(log_dir / "training_curve.png", title=f"PPO, {args.mode}, {world} x {cfg['num_envs']} envs")
    out = args.export or (log_dir / f"throw{args.mode}.onnx" if passed else None)
    if out:
        ckpt = Path(passed["onnx"]).with_suffix(".pt") if passed else log_dir / "checkpoint.pt"
        it = passed["iteration"] if passed else runner.current_learning_iteration
        _export(ckpt, cfg, out, args.name or out.stem, command=getattr(args, "command", None), card=dict(
            iteration=it, train_wall_s=passed["train_wall_s"] if passed else clock(),
            verdict_wall_s=passed["verdict_wall_s"] if passed else None, world_size=world,
            matrices=[r.__dict__ for r in gate.results if r.iteration == it] if gate else [], bars_met=bool(passed)))
    return 0


def _export(checkpoint: Path, cfg: dict, out: Path, name: str, card: dict | None = None, command: str | None = None) -> Path:
    """Export ``checkpoint`` to ONNX + manifest; with ``card`` also write the model card (naming
    ``command``, by default this process's command line) and put it into the manifest's
    ``training`` section."""
    from runtime.policy import sha256_of, write_manifest
    from sim_twin import model_card
    from sim_twin.export import export_checkpoint

    export_checkpoint(checkpoint, cfg, out, name=name)
    if card is not None:
        c = model_card.build_card(command=command or shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]), cfg=cfg, gpus=model_card.accelerator(),
                                  policy_sha256=sha256_of(out), **card)
        model_card.write_card(out, c)
        manifest = json.loads(out.with_suffix(".json").read_text())
        manifest["training"]["model_card"] = c
        write_manifest(out, manifest)
    return out


def main(argv: list[str] | None = None) -> int:
    """``slinger train`` / ``python -m sim_twin.train``: with ``--gpus N`` > 1 (and not already a
    torchrun worker) re-launch under torchrun, one process per GPU; otherwise train here.
    Returns the exit code; 2 with a message when the host has fewer GPUs than asked for."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--gpus", type=int, default=1)
    known, _ = p.parse_known_args(argv)
    if known.gpus < 1:
        print(f"slinger train: --gpus must be at least 1, not {known.gpus}", file=sys.stderr)
        return 2
    if known.gpus > 1 and "WORLD_SIZE" not in os.environ:
        import torch

        have = torch.cuda.device_count()
        if have < known.gpus:
            print(f"slinger train: --gpus {known.gpus} asks for {known.gpus} CUDA GPUs; this host has {have}", file=sys.stderr)
            return 2
        logging.basicConfig(level=logging.INFO)
        return _launch_torchrun(known, argv)

    def run_as_given(args: argparse.Namespace) -> int:
        args.command = shlex.join(["slinger", "train", *argv])  # for the model card
        return run(args)

    return module_main('slinger train', __doc__, build_parser, run_as_given, argv)


if __name__ == "__main__":
    raise SystemExit(main())
