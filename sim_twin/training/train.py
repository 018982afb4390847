"""PPO training of the throwing policy (rsl_rl's OnPolicyRunner on the MJX environment).

``slinger train --mode 2d`` trains from scratch on the GPU (JAX and PyTorch both on it; the CPU
when there is none: use tiny settings there) and, with ``--gate`` (the default), runs the site
matrix of its newest checkpoint on the CPU cores beside it (sim_twin.training.matrix_gate) and stops at the
first checkpoint that meets every site-matrix bar on every ``--gate-seeds`` seed. That checkpoint
is exported to ONNX (``--export``, default ``<log-dir>/throw<mode>.onnx``) with its model card
(sim_twin.training.model_card: command, config hash, GPU, wall time, matrices). If no checkpoint met the bars
when ``--iterations`` or ``--max-minutes`` run out, nothing is exported unless ``--export`` is given
(then the last checkpoint, its card saying the bars were not met). With ``--no-stop-at-bars`` the
training runs on to ``--iterations`` / ``--max-minutes``, the gate judging newer checkpoints, and the
newest checkpoint that met every bar is exported (its matrices feed the deploy comparison,
sim_twin.evaluation.matrix_compare); with ``--gate-compare-with`` the gate runs that comparison on its
seeds for every pass and the pass worse than the deployed policy on the fewest cells is exported.

The iterations run in one ``learn()`` of rsl_rl's runner with per-iteration callbacks
(sim_twin.training.runner.CallbackRunner; :class:`TrainingRun` says which), cut into chunks of
``--chunk`` iterations; after every chunk the checkpoint (policy, critic, optimiser state,
iteration count) is written to ``<log-dir>/checkpoint.pt`` with the resolved config, the training
curve (``curve.csv``, per-term reward means included) and the gate's state, so a run stopped at any
moment resumes with ``--resume <log-dir>/checkpoint.pt`` at the checkpoint's iteration count.
rsl_rl writes every iteration's losses, action std and per-term reward means (``Reward/<term>``)
to TensorBoard (``<log-dir>/tb``).

Exploration: the config's ``training.std_schedule`` caps the actor's learned action std at a
value that falls from ``start`` to ``end`` over ``iterations`` (exponentially), applied at the
start of every chunk; below the cap the std is learned (rsl_rl's GaussianDistribution).

Curriculum stage: the config's ``training.curriculum_stage`` (see :class:`CurriculumStage`; older
spelling ``training.randomization_stage``) changes ``env.randomization`` and/or ``env.rewards`` once,
at the first chunk boundary at or after its ``iteration``; the critic's privileged inputs are
normalised over the stage's ranges from the start (``env.privileged_ranges``), so their scale does
not change at the switch.
``training.gate_from_iteration`` (default 0) offers the gate only checkpoints from that iteration
on (a recipe that widens its randomisation judges the policies trained on the wide ranges).

Several GPUs: ``--gpus N`` re-launches the command under torchrun (one process per GPU, each with
``--num-envs`` environments, rsl_rl's multi-GPU mode: gradients all-reduced, rank 0 logs,
checkpoints and runs the gate; the runner broadcasts its stop decision to every rank).

The actor sees the ``policy`` group only (config ``runner.obs_groups.actor``, checked); the
critic the groups in ``runner.obs_groups.critic``: ["policy"] or, for the asymmetric
actor-critic, ["policy", "privileged"] (sim_twin.training.privileged). Resuming a checkpoint whose critic
had fewer inputs widens it without changing its values (sim_twin.training.critic_surgery).
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
from dataclasses import dataclass
from pathlib import Path

from runtime.entrypoint import module_main
from sim_twin.training.config import load_config, resolve_training

log = logging.getLogger(__name__)


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=["2d", "3d"], default="2d")
    parser.add_argument("--config", type=Path, default=None, help="default: sim_twin/configs/throw_<mode>.json")
    parser.add_argument("--num-envs", type=int, default=None, help="override the config's num_envs (per GPU)")
    parser.add_argument("--iterations", type=int, default=5000, help="most PPO iterations to run in this call")
    parser.add_argument("--chunk", type=int, default=25, help="iterations between checkpoints")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop after the chunk that passes this many minutes of this process's training")
    parser.add_argument("--max-run-minutes", type=float, default=None,
                        help="stop after the chunk at which the run's training wall time (the curve's wall_s, resumed "
                             "runs included) passes this many minutes")
    parser.add_argument("--log-dir", type=Path, default=None, help="default runs/throw_<mode>")
    parser.add_argument("--tb-dir", type=Path, default=None, help="TensorBoard dir (default <log-dir>/tb)")
    parser.add_argument("--resume", type=Path, default=None, help="checkpoint.pt to resume from")
    parser.add_argument("--seed", type=int, default=None,
                        help="training seed (default: the recipe's training.seed, that of the run its docs quote)")
    parser.add_argument("--keep-every", type=int, default=0, help="also keep checkpoint_<iter>.pt every N iterations")
    parser.add_argument("--export", type=Path, default=None,
                        help="ONNX to write (default with the gate: <log-dir>/throw<mode>.onnx once the bars are met)")
    parser.add_argument("--name", default=None, help="policy version name for the export (default: the file stem and iteration, throw2d-it600)")
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
    parser.add_argument("--gate-compare-with", default=None, metavar="MATRIX[,MATRIX...]",
                        help="the deployed policy's site matrices of the gate seeds, in their order (e.g. reports/site_matrix_2d.json,"
                             "reports/site_matrix_2d_seed1.json): every pass is compared with it by the paired deploy test and "
                             "--no-stop-at-bars exports the pass worse on the fewest cells (sim_twin.training.matrix_gate)")
    parser.add_argument("--gate-wait-minutes", type=float, default=0.0,
                        help="at the end, wait this long for a running matrix")
    parser.add_argument("--physics", choices=["jax", "warp"], default="jax", help="MJX implementation")
    parser.add_argument("--gpus", type=int, default=1, help="GPUs of this host to train on (torchrun, one process each)")


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


def set_release_bias(runner, bias: float) -> None:
    """Set the initial mean of the release flag (the actor's last output) to ``bias`` through the
    bias of the actor's output layer (rsl_rl's MLP, an ``nn.Sequential`` ending in ``nn.Linear``),
    and zero that output's weights, so that every observation starts with the same mean. Used when
    a run starts from scratch (config ``training.release_bias_init``, see
    sim_twin.training.config.TrainingSection).

    Raises:
        TypeError: the actor's network does not end in a linear layer.
    """
    import torch

    last = runner.alg.actor.mlp[-1]
    if not isinstance(last, torch.nn.Linear):
        raise TypeError(f"the actor's network ends in {type(last).__name__}, not a Linear layer")
    with torch.no_grad():
        last.weight[-1].zero_()
        last.bias[-1] = bias


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
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.gpus}", "-m", "sim_twin.training.train", *argv]
    log.info("launching %s", shlex.join(cmd))
    return subprocess.call(cmd)


@dataclass(frozen=True)
class _Process:
    """This process's place in the run: ``world`` processes (one per GPU under torchrun, else 1),
    its ``rank`` and the torch ``device`` it trains on ("cuda", "cuda:<local rank>" or "cpu")."""

    world: int
    rank: int
    device: str

    @property
    def main(self) -> bool:
        """Rank 0: the process that logs, checkpoints, runs the gate and exports."""
        return self.rank == 0

    @classmethod
    def here(cls) -> _Process:
        """From torchrun's environment (WORLD_SIZE, RANK, LOCAL_RANK; absent: one process). Under
        torchrun JAX is put on this process's GPU too (DLPack hands arrays over without a copy).

        Raises:
            ValueError: more than one process without CUDA GPUs.
        """
        import jax
        import torch

        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if torch.cuda.is_available():
            if world > 1:
                jax.config.update("jax_default_device", jax.devices("gpu")[local_rank])
                return cls(world, rank, f"cuda:{local_rank}")
            return cls(world, rank, "cuda")
        if world > 1:
            raise ValueError("more than one process needs CUDA GPUs")
        return cls(world, rank, "cpu")


class TrainingRun:
    """One process of ``slinger train`` (see the module docstring): the config read and checked,
    the MJX environments, rsl_rl's runner (:class:`sim_twin.training.runner.CallbackRunner`), the
    training curve and, on rank 0 with ``--gate``, the site-matrix gate. :meth:`train` runs one
    ``learn()`` of ``--iterations`` that the runner's callbacks end early where the bars or the
    time budget say; :meth:`finish` exports the result.

    The run is divided into chunks: a chunk ends where the iteration count is a multiple of
    ``--chunk`` and at the last iteration of the call. The runner writes ``checkpoint.pt`` at each
    chunk's end (its checkpoint interval and its last iteration), before the callbacks; three
    callbacks do the rest, in this order after every iteration (the runner calls them on every
    rank):

    * :meth:`_keep_checkpoint` (rank 0): ``checkpoint_<count>.pt`` every ``--keep-every``
      iterations;
    * :meth:`_end_chunk` (rank 0, at a chunk's end): the curve row, the gate (poll, offer the
      checkpoint) and the stop decision (bars met with ``--stop-at-bars``, time budget); returns
      True to stop, which the runner broadcasts to the other ranks;
    * :meth:`_start_next_chunk` (every rank, at a chunk's end that is not the call's last): the
      recipe's randomisation stage and std cap for the chunk that follows (:meth:`_start_chunk`,
      also called once before ``learn()``).

    Iterations are counted as done: the curve's ``iteration``, a checkpoint's ``iter`` and the
    names ``checkpoint_<count>.pt`` / ``throw2d-it<count>`` say how many iterations the policy
    was trained, and a resumed run continues at its checkpoint's count.

    Raises (constructor):
        ValueError: a config the run refuses (mode, training section, actor observation groups,
            randomisation), before anything is written.
    """

    def __init__(self, args: argparse.Namespace):
        from sim_twin.training import critic_surgery, model_card
        from sim_twin.training.curve import TrainingCurve
        from sim_twin.training.matrix_gate import MatrixGate
        from sim_twin.training.mjx_env import EnvConfig
        from sim_twin.training.runner import CallbackRunner
        from sim_twin.training.vec_env import MjxThrowVecEnv

        self.args = args
        self.stop_at_bars = getattr(args, "stop_at_bars", True)
        self.log_dir = args.log_dir or Path("runs") / f"throw_{args.mode}"
        cfg = self.cfg = load_config(args.mode, args.config)
        if args.num_envs:
            cfg["num_envs"] = args.num_envs
        self.training = resolve_training(cfg, args.seed)
        env_before, env_after = self.training.env_dicts(cfg["env"])
        self.env_after: dict = env_after
        env_cfg = EnvConfig.from_dict(env_before)
        if env_cfg.mode != args.mode:
            raise ValueError(f"config is for mode {env_cfg.mode}, asked for {args.mode}")
        actor_groups = cfg["runner"].get("obs_groups", {}).get("actor", ["policy"])
        if actor_groups != ["policy"]:
            raise ValueError(f"runner.obs_groups.actor must be ['policy'] (the exported policy's input), not {actor_groups}")
        proc = self.proc = _Process.here()
        physics = getattr(args, "physics", "jax")
        if proc.main:
            log.info("training %s on %s: %d process(es) x %d envs, physics %s", args.mode, proc.device, proc.world,
                     cfg["num_envs"], physics)
            self.log_dir.mkdir(parents=True, exist_ok=True)
            (self.log_dir / "config.json").write_text(json.dumps(cfg, indent=2))

        seed = self.training.seed or 0  # resolve_training refuses a config without one
        # The training seed fixes the networks' initial weights and PPO's minibatch order as well as
        # the environments: rsl_rl draws both from torch's global generator, which nothing seeded, so
        # two runs "with the same seed" started from different networks.
        import torch

        torch.manual_seed(seed + 1000 * proc.rank)
        self._tf32_before = torch.backends.cuda.matmul.allow_tf32  # a process-wide flag: run() puts it back
        if self.training.tf32_matmul:  # rollout and update alike (TrainingSection); no effect on the CPU
            torch.backends.cuda.matmul.allow_tf32 = True  # (cuDNN's TF32 is on by default; the networks have no convolutions)
            log.info("TF32 matrix products on")
        self.env = MjxThrowVecEnv(env_cfg, cfg["num_envs"], seed=seed + 1000 * proc.rank, device=proc.device, impl=physics)
        self.tb_dir = (args.tb_dir or self.log_dir / "tb") if proc.main else None
        self.runner = CallbackRunner(self.env, copy.deepcopy(cfg["runner"]), log_dir=str(self.tb_dir) if self.tb_dir else None,
                                     device=proc.device, callbacks=[self._keep_checkpoint, self._end_chunk, self._start_next_chunk],
                                     checkpoint_dir=str(self.log_dir), checkpoint_name="checkpoint.pt", save_interval=max(args.chunk, 1),
                                     per_iteration_syncs=self.training.per_iteration_syncs)
        self.curve = TrainingCurve.load_or_new(self.log_dir / "curve.csv")
        self._wall_offset = self.curve.last_wall_s()
        if args.resume:
            critic_surgery.resume(self.runner, args.resume, proc.device)  # widens an older critic (privileged inputs)
            log.info("resumed from %s at iteration %d", args.resume, self.runner.current_learning_iteration)
        elif self.training.release_bias_init is not None:
            set_release_bias(self.runner, self.training.release_bias_init)

        self.accelerators = (model_card.record_accelerator(self.log_dir, self.runner.current_learning_iteration,
                                                           model_card.accelerator(), proc.world) if proc.main else [])
        self._start = time.time()
        self.gate = None
        if getattr(args, "gate", False) and proc.main:
            self.gate = MatrixGate(self.log_dir / "matrices", args.mode, [int(s) for s in str(args.gate_seeds).split(",")],
                                   throws=args.gate_throws, targets=args.gate_targets, workers=args.gate_workers,
                                   clock=self.clock, judge_after_pass=not self.stop_at_bars,
                                   compare_with=[Path(x) for x in str(args.gate_compare_with).split(",")]
                                   if getattr(args, "gate_compare_with", None) else None)
            if args.resume:
                self.gate.resume_pending()  # the candidate under test when the run stopped, from its seed
            self.gate.watch()  # verdicts are recorded when each matrix ends, not at the next checkpoint
        self.passed: dict | None = self.gate.passed if self.gate else None
        self.stop_reason = "iterations"
        self._staged = False
        self._chunks = 0
        self._end_it = self.runner.current_learning_iteration  # the count this call trains to (train())
        self._chunk_from, self._chunk_t = self._end_it, time.time()  # the running chunk's first count and start time

    def restore_process_settings(self) -> None:
        """Put back what the run set for the whole process (``training.tf32_matmul``'s torch flag),
        so that a caller that trains in its own process (a test, a notebook) gets it as it was."""
        import torch

        torch.backends.cuda.matmul.allow_tf32 = self._tf32_before

    def clock(self) -> float:
        """Training wall time of the run, s, resumed runs included (the curve's last wall_s on)."""
        return self._wall_offset + time.time() - self._start

    @property
    def _bars_end_it(self) -> bool:
        return bool(self.passed) and self.stop_at_bars

    def train(self) -> None:
        """``--iterations`` PPO iterations from the checkpoint's count on (one ``learn()`` call),
        fewer where rank 0 decides to stop at a chunk's end (bars met, time budget); the runner
        broadcasts that decision to every rank."""
        import torch

        runner, start = self.runner, self.runner.current_learning_iteration
        self._end_it = start + max(self.args.iterations, 0)
        if self._end_it > start and not self._bars_end_it:
            self._start_chunk(start)
            runner.learn(num_learning_iterations=self._end_it - start)
        if self.proc.world > 1:
            torch.distributed.destroy_process_group()  # rsl_rl's runner made it; NCCL warns at exit otherwise

    def _chunk_ends(self, done: int) -> bool:
        """Whether a chunk ends once ``done`` iterations are done (a multiple of ``--chunk``, or
        the last iteration of this call)."""
        return done % max(self.args.chunk, 1) == 0 or done >= self._end_it

    def _start_chunk(self, done: int) -> None:
        """Before the chunk that starts after ``done`` iterations: apply the curriculum stage once
        the recipe's stage is reached, cap the std at the schedule's value for ``done``, set PPO's
        KL aim from the desired-KL stage once reached, and start the chunk's throw statistics and
        timer."""
        from sim_twin.training.mjx_env import EnvConfig

        stage, schedule = self.training.curriculum_stage, self.training.std_schedule
        if stage and not self._staged and done >= stage.iteration:
            self.env.reconfigure(EnvConfig.from_dict(self.env_after))
            self._staged = True
            log.info("curriculum stage at iteration %d: randomisation %s, rewards %s", done, stage.randomization, stage.rewards)
        if schedule:
            apply_std_cap(self.runner, schedule.cap(done), schedule.release_floor)
        kl_stage = self.training.desired_kl_stage
        if kl_stage and done >= kl_stage.iteration and self.runner.alg.desired_kl != kl_stage.desired_kl:
            self.runner.alg.desired_kl = kl_stage.desired_kl
            log.info("desired KL stage at iteration %d: PPO's adaptive learning rate now aims at %g", done, kl_stage.desired_kl)
        self.env.reset_stats()
        self._chunk_from, self._chunk_t = done, time.time()

    def _start_next_chunk(self, runner, it: int) -> bool:
        """Callback: after iteration ``it`` ends a chunk that is not the call's last, start the
        next (:meth:`_start_chunk`). Never stops the run."""
        done = it + 1
        if self._chunk_ends(done) and done < self._end_it:
            self._start_chunk(done)
        return False

    def _keep_checkpoint(self, runner, it: int) -> bool:
        """Callback, rank 0: with ``--keep-every N``, also keep ``checkpoint_<count>.pt`` when the
        iteration count is a multiple of N. Never stops the run."""
        done = it + 1
        if self.proc.main and self.args.keep_every and done % self.args.keep_every == 0:
            runner.save(str(self.log_dir / f"checkpoint_{done}.pt"))
        return False

    def _end_chunk(self, runner, it: int) -> bool:
        """Callback, rank 0, after iteration ``it`` where it ends a chunk: curve row, gate and the
        stop decision; returns True to stop (bars met with ``--stop-at-bars``, time budget)."""
        done = it + 1
        if not self.proc.main or not self._chunk_ends(done):
            return False
        if self.proc.device.startswith("cuda"):
            import torch

            torch.cuda.synchronize()
        self._chunks += 1
        self._record(done, done - self._chunk_from, time.time() - self._chunk_t)
        if self.gate:
            self.passed = self.gate.poll()
            self._offer_to_gate(done)
        if self._bars_end_it:
            self.stop_reason = "bars met"
        elif self.args.max_minutes and (time.time() - self._start) / 60.0 > self.args.max_minutes:
            self.stop_reason = "time budget"
        elif getattr(self.args, "max_run_minutes", None) and self.clock() / 60.0 > self.args.max_run_minutes:
            self.stop_reason = "time budget"
        return self.stop_reason != "iterations"

    def _record(self, it: int, n: int, chunk_s: float) -> None:
        """Append the curve row of iteration count ``it`` (a chunk of ``n`` iterations in
        ``chunk_s`` s) and save the curve (``checkpoint.pt`` is the runner's)."""
        runner, cfg = self.runner, self.cfg
        stats = self.env.read_stats()
        std = current_std(runner)
        rewards, lengths = runner.logger.rewbuffer, runner.logger.lenbuffer
        self.curve.append(
            iteration=it,
            wall_s=self.clock(),
            mean_reward=statistics.mean(rewards) if rewards else float("nan"),
            mean_episode_length=statistics.mean(lengths) if lengths else float("nan"),
            action_std=std,
            control_steps_per_s=cfg["num_envs"] * self.proc.world * cfg["runner"]["num_steps_per_env"] * n / chunk_s,
            **stats,
            **self.env.read_term_means(),
        )
        self.curve.save()
        log.info("checkpoint at iteration %d (%.1f min): %s, std %.3f", it, self.clock() / 60, stats, std)

    def _offer_to_gate(self, it: int) -> None:
        """Export the checkpoint of iteration count ``it`` and hand it to the gate, unless the
        bars are already met (and end the run), the gate is busy, this is not a ``--gate-every``-th
        chunk or ``it`` is before the recipe's ``gate_from_iteration``."""
        assert self.gate is not None
        if self._bars_end_it or self.gate.busy or self._chunks % max(self.args.gate_every, 1) != 0:
            return
        if it < self.training.gate_from_iteration:
            return
        cand = self.log_dir / "candidates" / f"checkpoint_{it}.pt"
        cand.parent.mkdir(exist_ok=True)
        self.runner.save(str(cand))
        onnx = _export(cand, self.cfg, cand.with_suffix(".onnx"), f"throw{self.args.mode}-it{it}")
        self.gate.submit(it, onnx, self.clock())

    def finish(self) -> Path | None:
        """Rank 0: wait for a running matrix (``--gate-wait-minutes``), stop the gate, plot the curve
        and export the checkpoint that met the bars (with ``--no-stop-at-bars`` the newest such, or with
        ``--gate-compare-with`` the one worse than the deployed policy on the fewest cells: matrix_gate.choose_pass,
        among the passes whose checkpoint is here: MatrixGate.exportable_passes),
        else, where ``--export`` asks, the last one with a card saying the bars were not met.
        Returns the ONNX written or None. Other ranks return None at once.

        Raises:
            FileNotFoundError: the checkpoint of the candidate that met the bars is not in the run
                directory (a run resumed from a state that carried none of its passes' checkpoints)."""
        if not self.proc.main:
            return None
        from sim_twin.training import model_card
        from sim_twin.training.matrix_gate import choose_pass

        args, gate = self.args, self.gate
        if gate and not self._bars_end_it and args.gate_wait_minutes > 0:
            log.info("waiting up to %.1f min for the running site matrix", args.gate_wait_minutes)
            self.passed = gate.wait(args.gate_wait_minutes * 60)
        if gate:
            gate.stop()
            if gate.passes and not self.stop_at_bars:
                here = gate.exportable_passes()
                if len(here) < len(gate.passes):
                    log.warning("passes without their checkpoint here (a resume state without them), not chosen: iterations %s",
                                [p["iteration"] for p in gate.passes if p not in here])
                # the newest that met every bar, or the fewest cells worse than the deployed; all where none is here
                self.passed = choose_pass(here or gate.passes)
        passed = self.passed
        log.info("training stopped (%s) at iteration %d after %.1f min", "bars met" if self._bars_end_it else self.stop_reason,
                 self.runner.current_learning_iteration, self.clock() / 60)
        self.curve.plot(self.log_dir / "training_curve.png",
                        title=f"PPO, {args.mode}, {self.proc.world} x {self.cfg['num_envs']} envs")
        out = args.export or (self.log_dir / f"throw{args.mode}.onnx" if passed else None)
        if not out:
            return None
        ckpt = self.log_dir / "checkpoint.pt"
        if passed and gate:  # the candidate's own checkpoint, where a resumed run's state put it
            ckpt = gate.locate(passed["onnx"]).with_suffix(".pt")
            if not ckpt.exists():
                raise FileNotFoundError(f"the checkpoint that met the bars (iteration {passed['iteration']}) is not there: "
                                        f"{ckpt} (a resume state without it); the verdicts are in {gate.state_path}, "
                                        f"the run's newest checkpoint in {self.log_dir / 'checkpoint.pt'}")
        it = passed["iteration"] if passed else self.runner.current_learning_iteration
        name = args.name or f"{out.stem}-it{it}"  # the Policies page lists versions by name
        return _export(ckpt, self.cfg, out, name, command=getattr(args, "command", None), card=dict(
            iteration=it, gpus=model_card.describe_accelerators(self.accelerators, it),
            train_wall_s=passed["train_wall_s"] if passed else self.clock(),
            verdict_wall_s=passed["verdict_wall_s"] if passed else None, world_size=self.proc.world,
            matrices=[r.__dict__ for r in gate.results if r.iteration == it] if gate else [], bars_met=bool(passed)))


def run(args: argparse.Namespace) -> int:
    """Train (:class:`TrainingRun`); returns 0. Raises ValueError on configuration errors, before
    anything is written."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    training = TrainingRun(args)
    try:
        training.train()
        training.finish()
    finally:
        training.restore_process_settings()
    return 0


def _export(checkpoint: Path, cfg: dict, out: Path, name: str, card: dict | None = None, command: str | None = None) -> Path:
    """Export ``checkpoint`` to ONNX + manifest; with ``card`` also write the model card (naming
    ``command``, by default this process's command line) and put it into the manifest's
    ``training`` section."""
    from sim_twin.training import model_card
    from sim_twin.training.export import export_checkpoint

    export_checkpoint(checkpoint, cfg, out, name=name)
    if card is not None:
        card = {"gpus": model_card.accelerator(), **card}  # the run's own record where it passes one (TrainingRun.finish)
        model_card.attach_card(out, cfg, command or shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]), card)
    return out


def main(argv: list[str] | None = None) -> int:
    """``slinger train`` / ``python -m sim_twin.training.train``: with ``--gpus N`` > 1 (and not already a
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
