"""rsl_rl VecEnv adapter around the batched MJX throwing environment.

Arrays cross between JAX and PyTorch by DLPack (no copy on the same device). Observations are
returned as a TensorDict with two groups: ``policy`` (runtime.observation, what the machine
measures) and ``privileged`` (sim_twin.training.privileged: the episode's randomised parameters and the
true passive joint state, for an asymmetric critic). rsl_rl picks the groups of actor and critic
by the config's ``runner.obs_groups``; the actor must keep ["policy"] (it is what is exported).

Every step returns in ``extras["log"]`` the mean over environments of each scaled reward term
(``Reward/<term>``, sim_twin.training.rewards; environments whose state diverged this step, whose terms
are not finite and whose reward is the failure reward, are left out of these means and counted in
``Throw/diverged_per_done``) and the throw statistics (``Throw/...``); rsl_rl's logger
averages them over the iteration and writes them to TensorBoard. They stay on the device (no
host synchronisation per step); :meth:`read_stats` copies the accumulated sums once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore
from sim_twin.training.rewards import REWARD_TERMS, diverged


def _to_torch(x) -> torch.Tensor:
    return torch.from_dlpack(x)


def _to_jax(t: torch.Tensor):
    return jax.dlpack.from_dlpack(t.contiguous())


class MjxThrowVecEnv(VecEnv):
    """``num_envs`` MJX throwing environments stepped in lockstep.

    Args:
        cfg: environment config.
        num_envs: number of parallel environments.
        seed: PRNG seed.
        device: torch device of the returned tensors ("cuda" or "cpu"); must be where JAX runs.
        impl: MJX implementation, "jax" or "warp".
        reset_slots: see :class:`sim_twin.training.mjx_env.ThrowEnvCore` (None: reset the whole batch each
            step; a fraction: reset only the finished environments).
        unroll_substeps, joint_limits, graph_mode: see :class:`sim_twin.training.mjx_env.ThrowEnvCore`.

    Shapes: observations ``policy`` (num_envs, observation_size(mode, cfg.history_steps)), ``privileged``
    (num_envs, PRIVILEGED_SIZE); actions (num_envs, num_actions(mode));
    rewards and dones (num_envs,).
    """

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int = 0, device: str = "cpu", impl: str = "jax",
                 reset_slots: float | None = None, unroll_substeps: bool = False, joint_limits: bool = False,
                 graph_mode: str | None = None):
        self._build(ThrowEnvCore(cfg, impl=impl, reset_slots=reset_slots, unroll_substeps=unroll_substeps,
                                 joint_limits=joint_limits, graph_mode=graph_mode))
        self.num_envs = num_envs
        self.num_actions = self.core.num_act
        self.max_episode_length = cfg.max_steps
        self.device = device
        keys = jax.random.split(jax.random.PRNGKey(seed), num_envs)
        self.state, obs = self._reset(keys)
        self._obs = obs
        self._priv = self._privileged(self.state)
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.log_keys = [f"Reward/{k}" for k in REWARD_TERMS] + ["Throw/landed_per_done", "Throw/failed_per_done", "Throw/impact_err_m",
                                                                 "Throw/diverged_per_done"]
        self.reset_stats()

    def reconfigure(self, cfg: EnvConfig) -> None:
        """Step with another config from now on (a curriculum stage, sim_twin.training.train): episodes in
        flight keep what they drew, new episodes draw from ``cfg``. The state's layout does not
        depend on the config, so the batch carries on; the step is compiled again.

        Raises:
            ValueError: ``cfg`` is for another mode or episode length.
        """
        if cfg.mode != self.core.mode or cfg.max_steps != self.max_episode_length:
            raise ValueError(f"reconfigure keeps mode and episode length ({self.core.mode}, {self.max_episode_length} steps); "
                             f"got {cfg.mode}, {cfg.max_steps}")
        c = self.core
        self._build(ThrowEnvCore(cfg, impl=c.impl, reset_slots=c.reset_slots, unroll_substeps=c.unroll_substeps,
                                 joint_limits=c.joint_limits, graph_mode=c.graph_mode))
        self._priv = self._privileged(self.state)

    def _build(self, core: ThrowEnvCore) -> None:
        """Take ``core`` and compile the batched reset, step and privileged observation on it."""
        self.core = core
        self.cfg = {"env": core.cfg.as_dict()}
        self._reset = jax.jit(jax.vmap(core.reset))
        self._step = jax.jit(self._batched_step)
        self._privileged = jax.jit(jax.vmap(core.privileged))

    def _batched_step(self, state, actions):
        """step_autoreset_batch plus the per-step means that are logged, in one jit."""
        state, obs, rew, done, tout, info = self.core.step_autoreset_batch(state, actions)
        landed = info["landed"]
        n_done, n_landed = jnp.sum(done), jnp.sum(landed)
        err_sum = jnp.sum(jnp.where(landed, info["impact_err_m"], 0.0))
        n_failed = jnp.sum(info["failed"])
        sums = jnp.stack([n_done, n_landed, n_failed, err_sum]).astype(jnp.float32)
        terms = info["reward_terms"]
        # a diverged state's reward is the failure reward (rewards.total_reward) and its distance terms are
        # NaN: the term means leave it out and count it instead
        gone = diverged(terms)
        n_kept = jnp.maximum(jnp.sum(~gone), 1)
        log = jnp.stack(
            [jnp.sum(jnp.where(gone, 0.0, terms[k])) / n_kept for k in REWARD_TERMS]
            + [n_landed / jnp.maximum(n_done, 1), n_failed / jnp.maximum(n_done, 1), err_sum / jnp.maximum(n_landed, 1),
               jnp.sum(gone) / jnp.maximum(n_done, 1)]
        ).astype(jnp.float32)
        return state, obs, rew, done, tout, self.core.privileged_batch(state), sums, log

    def reset_stats(self) -> None:
        """Start accumulating throw statistics afresh (see read_stats)."""
        self._sums = torch.zeros(4, dtype=torch.float64, device=self.device)
        self._log_sum = torch.zeros(len(self.log_keys), dtype=torch.float64, device=self.device)
        self._log_n = 0

    def read_term_means(self) -> dict[str, float]:
        """Mean over the steps since reset_stats() of each scaled reward term's mean over the
        environments whose state did not diverge: {"reward_<term>": value}."""
        means = (self._log_sum / max(self._log_n, 1)).cpu().tolist()
        return {"reward_" + k.split("/", 1)[1]: v for k, v in zip(self.log_keys, means) if k.startswith("Reward/")}

    def read_stats(self) -> dict[str, float]:
        """Fractions of finished episodes that landed / failed and the mean impact error of the
        landings since reset_stats() (one device->host copy)."""
        done, landed, failed, err_sum = (float(x) for x in self._sums.cpu())
        return {
            "landed_per_done": landed / max(done, 1.0),
            "failed_per_done": failed / max(done, 1.0),
            "impact_err_m": err_sum / max(landed, 1.0),
        }

    def _t(self, x) -> torch.Tensor:
        return _to_torch(x).to(self.device)

    def get_observations(self) -> TensorDict:
        obs = {"policy": self._t(self._obs), "privileged": self._t(self._priv)}
        return TensorDict(obs, batch_size=[self.num_envs], device=self.device)

    def step(self, actions: torch.Tensor):
        """Shapes: actions (num_envs, num_actions) -> (obs TensorDict, rewards (num_envs,),
        dones (num_envs,) long, extras {"time_outs", "log"})."""
        a = _to_jax(actions.detach().to(torch.float32))
        self.state, self._obs, rew, done, tout, self._priv, sums, log = self._step(self.state, a)
        self.episode_length_buf = self._t(self.state.step).to(torch.long)
        self._sums += self._t(sums)
        log_t = self._t(log)
        self._log_sum += log_t
        self._log_n += 1
        extras = {"time_outs": self._t(tout).to(torch.float32), "log": {k: log_t[i] for i, k in enumerate(self.log_keys)}}
        return self.get_observations(), self._t(rew).to(torch.float32), self._t(done).to(torch.long), extras
