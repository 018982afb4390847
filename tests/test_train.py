"""PPO training on the CPU with tiny settings: checkpoints, exact resume, curve, ONNX export, the
per-term reward logs in TensorBoard, the std cap, and the one-command run with its site-matrix gate
and model card."""

from __future__ import annotations

import argparse

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("jax")
pytestmark = pytest.mark.torch

from runtime.policy import PolicyRunner  # noqa: E402
from sim_twin.training import train
from sim_twin.training import config as training_config  # noqa: E402


def _args(tmp_path, **kw):
    p = argparse.ArgumentParser()
    train.build_parser(p)
    argv = ["--mode", "2d", "--num-envs", "8", "--iterations", "2", "--chunk", "1", "--log-dir", str(tmp_path / "run")]
    if not kw.pop("gate", False):
        argv.append("--no-gate")
    for k, v in kw.items():
        argv += [f"--{k.replace('_', '-')}"] + ([] if v is True else [str(v)])
    return p.parse_args(argv)


def test_train_checkpoint_resume_export(tmp_path):
    assert train.run(_args(tmp_path)) == 0
    ckpt = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=False)
    assert {"actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter"} <= set(state)
    first_iter = state["iter"]

    onnx = tmp_path / "p.onnx"
    assert train.run(_args(tmp_path, iterations=1, resume=ckpt, export=onnx, name="tiny")) == 0
    resumed = torch.load(ckpt, weights_only=False)
    assert resumed["iter"] > first_iter  # continued, not restarted
    rows = (tmp_path / "run" / "curve.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 3  # header + 2 chunks + 1 resumed chunk
    assert (tmp_path / "run" / "training_curve.png").stat().st_size > 1000
    runner = PolicyRunner.load(onnx)
    assert runner.version == "tiny" and runner.mode == "2d"


def _tb_tags(tb_dir):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = set()
    for f in tb_dir.glob("events.out.tfevents.*"):
        acc = EventAccumulator(str(f))
        acc.Reload()
        tags |= set(acc.Tags()["scalars"])
    return tags


def test_one_command_with_gate_model_card_and_term_logs(tmp_path):
    """slinger train with the gate on tiny settings: the matrix of a checkpoint runs beside the
    training, its verdict is kept, the export carries a model card (bars not met here)."""
    import json

    from sim_twin.training.rewards import REWARD_TERMS

    onnx = tmp_path / "p.onnx"
    args = _args(tmp_path, gate=True, gate_targets="8.5", gate_throws=1, gate_seeds="0", gate_workers=2,
                 gate_wait_minutes=10, export=onnx, name="tiny-gated")
    assert train.run(args) == 0
    run = tmp_path / "run"
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    assert gate["results"] and gate["results"][0]["seed"] == 0 and gate["results"][0]["passed"] is False
    assert (run / "matrices" / f"site_matrix_2d_it{gate['results'][0]['iteration']}.md").exists()
    card = json.loads((tmp_path / "p.card.json").read_text())
    assert card["bars_met"] is False and len(card["config_sha256"]) == 64 and card["command"]
    # no --seed: the recipe's training seed, recorded in the card and in the run's config
    recipe = training_config.load_config("2d", None)
    assert card["training_seed"] == recipe["training"]["seed"]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["training"]["seed"] == recipe["training"]["seed"]
    assert json.loads(onnx.with_suffix(".json").read_text())["training"]["model_card"]["onnx_sha256"] == card["onnx_sha256"]
    header = (run / "curve.csv").read_text().splitlines()[0].split(",")
    assert {f"reward_{k}" for k in REWARD_TERMS} <= set(header) and "action_std" in header
    tags = _tb_tags(run / "tb")
    assert {f"Reward/{k}" for k in REWARD_TERMS} <= tags and "Policy/mean_std" in tags
    assert not list((run / "tb").glob("model_*.pt"))


@pytest.mark.parametrize("stop_at_bars", [True, False])
def test_the_run_stops_at_the_bars_or_trains_past_them(tmp_path, monkeypatch, stop_at_bars):
    """Every candidate meets the bars here (a matrix that always passes): by default the run stops
    at the first and exports it; with --no-stop-at-bars it trains every iteration, the gate judging
    on, and exports the newest candidate that met the bars."""
    import json
    import sys

    from sim_twin.training.matrix_gate import MatrixGate

    def passing(self, onnx, seed, out):
        rep = {"pass": True, "profiles": []}
        return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]

    monkeypatch.setattr(MatrixGate, "command", passing)
    extra = {} if stop_at_bars else {"no_stop_at_bars": True}
    args = _args(tmp_path, gate=True, iterations=4, gate_seeds="0", gate_workers=1, gate_wait_minutes=5, **extra)
    if not stop_at_bars:
        assert args.stop_at_bars is False
    assert train.run(args) == 0
    run = tmp_path / "run"
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    card = json.loads((run / "throw2d.card.json").read_text())
    iterations = [int(line.split(",")[0].split(".")[0]) for line in (run / "curve.csv").read_text().splitlines()[1:]]
    assert card["bars_met"] is True
    manifest = json.loads((run / "throw2d.json").read_text())
    assert manifest["name"] == f"throw2d-it{card['iteration']}"  # no --name: named by its iteration
    if stop_at_bars:
        assert card["iteration"] == gate["passed"]["iteration"] and len(gate["passes"]) == 1
        assert len(iterations) < 4  # stopped before its 4 iterations were done
    else:
        assert len(iterations) == 4 and len(gate["passes"]) >= 2
        assert card["iteration"] == gate["passes"][-1]["iteration"] > gate["passed"]["iteration"]


def test_std_schedule_caps_the_learned_std():
    s = training_config.StdSchedule.from_dict({"start": 0.6, "end": 0.06, "iterations": 100})
    assert s.cap(0) == pytest.approx(0.6) and s.cap(50) == pytest.approx(0.6 * 0.1**0.5) and s.cap(500) == pytest.approx(0.06)
    with pytest.raises(ValueError):
        training_config.StdSchedule.from_dict({"start": 0.6, "end": 0.0, "iterations": 100})
    with pytest.raises(ValueError):
        training_config.StdSchedule.from_dict({"start": 0.6, "end": 0.1, "iters": 100})
    from rsl_rl.modules.distribution import GaussianDistribution

    dist = GaussianDistribution(3, init_std=0.6, std_range=(0.02, 0.6), std_type="log")

    class R:  # the runner attributes apply_std_cap touches
        class alg:
            class actor:
                distribution = dist

    train.apply_std_cap(R, 0.2)
    assert train.current_std(R) == pytest.approx(0.2, rel=1e-5)
    dist.log_std_param.data -= 1.0  # learned below the cap: kept
    train.apply_std_cap(R, 0.3)
    assert train.current_std(R) == pytest.approx(0.2 * 2.718281828**-1, rel=1e-4)
    # the release flag (last action) keeps at least its floor; the other actions keep learning below
    train.apply_std_cap(R, 0.3, release_floor=0.25)
    std = dist.log_std_param.exp()
    assert std[-1].item() == pytest.approx(0.25, rel=1e-5) and std[0].item() == pytest.approx(0.2 * 2.718281828**-1, rel=1e-4)
    with pytest.raises(ValueError, match="release_floor"):
        training_config.StdSchedule.from_dict({"start": 0.6, "end": 0.1, "iterations": 100, "release_floor": 0.3})


def test_model_card_commit_outside_git_comes_from_the_environment(tmp_path, monkeypatch):
    """A copy of the tree without git (as on a lent GPU machine) records the commit it was given."""
    from sim_twin.training.model_card import git_commit

    monkeypatch.delenv("SLINGER_GIT_COMMIT", raising=False)
    assert git_commit(tmp_path) == "unknown"
    monkeypatch.setenv("SLINGER_GIT_COMMIT", "8cb5ce7")
    assert git_commit(tmp_path) == "8cb5ce7"
    assert git_commit().split("-")[0] != "8cb5ce7"  # inside the repository git's own answer wins


def test_training_seed_from_the_flag_else_the_recipe_else_a_clear_error():
    cfg = {"training": {"seed": 2}}
    assert training_config.resolve_training(cfg, None).seed == 2
    assert training_config.resolve_training(cfg, 5).seed == 5 and cfg["training"]["seed"] == 5  # recorded as used
    with pytest.raises(ValueError, match="training.seed"):
        training_config.resolve_training({"training": {}}, None)
    with pytest.raises(ValueError, match="integer"):
        training_config.resolve_training({"training": {"seed": "0"}}, None)
    assert training_config.resolve_training({}, 3).seed == 3  # a config without a training section takes the flag


def test_randomization_stage_widens_once_and_the_gate_judges_from_its_iteration(tmp_path, monkeypatch):
    """training.randomization_stage: the environment is reconfigured once, at the first chunk
    boundary at or after its iteration, to the widened ranges, with the critic's normalisation
    over the widened ranges from the start; training.gate_from_iteration keeps earlier
    checkpoints from the gate (which passes everything here)."""
    import json
    import sys

    from sim_twin.training.matrix_gate import MatrixGate
    from sim_twin.training.vec_env import MjxThrowVecEnv

    def passing(self, onnx, seed, out):
        rep = {"pass": True, "profiles": []}
        return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]

    monkeypatch.setattr(MatrixGate, "command", passing)
    seen = []
    orig_init, orig_reconf = MjxThrowVecEnv.__init__, MjxThrowVecEnv.reconfigure

    def init(self, cfg, *a, **kw):
        seen.append(("init", cfg.randomization, cfg.privileged_ranges))
        orig_init(self, cfg, *a, **kw)

    def reconf(self, cfg):
        seen.append(("widen", cfg.randomization, cfg.privileged_ranges))
        orig_reconf(self, cfg)

    monkeypatch.setattr(MjxThrowVecEnv, "__init__", init)
    monkeypatch.setattr(MjxThrowVecEnv, "reconfigure", reconf)
    cfg = training_config.load_config("2d", None)
    wide = {"friction_scale": [0.5, 10.0], "friction_sampling": "log_uniform", "grasp_forward_m": [-0.2, 0.2]}
    cfg["training"]["randomization_stage"] = {"iteration": 2, "randomization": wide}
    cfg["training"]["gate_from_iteration"] = 3
    path = tmp_path / "staged.json"
    path.write_text(json.dumps(cfg))
    args = _args(tmp_path, gate=True, iterations=5, gate_seeds="0", gate_workers=1, gate_wait_minutes=5, config=path)
    assert train.run(args) == 0
    assert [s[0] for s in seen] == ["init", "widen"]
    (_, before, priv0), (_, after, priv1) = seen
    assert before.friction_scale == (0.5, 3.5) and before.friction_sampling == "uniform" and before.grasp_forward_m == (0.0, 0.0)
    assert after.friction_scale == (0.5, 10.0) and after.friction_sampling == "log_uniform" and after.grasp_forward_m == (-0.2, 0.2)
    assert after.lag_s == before.lag_s  # entries the stage does not name stay the recipe's
    assert priv0 == priv1 and priv0["friction_scale"] == [0.5, 10.0] and priv0["friction_sampling"] == "log_uniform"
    gate = json.loads((tmp_path / "run" / "matrices" / "matrix_gate.json").read_text())
    assert gate["passed"]["iteration"] >= 3  # iterations 1 and 2 were trained but not judged


@pytest.mark.parametrize("stage, match", [
    ({"iteration": -1, "randomization": {}}, "integer >= 0"),
    ({"iteration": 5}, "exactly 'iteration' and 'randomization'"),
    ({"iteration": 5, "randomization": {}, "when": 3}, "exactly"),
    ({"iteration": 5, "randomization": {"friction_scal": [1, 2]}}, "unknown entries"),
    ({"iteration": 5, "randomization": {"grasp_up_m": [0.1, -0.1]}}, "must be a range"),
])
def test_randomization_stage_refuses_bad_input(stage, match):
    with pytest.raises(ValueError, match=match):
        training_config.RandomizationStage.from_dict(stage)


def test_gate_from_iteration_refuses_bad_input(tmp_path):
    import json

    cfg = training_config.load_config("2d", None)
    cfg["training"]["gate_from_iteration"] = "600"
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="gate_from_iteration must be an integer"):
        train.run(_args(tmp_path, config=path))
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_the_training_section_is_typed_and_refuses_a_misspelt_setting():
    cfg = training_config.load_config("2d", None)
    section = training_config.TrainingSection.from_dict(cfg["training"])
    assert section.seed == cfg["training"]["seed"] and isinstance(section.std_schedule, training_config.StdSchedule)
    assert section.randomization_stage is None and section.gate_from_iteration == 0
    with pytest.raises(ValueError, match=r"unknown training settings \['gate_from_iteratoin'\]"):
        training_config.TrainingSection.from_dict({**cfg["training"], "gate_from_iteratoin": 600})
    with pytest.raises(ValueError, match="unknown training settings"):
        training_config.resolve_training({"training": {"seed": 1, "sed": 2}}, None)


def _initial_actor(tmp_path, name, seed):
    run = train.TrainingRun(_args(tmp_path / name, seed=seed, iterations=0))
    return [p.detach().clone() for p in run.runner.alg.actor.parameters()]


def test_the_training_seed_fixes_the_initial_networks(tmp_path):
    # rsl_rl initialises the actor and critic from torch's global generator: unseeded, two runs with
    # the same training seed started from different networks
    torch.manual_seed(123)
    a = _initial_actor(tmp_path, "a", seed=3)
    torch.manual_seed(456)
    b = _initial_actor(tmp_path, "b", seed=3)
    c = _initial_actor(tmp_path, "c", seed=4)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(torch.equal(x, y) for x, y in zip(a, c, strict=True))
