"""rsl_rl's on-policy runner with per-iteration callbacks that may end ``learn()`` early, and a
checkpoint name, folder and interval of the caller's choosing.

:class:`CallbackRunner` is ``rsl_rl.runners.OnPolicyRunner`` of rsl-rl-lib 5.5.1
(``rsl_rl/runners/on_policy_runner.py``) with its ``learn()`` loop copied and three changes, each
marked ``# CHANGE`` in the copy, written to be proposed upstream as they stand:

1. **Callbacks** (``callbacks``): after every iteration (rollout, update, log, periodic
   checkpoint) each callback is called as ``callback(runner, it)`` on every rank, ``it`` being
   the index of the iteration that just ended (rsl_rl's loop variable, the TensorBoard step).
   A callback returns True to end ``learn()`` after this iteration (anything else: go on). Every
   callback runs each iteration, also after one has asked to stop. Under multi-GPU training
   (``WORLD_SIZE`` > 1) rank 0's decision is broadcast and every rank follows it, so the ranks
   leave the loop together (their gradient all-reduces stay matched). rsl_rl 5.5.1 has no such
   hook: ``learn(n)`` always runs n iterations, so schedules, curricula, gates and early stops
   had to call ``learn()`` in pieces and patch the runner in between.
2. **Iteration count**: ``current_learning_iteration`` is the number of iterations done (the
   index of the next one), set after each iteration, and a checkpoint stores that number as
   ``iter``. In 5.5.1 it is the index of the last iteration done, so a second ``learn()`` call,
   or one after ``load()``, runs that index again (its TensorBoard step and checkpoint name
   appear twice). Here consecutive calls and resumed runs continue the numbering without
   repeating or skipping one (``load()`` is rsl_rl's: it sets the count from ``iter``).
3. **Checkpoints** (``checkpoint_dir``, ``checkpoint_name``, ``save_interval``): written to
   ``checkpoint_dir`` (default the logger's log_dir, as rsl_rl) under ``checkpoint_name``
   formatted with ``it`` = the iteration count it stores (default ``model_{it}.pt``; a name
   without ``{it}`` is overwritten each time) whenever the count is a multiple of
   ``save_interval`` (default the config's ``save_interval``; 0: none on the way) and after the
   last iteration, before the callbacks see it; at the end of ``learn()`` only if a callback
   stopped the loop at an iteration not yet written (5.5.1 writes the last one at the end, twice
   when the interval has just written it).
   As in rsl_rl only a process with a log writer (rank 0 with a log_dir) writes checkpoints.
4. **Host syncs** (``per_iteration_syncs``, default False: rsl_rl's loop as it is): rsl_rl's rollout
   waits for the GPU at every environment step, in ``check_nan`` (``tensor.any()`` in an ``if``, per
   observation group, rewards and dones) and in the logger's episode bookkeeping (``nonzero()``,
   ``.cpu()``), so the host cannot queue the next step's work while the GPU runs this one. With
   ``per_iteration_syncs`` the NaN flags and the finished episodes' returns and lengths stay on the
   device (:class:`DeviceEpisodeLog`) and are read once after the rollout, before the update: a NaN
   raises the same ValueError one rollout later than rsl_rl would (before any update uses it), and
   the logger's return and length buffers (its last 100 finished episodes, in rsl_rl's order) hold
   the same values (tests/test_training_runner.py). RND's intrinsic rewards are not supported then.

Everything else (the constructor, ``save``, ``load``, the logger, multi-GPU set-up, exports) is
rsl_rl's. The copied loop is BSD-3-Clause, Copyright (c) 2021-2026, ETH Zurich and NVIDIA
CORPORATION (rsl-rl-lib's licence); keep it in step with the installed rsl_rl when it is updated
(tests/test_training_runner.py runs it on a toy environment).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable

import torch
from rsl_rl.env import VecEnv
from rsl_rl.runners import OnPolicyRunner
from rsl_rl.utils import check_nan

IterationCallback = Callable[["CallbackRunner", int], "bool | None"]
"""``callback(runner, it) -> bool | None``: called after iteration ``it`` (0-based index) on every
rank; True ends ``learn()`` after it (under multi-GPU, rank 0's answer counts)."""


class CallbackRunner(OnPolicyRunner):
    """OnPolicyRunner (rsl-rl-lib 5.5.1) with per-iteration callbacks, an iteration count that
    continues across ``learn()`` calls and resumes, and a checkpoint name / folder / interval (see
    the module docstring).

    Args:
        env, train_cfg, log_dir, device: as ``OnPolicyRunner``.
        callbacks: called in this order after every iteration (:data:`IterationCallback`); the
            list stays open (``runner.callbacks.append``).
        checkpoint_dir: folder of the checkpoints; None: the logger's log_dir (as rsl_rl).
        checkpoint_name: file name, formatted with ``it`` (the iteration count it stores).
        save_interval: write a checkpoint when the iteration count is a multiple of this; None:
            ``train_cfg["save_interval"]``; 0: only the last iteration's.
        per_iteration_syncs: wait for the GPU once per rollout instead of at every step (module
            docstring, change 4).

    Raises:
        ValueError: a negative ``save_interval``; ``per_iteration_syncs`` with RND; OnPolicyRunner's
            errors.
    """

    current_learning_iteration: int
    """Iterations done (the index of the next one); a checkpoint stores it as ``iter``."""

    def __init__(self, env: VecEnv, train_cfg: dict, log_dir: str | None = None, device: str = "cpu", *,
                 callbacks: Iterable[IterationCallback] = (), checkpoint_dir: str | None = None,
                 checkpoint_name: str = "model_{it}.pt", save_interval: int | None = None,
                 per_iteration_syncs: bool = False) -> None:
        if per_iteration_syncs and train_cfg["algorithm"].get("rnd_cfg"):
            raise ValueError("per_iteration_syncs does not support RND (its intrinsic rewards are logged per step)")
        super().__init__(env, train_cfg, log_dir=log_dir, device=device)
        self.per_iteration_syncs = per_iteration_syncs
        self.callbacks: list[IterationCallback] = list(callbacks)
        self.checkpoint_dir = checkpoint_dir
        self.checkpoint_name = checkpoint_name
        self.save_interval = int(train_cfg["save_interval"] if save_interval is None else save_interval)
        if self.save_interval < 0:
            raise ValueError(f"save_interval must be >= 0, not {self.save_interval}")

    def checkpoint_path(self, it: int) -> str:
        """Path of the checkpoint that stores iteration count ``it``.

        Raises:
            ValueError: neither ``checkpoint_dir`` nor a logger log_dir is set.
        """
        folder = self.checkpoint_dir or self.logger.log_dir
        if folder is None:
            raise ValueError("no checkpoint_dir and no log_dir: nowhere to write checkpoints")
        return os.path.join(folder, self.checkpoint_name.format(it=it))

    def learn(self, num_learning_iterations: int, init_at_random_ep_len: bool = False) -> None:
        """Run ``num_learning_iterations`` iterations from ``current_learning_iteration`` on, fewer
        when a callback ends the loop (module docstring)."""
        # --- copied from rsl_rl 5.5.1 OnPolicyRunner.learn; changes marked CHANGE ---------------
        # Randomize initial episode lengths (for exploration)
        if init_at_random_ep_len:
            self.env.episode_length_buf = torch.randint_like(
                self.env.episode_length_buf, high=int(self.env.max_episode_length)
            )

        # Start learning
        obs = self.env.get_observations().to(self.device)
        self.alg.train_mode()  # switch to train mode (for dropout for example)

        # Ensure all parameters are in-synced
        if self.is_distributed:
            print(f"Synchronizing parameters for rank {self.gpu_global_rank}...")
            self.alg.broadcast_parameters()

        # Initialize the logging writer
        self.logger.init_logging_writer()

        # Start training
        start_it = self.current_learning_iteration
        total_it = start_it + num_learning_iterations
        saved_it = None  # CHANGE (3): the count whose checkpoint was written last
        for it in range(start_it, total_it):
            start = time.time()
            # CHANGE (4): the NaN flags and the episode bookkeeping on the device, read after the rollout
            episodes = DeviceEpisodeLog(self.logger, self.cfg["num_steps_per_env"]) if self.per_iteration_syncs else None
            # Rollout
            with torch.inference_mode():
                for _ in range(self.cfg["num_steps_per_env"]):
                    # Sample actions
                    actions = self.alg.act(obs)
                    # Step the environment
                    obs, rewards, dones, extras = self.env.step(actions.to(self.env.device))
                    # Check for NaN values from the environment
                    if self.cfg.get("check_for_nan", True):
                        if episodes is not None:  # CHANGE (4)
                            episodes.note_nan(obs, rewards, dones)
                        else:
                            check_nan(obs, rewards, dones)
                    # Move to device
                    obs, rewards, dones = (obs.to(self.device), rewards.to(self.device), dones.to(self.device))
                    # Process the step
                    self.alg.process_env_step(obs, rewards, dones, extras)
                    # Extract intrinsic rewards if RND is used (only for logging)
                    intrinsic_rewards = self.alg.intrinsic_rewards if self.cfg["algorithm"].get("rnd_cfg") else None
                    # Book keeping
                    if episodes is not None:  # CHANGE (4)
                        episodes.step(rewards, dones, extras)
                    else:
                        self.logger.process_env_step(rewards, dones, extras, intrinsic_rewards)

                if episodes is not None:  # CHANGE (4): the rollout's one wait, before the update
                    episodes.finish()

                stop = time.time()
                collect_time = stop - start
                start = stop

                # Compute returns
                self.alg.compute_returns(obs)

            # Update policy
            loss_dict = self.alg.update()

            stop = time.time()
            learn_time = stop - start
            self.current_learning_iteration = it + 1  # CHANGE (2): iterations done (5.5.1: it)

            # Log information
            self.logger.log(
                it=it,
                start_it=start_it,
                total_it=total_it,
                collect_time=collect_time,
                learn_time=learn_time,
                loss_dict=loss_dict,
                learning_rate=self.alg.learning_rate,
                action_std=self.alg.get_policy().output_std,
                rnd_weight=self.alg.rnd.weight if self.cfg["algorithm"].get("rnd_cfg") else None,
            )

            # Save model
            # CHANGE (3): checkpoint_path / save_interval on the iteration count, and the last iteration's
            # here, before the callbacks (5.5.1: log_dir/model_{it}.pt when it % cfg["save_interval"] == 0)
            done = self.current_learning_iteration
            if self.logger.writer is not None and ((self.save_interval and done % self.save_interval == 0) or done == total_it):
                self.save(self.checkpoint_path(done))
                saved_it = done

            # CHANGE (1): the callbacks, every one of them, then rank 0's stop decision on every rank
            if self._callbacks_stop(it):
                break

        # Save the final model after training and stop the logging writer
        if self.logger.writer is not None:
            if saved_it != self.current_learning_iteration:  # CHANGE (3): not twice (stopped by a callback, or no iteration)
                self.save(self.checkpoint_path(self.current_learning_iteration))
            self.logger.stop_logging_writer()
        # --- end of the copy ---------------------------------------------------------------------

    def _callbacks_stop(self, it: int) -> bool:
        """Call every callback after iteration ``it``; True if the loop is to end (rank 0's
        answer, broadcast to every rank under multi-GPU training)."""
        stop = False
        for callback in self.callbacks:
            stop = bool(callback(self, it)) or stop
        if self.is_distributed:  # every rank takes part, whatever callbacks it has
            flag = torch.tensor([1.0 if stop else 0.0], device=self.device)
            torch.distributed.broadcast(flag, src=0)
            stop = bool(flag.item() > 0)
        return stop


class DeviceEpisodeLog:
    """One rollout's episode bookkeeping for rsl_rl's Logger without waiting for the GPU at each
    step (CallbackRunner change 4). Per step it adds the rewards to the logger's running sums
    (``cur_reward_sum``, ``cur_episode_length``; shape (num_envs,)) and records, where an episode
    ended, its return and length into (steps, num_envs) device buffers, then zeroes the sums there,
    all with masked tensor operations; the NaN checks of rsl_rl's ``check_nan`` accumulate into one
    device flag. :meth:`finish` reads both once and extends the logger's ``rewbuffer`` and
    ``lenbuffer`` with the finished episodes in rsl_rl's order (by step, then by environment index,
    as ``nonzero()`` orders them), so the buffers end as rsl_rl's per-step bookkeeping leaves them.

    Args:
        logger: rsl_rl's Logger (``runner.logger``); nothing is recorded when it has no writer
            (as rsl_rl: only the logging rank keeps episode statistics).
        steps: the rollout's steps per environment (``num_steps_per_env``).
    """

    def __init__(self, logger, steps: int) -> None:
        self.logger = logger
        self.i = 0
        self.nan: torch.Tensor | None = None
        self.returns: torch.Tensor | None = None
        self.lengths: torch.Tensor | None = None
        """Per step and environment: the return and length of the episode that ended there, else 0
        (a finished episode lasted at least one step: its length marks it)."""
        if logger.writer is not None:
            self.returns = logger.cur_reward_sum.new_zeros((steps, logger.cur_reward_sum.shape[0]))
            self.lengths = logger.cur_episode_length.new_zeros((steps, logger.cur_episode_length.shape[0]))

    def note_nan(self, obs, rewards: torch.Tensor, dones: torch.Tensor) -> None:
        """Accumulate whether any observation group, reward or done of this step is NaN (no wait)."""
        flags = [torch.isnan(t).any() for t in (*obs.values(), rewards, dones)]
        flag = torch.stack(flags).any()
        self.nan = flag if self.nan is None else self.nan | flag

    def step(self, rewards: torch.Tensor, dones: torch.Tensor, extras: dict) -> None:
        """The logger's ``process_env_step`` without RND, its per-episode part kept on the device.
        Shapes: rewards, dones (num_envs,)."""
        lg = self.logger
        if lg.writer is None:
            return
        if "episode" in extras:
            lg.ep_extras.append(extras["episode"])
        elif "log" in extras:
            lg.ep_extras.append(extras["log"])
        lg.cur_reward_sum += rewards
        lg.cur_episode_length += 1
        ended = dones > 0
        assert self.returns is not None and self.lengths is not None
        self.returns[self.i] = torch.where(ended, lg.cur_reward_sum, 0.0)
        self.lengths[self.i] = torch.where(ended, lg.cur_episode_length, 0.0)
        lg.cur_reward_sum.masked_fill_(ended, 0)
        lg.cur_episode_length.masked_fill_(ended, 0)
        self.i += 1

    def finish(self) -> None:
        """Read the rollout's NaN flag and finished episodes (one device->host copy each).

        Raises:
            ValueError: an observation, reward or done of the rollout was NaN (rsl_rl's check_nan's
                condition; which step is not known here).
        """
        if self.nan is not None and bool(self.nan):
            raise ValueError("The environment returned NaN values (observations, rewards or dones) in this rollout. "
                             "This usually indicates a bug in the environment's step() or reset() function.")
        if self.returns is None or self.lengths is None or self.i == 0:
            return
        lengths = self.lengths[: self.i].cpu().numpy().ravel()
        ended = lengths > 0
        keep = self.logger.rewbuffer.maxlen or len(lengths)
        self.logger.rewbuffer.extend(self.returns[: self.i].cpu().numpy().ravel()[ended][-keep:].tolist())
        self.logger.lenbuffer.extend(lengths[ended][-keep:].tolist())
