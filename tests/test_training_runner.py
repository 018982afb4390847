"""sim_twin.training.runner.CallbackRunner on a toy environment (no MJX, a few ms an iteration):
the per-iteration callbacks and their stop, the iteration count across learn() calls and resumes,
the checkpoint name / folder / interval, and rank 0's stop decision under multi-GPU training."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("rsl_rl")
pytestmark = pytest.mark.torch

from rsl_rl.env import VecEnv  # noqa: E402
from rsl_rl.runners import OnPolicyRunner  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from sim_twin.training.runner import CallbackRunner  # noqa: E402


class ToyEnv(VecEnv):
    """4 environments, 3 observations, 2 actions; reward -|action|^2, episodes of 5 steps."""

    def __init__(self, num_envs: int = 4):
        self.num_envs, self.num_actions, self.max_episode_length = num_envs, 2, 5
        self.device, self.cfg = "cpu", {}
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long)
        self._obs = torch.zeros(num_envs, 3)

    def get_observations(self) -> TensorDict:
        return TensorDict({"policy": self._obs.clone()}, batch_size=[self.num_envs])

    def step(self, actions):
        self.episode_length_buf += 1
        done = (self.episode_length_buf >= self.max_episode_length).long()
        self.episode_length_buf[done > 0] = 0
        self._obs = torch.cat([actions, self.episode_length_buf[:, None].float()], dim=1)
        return self.get_observations(), -(actions**2).sum(dim=1), done, {"time_outs": done.float()}


def _cfg(save_interval: int = 50) -> dict:
    mlp = {"class_name": "MLPModel", "hidden_dims": [8], "activation": "elu"}
    return {
        "num_steps_per_env": 4, "save_interval": save_interval, "obs_groups": {"actor": ["policy"], "critic": ["policy"]},
        "algorithm": {"class_name": "PPO", "num_learning_epochs": 1, "num_mini_batches": 1},
        "actor": {**mlp, "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 1.0}}, "critic": mlp,
    }


def _runner(tmp_path, **kw) -> CallbackRunner:
    torch.manual_seed(0)
    return CallbackRunner(ToyEnv(), _cfg(), log_dir=str(tmp_path / "tb"), **kw)


def _pts(folder):
    return sorted(p.name for p in folder.glob("*.pt"))


def test_every_callback_runs_after_every_iteration_and_true_ends_learn(tmp_path):
    seen: list[tuple[str, int, int]] = []

    def stop_after_third(runner, it):
        seen.append(("stop", it, runner.current_learning_iteration))
        return it == 2

    def record(runner, it):
        seen.append(("record", it, runner.current_learning_iteration))

    runner = _runner(tmp_path, callbacks=[stop_after_third, record])
    runner.learn(10)
    # in order, each one after every iteration, the later one too at the iteration that stops
    assert seen == [(name, it, it + 1) for it in range(3) for name in ("stop", "record")]
    assert runner.current_learning_iteration == 3
    assert _pts(tmp_path / "tb") == ["model_3.pt"]  # the final checkpoint, at the iteration that stopped
    assert torch.load(tmp_path / "tb" / "model_3.pt", weights_only=False)["iter"] == 3


def test_the_count_continues_across_learn_calls_and_a_resume(tmp_path):
    its: list[int] = []
    runner = _runner(tmp_path, callbacks=[lambda r, it: its.append(it)], save_interval=2)
    runner.learn(2)
    runner.learn(3)
    assert its == [0, 1, 2, 3, 4] and runner.current_learning_iteration == 5
    assert _pts(tmp_path / "tb") == ["model_2.pt", "model_4.pt", "model_5.pt"]
    assert [torch.load(tmp_path / "tb" / f"model_{n}.pt", weights_only=False)["iter"] for n in (2, 4, 5)] == [2, 4, 5]

    resumed = CallbackRunner(ToyEnv(), _cfg(), log_dir=str(tmp_path / "tb2"), callbacks=[lambda r, it: its.append(it)])
    resumed.load(str(tmp_path / "tb" / "model_5.pt"))  # rsl_rl's load: the count from the checkpoint's iter
    assert resumed.current_learning_iteration == 5
    resumed.learn(1)
    assert its[-1] == 5 and _pts(tmp_path / "tb2") == ["model_6.pt"]


def test_rsl_rl_5_5_runs_the_last_index_again_in_a_second_learn_call(tmp_path):
    """What change (2) of the runner is for: OnPolicyRunner keeps the index of the last iteration
    done, so a second learn(1) runs (logs and saves) iteration 0 again."""
    torch.manual_seed(0)
    plain = OnPolicyRunner(ToyEnv(), _cfg(save_interval=1), log_dir=str(tmp_path / "tb"))
    plain.learn(1)
    plain.learn(1)
    assert plain.current_learning_iteration == 0 and _pts(tmp_path / "tb") == ["model_0.pt"]


def test_checkpoint_folder_name_and_interval(tmp_path, monkeypatch):
    runner = _runner(tmp_path, checkpoint_dir=str(tmp_path / "run"), checkpoint_name="checkpoint.pt", save_interval=2)
    (tmp_path / "run").mkdir()
    saved: list[int] = []
    orig = runner.save
    monkeypatch.setattr(runner, "save", lambda path, infos=None: (saved.append(runner.current_learning_iteration), orig(path, infos)))
    runner.learn(4)
    assert saved == [2, 4]  # every 2 iterations; the last one not written twice at the end
    runner.learn(1)
    assert saved == [2, 4, 5]  # the end of learn() writes the count the interval did not
    assert _pts(tmp_path / "run") == ["checkpoint.pt"] and not _pts(tmp_path / "tb")
    assert torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["iter"] == 5


def test_save_interval_zero_writes_only_the_last_and_no_log_dir_writes_none(tmp_path):
    runner = _runner(tmp_path, save_interval=0)
    runner.learn(3)
    assert _pts(tmp_path / "tb") == ["model_3.pt"]
    quiet = CallbackRunner(ToyEnv(), _cfg(), log_dir=None)  # as rsl_rl: no writer, no checkpoints
    quiet.learn(1)
    assert quiet.current_learning_iteration == 1
    with pytest.raises(ValueError, match="nowhere to write"):
        quiet.checkpoint_path(1)
    with pytest.raises(ValueError, match="save_interval"):
        CallbackRunner(ToyEnv(), _cfg(), save_interval=-1)


@pytest.mark.parametrize("rank0_says, here_says, stops", [(False, True, False), (True, False, True), (True, True, True)])
def test_under_multi_gpu_every_rank_follows_rank_0(tmp_path, monkeypatch, rank0_says, here_says, stops):
    """A rank other than 0: its callbacks run, but the stop decision is the one rank 0 broadcasts."""
    runner = _runner(tmp_path, callbacks=[lambda r, it: here_says])
    broadcasts: list[float] = []

    def broadcast(tensor, src):
        assert src == 0
        broadcasts.append(float(tensor.item()))
        tensor.fill_(1.0 if rank0_says else 0.0)

    monkeypatch.setattr(runner, "is_distributed", True)
    monkeypatch.setattr(torch.distributed, "broadcast", broadcast)
    assert runner._callbacks_stop(0) is stops
    assert broadcasts == [1.0 if here_says else 0.0]


class RaggedEnv(ToyEnv):
    """16 environments whose episodes last 2-6 steps (by environment), rewards that vary by step."""

    def __init__(self, nan_at_step: int | None = None):
        super().__init__(num_envs=16)
        self.limit = 2 + torch.arange(16) % 5
        self.t, self.nan_at_step = 0, nan_at_step

    def step(self, actions):
        self.t += 1
        self.episode_length_buf += 1
        done = (self.episode_length_buf >= self.limit).long()
        self.episode_length_buf[done > 0] = 0
        self._obs = torch.cat([actions, self.episode_length_buf[:, None].float()], dim=1)
        rew = -(actions**2).sum(dim=1) + 0.1 * self.episode_length_buf.float()
        if self.t == self.nan_at_step:
            rew = rew.clone()
            rew[3] = float("nan")
        return self.get_observations(), rew, done, {"time_outs": torch.zeros(16), "log": {"x": rew.mean()}}


def _ragged_runner(tmp_path, name: str, env=None, **kw) -> CallbackRunner:
    torch.manual_seed(0)
    cfg = {**_cfg(), "num_steps_per_env": 8}
    return CallbackRunner(env or RaggedEnv(), cfg, log_dir=str(tmp_path / name), **kw)


def test_per_iteration_syncs_leave_the_loggers_episode_buffers_and_the_training_as_rsl_rls(tmp_path):
    """Change 4: the episode bookkeeping on the device gives the logger the same last 100 returns
    and lengths, in the same order, and the same running sums, and the policy trains the same."""
    per_step = _ragged_runner(tmp_path, "a")
    per_step.learn(7)  # 16 x 8 x 7 steps, about 300 episodes: the 100-episode buffers wrap
    per_iteration = _ragged_runner(tmp_path, "b", per_iteration_syncs=True)  # the same seed, the same actions
    per_iteration.learn(7)
    a, b = per_step.logger, per_iteration.logger
    assert len(a.rewbuffer) == 100 and list(a.lenbuffer) == list(b.lenbuffer)
    assert list(a.rewbuffer) == pytest.approx(list(b.rewbuffer), rel=1e-6, abs=1e-6)
    assert sorted(set(a.lenbuffer)) == [2.0, 3.0, 4.0, 5.0, 6.0]
    assert torch.allclose(a.cur_reward_sum, b.cur_reward_sum) and torch.equal(a.cur_episode_length, b.cur_episode_length)
    for pa, pb in zip(per_step.alg.actor.parameters(), per_iteration.alg.actor.parameters(), strict=True):
        assert torch.allclose(pa, pb)


def test_per_iteration_syncs_still_refuse_a_nan_before_the_update_uses_it(tmp_path):
    runner = _ragged_runner(tmp_path, "n", env=RaggedEnv(nan_at_step=11), per_iteration_syncs=True)
    before = [p.detach().clone() for p in runner.alg.actor.parameters()]
    with pytest.raises(ValueError, match="NaN"):
        runner.learn(3)  # step 11 lies in the second rollout (8 steps each)
    assert runner.current_learning_iteration == 1  # the first iteration's update ran, the second's did not
    changed = [not torch.equal(p, q) for p, q in zip(before, runner.alg.actor.parameters(), strict=True)]
    assert any(changed)
    with pytest.raises(ValueError, match="RND"):
        CallbackRunner(RaggedEnv(), {**_cfg(), "algorithm": {**_cfg()["algorithm"], "rnd_cfg": {"weight": 1.0}}},
                       per_iteration_syncs=True)
