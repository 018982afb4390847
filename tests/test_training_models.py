"""sim_twin.training.models.Float32MLPModel: inside rsl_rl's bfloat16 update the actor's policy mean
and distribution are the float32 rollout's to the bit (plain MLPModel's are not: the rounding shows
as a KL divergence at a small std), a mixed-precision PPO update trains with it on the CPU, and its
checkpoints load into MLPModel (resume and ONNX export build that)."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("rsl_rl")
pytestmark = pytest.mark.torch

from rsl_rl.models import MLPModel  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from sim_twin.training.models import FLOAT32_ACTOR, Float32MLPModel  # noqa: E402

N_OBS, N_ACT = 56, 4  # the 2D actor's sizes


def _actor(cls, std: float = 0.05):
    torch.manual_seed(0)
    obs = TensorDict({"policy": torch.zeros(1, N_OBS)}, batch_size=[1])
    return cls(obs, {"actor": ["policy"]}, "actor", N_ACT, hidden_dims=[256, 128], activation="elu",
               obs_normalization=True, distribution_cfg={"class_name": "GaussianDistribution", "init_std": std})


def _params(actor, obs, autocast: bool):
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        actor(obs, stochastic_output=True)
        return tuple(p.float() for p in actor.output_distribution_params)


@pytest.mark.parametrize("cls", [MLPModel, Float32MLPModel])
def test_the_float32_actor_keeps_the_rollout_policy_inside_bfloat16_autocast(cls):
    actor = _actor(cls)
    with torch.no_grad():
        actor.mlp[-1].bias.add_(0.7)  # means of a trained actor's size (0.5-1), where bf16 steps are 0.004
    obs = TensorDict({"policy": torch.randn(4096, N_OBS)}, batch_size=[4096])
    rollout, update = _params(actor, obs, autocast=False), _params(actor, obs, autocast=True)
    kl = actor.get_kl_divergence(rollout, update).mean().item()
    if cls is Float32MLPModel:
        assert all(torch.equal(a, b) for a, b in zip(rollout, update))
        assert kl == 0.0
    else:  # the fault the class removes: the rounding alone is a KL of the order of PPO's target 0.01
        assert not torch.equal(rollout[0], update[0])
        assert kl > 1e-3


def test_a_bfloat16_update_trains_with_the_float32_actor_and_its_checkpoint_loads_into_mlpmodel(tmp_path):
    from sim_twin.training.runner import CallbackRunner
    from tests.test_training_runner import ToyEnv, _cfg

    cfg = _cfg()
    cfg["actor"]["class_name"] = FLOAT32_ACTOR
    cfg["algorithm"]["use_mixed_precision"] = True
    torch.manual_seed(0)
    runner = CallbackRunner(ToyEnv(), cfg, log_dir=str(tmp_path / "tb"))
    assert type(runner.alg.actor) is Float32MLPModel
    before = {k: v.clone() for k, v in runner.alg.actor.state_dict().items()}
    runner.learn(num_learning_iterations=3)
    after = runner.alg.actor.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before), "the update changed no actor weight"
    assert all(v.dtype == torch.float32 for v in after.values() if v.is_floating_point())
    runner.save(str(tmp_path / "checkpoint.pt"))
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)["actor_state_dict"]
    obs = TensorDict({"policy": torch.zeros(1, 3)}, batch_size=[1])
    plain = MLPModel(obs, {"actor": ["policy"]}, "actor", 2, hidden_dims=[8], activation="elu",
                     distribution_cfg={"class_name": "GaussianDistribution", "init_std": 1.0})
    plain.load_state_dict(state)  # strict: the same keys and shapes


def test_on_a_trained_actor_the_rounding_alone_passes_desired_kl_at_the_std_floor():
    """The committed throw2d-scratch-at actor (trained with the bfloat16 update): at its std floor
    0.05 the bfloat16 update's rounding alone is a KL above the recipe's desired_kl, with the actor
    in float32 none (reports/training_policy_rounding_2d.md, in the lab notebook, measures it on 65536 observations)."""
    from pathlib import Path

    from sim_twin.training.export import load_actor
    from tests.benchmarks.training_policy_rounding import rounding

    run = Path(__file__).resolve().parents[1] / "policies" / "training" / "throw2d-scratch-at"
    cfg = json.loads((run / "config.json").read_text())
    plain, _ = load_actor(run / "checkpoint.pt", cfg, MLPModel)
    fixed, _ = load_actor(run / "checkpoint.pt", cfg, Float32MLPModel)
    desired = cfg["runner"]["algorithm"]["desired_kl"]
    floor = cfg["runner"]["actor"]["distribution_cfg"]["std_range"][0]
    at_floor = {m: rounding(a, 8192, sigmas=(floor,))["per_sigma"][0] for m, a in [("plain", plain), ("fixed", fixed)]}
    assert at_floor["plain"]["kl_mean"] > desired and at_floor["plain"]["clipped_share"] > 0.05
    assert at_floor["fixed"]["kl_mean"] == 0.0 and at_floor["fixed"]["clipped_share"] == 0.0
