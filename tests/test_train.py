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


def test_train_checkpoint_resume_export(tmp_path, monkeypatch):
    """A run resumed on another machine (here: another accelerator name) exports a card naming
    both, with the iterations each trained; the exporting process's GPU alone would misname it."""
    import json

    from sim_twin.training import model_card

    monkeypatch.setattr(model_card, "accelerator", lambda: "1 x NVIDIA H100 80GB HBM3")
    assert train.run(_args(tmp_path)) == 0
    ckpt = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=False)
    assert {"actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter"} <= set(state)
    first_iter = state["iter"]

    onnx = tmp_path / "p.onnx"
    monkeypatch.setattr(model_card, "accelerator", lambda: "1 x NVIDIA H200")
    assert train.run(_args(tmp_path, iterations=1, resume=ckpt, export=onnx, name="tiny")) == 0
    resumed = torch.load(ckpt, weights_only=False)
    assert first_iter == 2 and resumed["iter"] == 3  # continued at the next iteration, not restarted nor one skipped
    card = json.loads((tmp_path / "p.card.json").read_text())
    assert card["accelerator"] == "1 x NVIDIA H100 80GB HBM3 (iterations 0-2), 1 x NVIDIA H200 (2-3)"
    assert "1 x NVIDIA H100 80GB HBM3 (iterations 0-2), 1 x NVIDIA H200 (2-3), 1 process(es)" in (tmp_path / "p.card.md").read_text()
    rows = (tmp_path / "run" / "curve.csv").read_text().strip().splitlines()
    assert [float(r.split(",")[0]) for r in rows[1:]] == [1, 2, 3]  # 2 chunks + 1 resumed chunk
    assert (tmp_path / "run" / "training_curve.png").stat().st_size > 1000
    runner = PolicyRunner.load(onnx)
    assert runner.version == "tiny" and runner.mode == "2d"


def test_accelerator_segments_of_a_run_directory(tmp_path):
    """record_accelerator keeps one segment per start; a resume from an older checkpoint drops the
    segments of the iterations it trains again; describe_accelerators names one accelerator alone
    and several with their iterations; a damaged record is refused, naming the file."""
    from sim_twin.training.model_card import ACCELERATORS_FILE, describe_accelerators, record_accelerator

    record_accelerator(tmp_path, 0, "1 x A", 1)
    assert describe_accelerators(record_accelerator(tmp_path, 925, "1 x A", 1), 950) == "1 x A"  # the same machine kind
    segs = record_accelerator(tmp_path, 950, "1 x B", 1)
    assert describe_accelerators(segs, 1000) == "1 x A (iterations 0-950), 1 x B (950-1000)"
    assert describe_accelerators(segs, 940) == "1 x A"  # the exported checkpoint was trained before B
    segs = record_accelerator(tmp_path, 900, "2 x C", 2)  # resumed from an older checkpoint: 925 on are trained again
    assert [s["from_iteration"] for s in segs] == [0, 900] and describe_accelerators(segs, 1000) == "1 x A (iterations 0-900), 2 x C (900-1000)"
    assert describe_accelerators(segs, 0) == "1 x A"
    (tmp_path / ACCELERATORS_FILE).write_text('{"not": "a list"}')
    with pytest.raises(ValueError, match=ACCELERATORS_FILE):
        record_accelerator(tmp_path, 1000, "1 x A", 1)


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


def test_the_run_stops_at_the_bars(tmp_path, monkeypatch):
    """Every candidate meets the bars here (a matrix that always passes): by default the run stops
    at the first and exports it. (With --no-stop-at-bars it trains on: the next two tests, one
    exporting the newest pass, one the pass worse than the deployed policy on the fewest cells.)"""
    import json
    import sys

    from sim_twin.training.matrix_gate import MatrixGate

    def passing(self, onnx, seed, out):
        rep = {"pass": True, "profiles": []}
        return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]

    monkeypatch.setattr(MatrixGate, "command", passing)
    args = _args(tmp_path, gate=True, iterations=4, gate_seeds="0", gate_workers=1, gate_wait_minutes=5)
    assert train.run(args) == 0
    run = tmp_path / "run"
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    card = json.loads((run / "throw2d.card.json").read_text())
    iterations = [int(line.split(",")[0].split(".")[0]) for line in (run / "curve.csv").read_text().splitlines()[1:]]
    assert card["bars_met"] is True
    manifest = json.loads((run / "throw2d.json").read_text())
    assert manifest["name"] == f"throw2d-it{card['iteration']}"  # no --name: named by its iteration
    assert card["iteration"] == gate["passed"]["iteration"] and len(gate["passes"]) == 1
    assert len(iterations) < 4  # stopped before its 4 iterations were done


def test_a_run_past_the_bars_compared_with_the_deployed_exports_the_pass_worse_on_the_fewest_cells(tmp_path, monkeypatch):
    """--gate-compare-with: the gate's matrices here are committed ones, the deployed policy's own
    (worse on no cell against itself) for odd iterations and throw2d-scratch-n1's iteration 3075 (worse
    on two cells, seed 0) for even ones; every pass records its count and the export is the pass worse
    on the fewest cells, the newest among equals, whatever was judged."""
    import json
    import sys
    from pathlib import Path

    from sim_twin.training.matrix_gate import MatrixGate

    root = Path(__file__).resolve().parents[1]
    deployed = root / "reports" / "site_matrix_2d.json"
    n1 = root / "policies" / "training" / "throw2d-scratch-n1" / "matrices" / "site_matrix_2d_it3075.json"

    def copying(self, onnx, seed, out):
        src = deployed if int(onnx.rsplit("_", 1)[1].split(".")[0]) % 2 else n1
        return [sys.executable, "-c", f"import shutil; shutil.copyfile({str(src)!r}, {out!r})"]

    monkeypatch.setattr(MatrixGate, "command", copying)
    args = _args(tmp_path, gate=True, iterations=4, gate_seeds="0", gate_workers=1, gate_wait_minutes=5,
                 no_stop_at_bars=True, gate_compare_with=deployed)
    assert args.stop_at_bars is False and train.run(args) == 0
    iterations = [int(line.split(",")[0].split(".")[0]) for line in (tmp_path / "run" / "curve.csv").read_text().splitlines()[1:]]
    assert len(iterations) == 4  # trained every iteration past the first pass
    passes = json.loads((tmp_path / "run" / "matrices" / "matrix_gate.json").read_text())["passes"]
    assert len(passes) >= 2 and all(p["worse_than_deployed"] == (0 if p["iteration"] % 2 else 2) for p in passes)
    fewest = min(p["worse_than_deployed"] for p in passes)
    card = json.loads((tmp_path / "run" / "throw2d.card.json").read_text())
    assert card["iteration"] == max(p["iteration"] for p in passes if p["worse_than_deployed"] == fewest)


def test_a_run_resumed_from_its_state_elsewhere_exports_the_pass_it_carried(tmp_path, monkeypatch):
    """--no-stop-at-bars: every candidate passes on the first machine; the run's state
    (tests/benchmarks/device_runs.sh state, under another name) resumes on a second machine, where the
    first machine's directory is gone and every candidate misses. The export is the first machine's
    newest pass, found in the state, not a crash on its path there; a run whose state lacks that
    checkpoint exports the newest pass whose checkpoint it has, and one with none fails with a clear error."""
    import json
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from sim_twin.training.matrix_gate import MatrixGate

    def verdict(ok):
        def command(self, onnx, seed, out):
            rep = {"pass": ok, "profiles": [{"name": "nominal", "targets": [{"target_m": 10.0, "bars": {"accuracy": ok}}]}]}
            return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]
        return command

    monkeypatch.setattr(MatrixGate, "command", verdict(True))
    first = tmp_path / "m1"
    assert train.run(_args(first, gate=True, iterations=3, gate_seeds="0", gate_workers=1, gate_wait_minutes=5,
                           no_stop_at_bars=True)) == 0
    newest = json.loads((first / "run" / "matrices" / "matrix_gate.json").read_text())["passes"][-1]
    script = Path(__file__).resolve().parents[1] / "tests" / "benchmarks" / "device_runs.sh"
    second = tmp_path / "m2"
    second.mkdir()
    subprocess.run(["bash", str(script), "state", str(first / "run"), "moved", str(second)], check=True, capture_output=True)
    shutil.rmtree(first)  # the first machine is gone
    subprocess.run(["tar", "xf", "moved.tar"], cwd=second, check=True)
    run2 = second / "runs" / "moved"

    monkeypatch.setattr(MatrixGate, "command", verdict(False))
    args = _args(tmp_path, gate=True, iterations=1, gate_seeds="0", gate_workers=1, gate_wait_minutes=5,
                 no_stop_at_bars=True, resume=run2 / "checkpoint.pt", log_dir=run2)
    assert train.run(args) == 0
    card = json.loads((run2 / "throw2d.card.json").read_text())
    assert card["bars_met"] is True and card["iteration"] == newest["iteration"]

    (run2 / "candidates" / f"checkpoint_{newest['iteration']}.pt").unlink()  # a state without it
    (run2 / "throw2d.onnx").unlink()
    passes = [q["iteration"] for q in json.loads((run2 / "matrices" / "matrix_gate.json").read_text())["passes"]]
    here = sorted(i for i in passes if (run2 / "candidates" / f"checkpoint_{i}.pt").exists())
    args = _args(tmp_path, gate=True, iterations=1, gate_seeds="0", gate_workers=1, gate_wait_minutes=5,
                 no_stop_at_bars=True, resume=run2 / "checkpoint.pt", log_dir=run2)
    assert here  # the state carries an older pass's checkpoint too: the newest of those is exported instead
    assert train.run(args) == 0
    card = json.loads((run2 / "throw2d.card.json").read_text())
    assert card["iteration"] == max(here) < newest["iteration"]
    for c in (run2 / "candidates").glob("checkpoint_*.pt"):
        c.unlink()
    (run2 / "throw2d.onnx").unlink()
    with pytest.raises(FileNotFoundError, match=f"iteration {newest['iteration']}"):  # no pass's checkpoint: a clear error
        train.run(args)


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
    from sim_twin.provenance import git_commit

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
    ({"iteration": 5}, "needs 'iteration' and 'randomization' and/or 'rewards'"),
    ({"randomization": {}}, "needs 'iteration'"),
    ({"iteration": 5, "randomization": {}, "when": 3}, "needs"),
    ({"iteration": 5, "randomization": {"friction_scal": [1, 2]}}, "unknown entries"),
    ({"iteration": 5, "randomization": {"grasp_up_m": [0.1, -0.1]}}, "must be a range"),
    ({"iteration": 5, "rewards": {"hld": 0.01}}, r"unknown reward settings \['hld'\]"),
    ({"iteration": 5, "rewards": {"hold": "0.01"}}, "rewards.hold must be a finite number"),
    ({"iteration": 5, "rewards": {"hold": float("nan")}}, "finite number"),
])
def test_curriculum_stage_refuses_bad_input(stage, match):
    with pytest.raises(ValueError, match=match):
        training_config.CurriculumStage.from_dict(stage)


def test_both_spellings_of_the_curriculum_stage_are_refused_together():
    stage = {"iteration": 5, "rewards": {"hold": 0.01}}
    section = training_config.TrainingSection.from_dict({"randomization_stage": stage})
    assert section.curriculum_stage == training_config.CurriculumStage(5, {}, {"hold": 0.01})
    with pytest.raises(ValueError, match="one setting: give one"):
        training_config.TrainingSection.from_dict({"curriculum_stage": stage, "randomization_stage": stage})


def test_a_reward_stage_changes_the_rewards_once_and_leaves_the_rest(tmp_path, monkeypatch):
    """training.curriculum_stage with ``rewards`` only: the environment is reconfigured once, at the
    first chunk boundary at or after its iteration, with the named reward entries changed and every
    other reward entry and the randomisation as the recipe has them. The same run's
    training.desired_kl_stage: the updates before its iteration aim at the recipe's KL, those from
    it on at the stage's."""
    import json

    from rsl_rl.algorithms import PPO

    from sim_twin.training.vec_env import MjxThrowVecEnv

    seen = []
    orig_init, orig_reconf = MjxThrowVecEnv.__init__, MjxThrowVecEnv.reconfigure
    kl_aims, orig_update = [], PPO.update

    def update(self, *a, **kw):
        kl_aims.append(self.desired_kl)
        return orig_update(self, *a, **kw)

    monkeypatch.setattr(PPO, "update", update)

    def init(self, cfg, *a, **kw):
        seen.append(("init", cfg))
        orig_init(self, cfg, *a, **kw)

    def reconf(self, cfg):
        seen.append(("stage", cfg))
        orig_reconf(self, cfg)

    monkeypatch.setattr(MjxThrowVecEnv, "__init__", init)
    monkeypatch.setattr(MjxThrowVecEnv, "reconfigure", reconf)
    cfg = training_config.load_config("2d", None)
    cfg["env"]["rewards"]["hold"] = 0.0
    cfg["training"]["curriculum_stage"] = {"iteration": 2, "rewards": {"hold": 0.02, "hold_after_s": 4.0}}
    cfg["training"]["desired_kl_stage"] = {"iteration": 1, "desired_kl": 0.002}
    path = tmp_path / "staged.json"
    path.write_text(json.dumps(cfg))
    assert train.run(_args(tmp_path, iterations=3, chunk=1, config=path)) == 0
    assert [s[0] for s in seen] == ["init", "stage"]
    (_, before), (_, after) = seen
    assert (before.rewards.hold, after.rewards.hold, after.rewards.hold_after_s) == (0.0, 0.02, 4.0)
    assert after.rewards.landing == before.rewards.landing and after.randomization == before.randomization
    assert json.loads((tmp_path / "run" / "config.json").read_text())["training"]["curriculum_stage"]["iteration"] == 2
    assert kl_aims == [cfg["runner"]["algorithm"]["desired_kl"], 0.002, 0.002]


@pytest.mark.parametrize(("stage", "match"), [
    ({"iteration": 100}, "needs exactly 'iteration' and 'desired_kl'"),
    ({"iteration": 100, "desired_kl": 0.002, "lr": 1e-4}, "needs exactly"),
    ({"iteration": -1, "desired_kl": 0.002}, "iteration must be"),
    ({"iteration": 100, "desired_kl": 0.0}, "desired_kl must be > 0"),
    ({"iteration": 100, "desired_kl": float("nan")}, "desired_kl"),
    ([100, 0.002], "needs exactly"),
])
def test_the_desired_kl_stage_refuses_bad_input(stage, match):
    with pytest.raises(ValueError, match=match):
        training_config.TrainingSection.from_dict({"desired_kl_stage": stage})


def test_the_desired_kl_stage_needs_the_adaptive_schedule_and_writes_nothing_without_it(tmp_path):
    import json

    cfg = training_config.load_config("2d", None)
    cfg["runner"]["algorithm"]["schedule"] = "fixed"
    cfg["training"]["desired_kl_stage"] = {"iteration": 100, "desired_kl": 0.002}
    path = tmp_path / "fixed.json"
    path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="needs runner.algorithm.schedule 'adaptive'"):
        train.run(_args(tmp_path, config=path))
    assert not (tmp_path / "run").exists()


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
    assert section.curriculum_stage is None and section.gate_from_iteration == 0
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


def test_release_bias_init_sets_the_first_flag_mean_and_refuses_bad_input(tmp_path):
    """training.release_bias_init: a run from scratch starts with the release flag's mean at the
    bias for every observation (so the first episodes release later than rsl_rl's mean near 0);
    the velocity outputs keep their initialisation; a non-number is refused before anything runs."""
    import json

    cfg = training_config.load_config("2d", None)
    cfg["training"]["release_bias_init"] = -0.35
    path = tmp_path / "biased.json"
    path.write_text(json.dumps(cfg))
    run = train.TrainingRun(_args(tmp_path / "b", seed=3, iterations=0, config=path))
    plain = train.TrainingRun(_args(tmp_path / "p", seed=3, iterations=0))
    obs = run.env.get_observations()
    with torch.no_grad():
        mean = run.runner.alg.actor(obs)  # deterministic mean, (num_envs, num_actions)
        plain_mean = plain.runner.alg.actor(plain.env.get_observations())
    assert torch.allclose(mean[:, -1], torch.full_like(mean[:, -1], -0.35))
    assert plain_mean[:, -1].std() > 0  # rsl_rl's own initialisation depends on the observation
    assert torch.equal(mean[:, :-1], plain_mean[:, :-1])  # the velocity outputs are untouched

    cfg["training"]["release_bias_init"] = "low"
    path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="release_bias_init must be a finite number"):
        train.TrainingRun(_args(tmp_path / "c", config=path))


REF_REL = 1e-4
"""Relative tolerance against tests/data/train_tiny_reference.json: the run is bit for bit the same
on the CPU that recorded it (an Intel Xeon); on an AMD EPYC the same versions give other float
roundings (the observation normaliser's mean 2.3e-6 relative apart after 3 iterations)."""


def test_the_callback_runner_trains_as_the_chunked_loop_did_and_a_resume_continues_the_count(tmp_path):
    """tests/data/train_tiny_reference.json holds a tiny run (a std cap falling over 4 iterations,
    the randomisation widened at iteration 2, chunks of 2, --keep-every 2) as the loop that called
    OnPolicyRunner.learn once per chunk trained it: one learn() with the callbacks gives the same
    curve and parameters (bit for bit on the machine that recorded it; within REF_REL on another
    CPU; other torch / JAX versions draw other numbers). Resumed, the run continues at iteration 4 with
    the cap of iteration 3 (the chunked loop skipped one count on resume)."""
    import json
    import math
    from pathlib import Path

    import jax

    ref = json.loads((Path(__file__).parent / "data" / "train_tiny_reference.json").read_text())
    if (torch.__version__, jax.__version__) != (ref["versions"]["torch"], ref["versions"]["jax"]):
        pytest.skip(f"reference recorded with torch {ref['versions']['torch']}, jax {ref['versions']['jax']}")
    cfg = training_config.load_config("2d", None)
    cfg["training"]["std_schedule"] = {"start": 0.6, "end": 0.08, "iterations": 4}
    cfg["training"]["randomization_stage"] = {"iteration": 2, "randomization": {"friction_scale": [0.5, 10.0]}}
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(cfg))
    run = tmp_path / "run"
    assert train.run(_args(tmp_path, iterations=3, chunk=2, keep_every=2, config=path)) == 0

    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["iter"] == ref["iter"] == 3
    assert sorted(p.name for p in run.glob("*.pt")) == ref["files"] and not list((run / "tb").glob("*.pt"))
    assert ckpt["optimizer_state_dict"]["param_groups"][0]["lr"] == pytest.approx(ref["learning_rate"])
    for group in ("actor", "critic"):
        state = ckpt[f"{group}_state_dict"]
        assert sorted(state) == sorted(ref[group])
        for name, (total, abs_total) in ref[group].items():
            t = state[name].double()
            assert (float(t.sum()), float(t.abs().sum())) == pytest.approx((total, abs_total), rel=REF_REL, abs=1e-9), name
    curve = (run / "curve.csv").read_text().splitlines()
    header = curve[0].split(",")
    rows = [dict(zip(header, map(float, line.split(",")))) for line in curve[1:]]
    assert len(rows) == len(ref["curve"])
    for row, want in zip(rows, ref["curve"]):
        assert {k: row[k] for k in want} == pytest.approx(want, rel=REF_REL, abs=1e-9, nan_ok=True)

    assert train.run(_args(tmp_path, iterations=1, chunk=1, resume=run / "checkpoint.pt", config=path)) == 0
    rows = [line.split(",") for line in (run / "curve.csv").read_text().splitlines()[1:]]
    assert [float(r[0]) for r in rows] == [2, 3, 4] and torch.load(run / "checkpoint.pt", weights_only=False)["iter"] == 4
    cap3 = 0.6 * (0.08 / 0.6) ** (3 / 4)
    std4 = float(rows[-1][header.index("action_std")])
    assert std4 == pytest.approx(cap3, rel=0.02) and not math.isclose(std4, 0.08, rel_tol=0.05)  # cap(4) = 0.08


def test_per_iteration_syncs_and_tf32_train_as_the_plain_run_and_refuse_non_booleans(tmp_path):
    """training.per_iteration_syncs (CallbackRunner change 4) and training.tf32_matmul change how
    fast the run computes, not what: on the CPU (where TF32 does not apply) the tiny run's curve and
    networks are those of the run without them. A setting that is not true or false is refused."""
    import csv
    import json

    cfg = training_config.load_config("2d", None)
    cfg["training"].update(per_iteration_syncs=True, tf32_matmul=True)
    path = tmp_path / "fast.json"
    path.write_text(json.dumps(cfg))
    assert not torch.backends.cuda.matmul.allow_tf32
    assert train.run(_args(tmp_path / "fast", iterations=3, seed=5, config=path)) == 0
    assert not torch.backends.cuda.matmul.allow_tf32  # the run put the process-wide flag back
    assert train.run(_args(tmp_path / "plain", iterations=3, seed=5)) == 0

    def curve(name):
        with open(tmp_path / name / "run" / "curve.csv") as f:
            return [{k: float(v) for k, v in row.items() if k not in ("wall_s", "control_steps_per_s")} for row in csv.DictReader(f)]

    fast, plain = curve("fast"), curve("plain")
    assert len(fast) == 3 and fast[-1]["mean_episode_length"] > 0  # episodes finished: the buffers were filled
    for a, b in zip(fast, plain, strict=True):
        assert a == pytest.approx(b, rel=1e-6, nan_ok=True)
    ckpts = [torch.load(tmp_path / n / "run" / "checkpoint.pt", weights_only=False) for n in ("fast", "plain")]
    for name, t in ckpts[0]["actor_state_dict"].items():
        assert torch.allclose(t, ckpts[1]["actor_state_dict"][name]), name

    cfg["training"]["tf32_matmul"] = "yes"
    path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="training.tf32_matmul must be true or false"):
        train.TrainingRun(_args(tmp_path / "bad", config=path))


def test_max_run_minutes_counts_the_resumed_runs_earlier_time_and_max_minutes_does_not(tmp_path):
    """A run whose curve already holds 60 minutes of training stops after the first chunk of its
    resume under --max-run-minutes 30; --max-minutes 30 (this process's time) trains on."""
    run = tmp_path / "run"
    assert train.run(_args(tmp_path, iterations=2)) == 0
    curve = run / "curve.csv"
    lines = curve.read_text().splitlines()
    col = lines[0].split(",").index("wall_s")
    last = lines[-1].split(",")
    last[col] = "3600.0"  # as if the first machine had trained for an hour
    curve.write_text("\n".join([*lines[:-1], ",".join(last)]) + "\n")
    ckpt = run / "checkpoint.pt"

    assert train.run(_args(tmp_path, iterations=3, resume=ckpt, max_run_minutes=30)) == 0
    assert torch.load(ckpt, weights_only=False)["iter"] == 3  # one chunk (iteration 3), then the budget
    assert train.run(_args(tmp_path, iterations=2, resume=ckpt, max_minutes=30)) == 0
    assert torch.load(ckpt, weights_only=False)["iter"] == 5
