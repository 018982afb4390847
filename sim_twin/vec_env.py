"""rsl_rl VecEnv adapter around the batched MJX throwing environment.

Arrays cross between JAX and PyTorch by DLPack (no copy on the same device). Observations are
returned as a TensorDict with two groups: ``policy`` (runtime.observation, what the machine
measures) and ``privileged`` (sim_twin.privileged: the episode's randomised parameters and the
true passive joint state, for an asymmetric critic). rsl_rl picks the groups of actor and critic
by the config's ``runner.obs_groups``; the actor must keep ["policy"] (it is what is exported).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from sim_twin.mjx_env import EnvConfig, ThrowEnvCore


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

    Shapes: observations ``policy`` (num_envs, observation_size(mode)), ``privileged``
    (num_envs, PRIVILEGED_SIZE); actions (num_envs, num_actions(mode));
    rewards and dones (num_envs,).
    """

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int = 0, device: str = "cpu"):
        self.core = ThrowEnvCore(cfg)
        self.cfg = {"env": cfg.__dict__}
        self.num_envs = num_envs
        self.num_actions = self.core.num_act
        self.max_episode_length = cfg.max_steps
        self.device = device
        keys = jax.random.split(jax.random.PRNGKey(seed), num_envs)
        self._reset = jax.jit(jax.vmap(self.core.reset))
        self._step = jax.jit(jax.vmap(self.core.step_autoreset))
        self._privileged = jax.jit(jax.vmap(self.core.privileged))
        self.state, obs = self._reset(keys)
        self._obs = obs
        self._priv = self._privileged(self.state)
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.reset_stats()

    def reset_stats(self) -> None:
        """Start accumulating throw statistics afresh (see read_stats)."""
        self._sums = {"done": 0.0, "landed": 0.0, "failed": 0.0, "err_sum": 0.0}

    def read_stats(self) -> dict[str, float]:
        """Fractions of finished episodes that landed / failed and the mean impact error of the
        landings since reset_stats()."""
        s = self._sums
        done = max(s["done"], 1.0)
        return {
            "landed_per_done": s["landed"] / done,
            "failed_per_done": s["failed"] / done,
            "impact_err_m": s["err_sum"] / max(s["landed"], 1.0),
        }

    def get_observations(self) -> TensorDict:
        obs = {"policy": _to_torch(self._obs), "privileged": _to_torch(self._priv)}
        return TensorDict(obs, batch_size=[self.num_envs], device=self.device)

    def step(self, actions: torch.Tensor):
        a = _to_jax(actions.detach().to(torch.float32))
        self.state, self._obs, rew, done, tout, info = self._step(self.state, a)
        self._priv = self._privileged(self.state)  # after the auto-reset: the new episode's
        dones = _to_torch(done).to(torch.long)
        self.episode_length_buf = _to_torch(self.state["step"]).to(torch.long)
        landed = info["landed"]
        sums = jnp.stack(
            [jnp.sum(done), jnp.sum(landed), jnp.sum(info["failed"]), jnp.sum(jnp.where(landed, info["impact_err_m"], 0.0))]
        )
        n_done, n_landed, n_failed, err_sum = (float(x) for x in np.asarray(sums))  # one device->host copy
        for k, v in zip(("done", "landed", "failed", "err_sum"), (n_done, n_landed, n_failed, err_sum)):
            self._sums[k] += v
        log = {
            "/throw/landed_per_done": n_landed / max(n_done, 1.0),
            "/throw/failed_per_done": n_failed / max(n_done, 1.0),
            "/throw/impact_err_m": err_sum / max(n_landed, 1.0),
        }
        extras = {"time_outs": _to_torch(tout).to(torch.float32), "log": log}
        return self.get_observations(), _to_torch(rew).to(torch.float32), dones, extras
