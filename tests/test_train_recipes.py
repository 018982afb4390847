"""The committed training recipes are the ones the committed from-scratch runs were made with, so
`slinger train --mode 2d|3d` reproduces them (docs/training.md). A run's saved config.json must equal
sim_twin/configs/throw_<mode>.json but for the free-text ``notes`` and the training seed (given by
``--seed``; the recipe's ``training.seed`` is that of the run the docs quote, RUNS). The runs of
earlier recipes and the experiments are in the lab notebook (policies/training/ARCHIVE.md)."""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNS = {"2d": "throw2d-scratch-u", "3d": "throw3d-scratch-t"}
ALL_RUNS = [("2d", "throw2d-scratch-u"), ("2d", "throw2d-scratch-aa"), ("3d", "throw3d-scratch-t")]
"""Every committed from-scratch run of the committed recipes (RUNS: the one per mode the docs quote first)."""
EXPORTED_2D = ["throw2d-scratch-u", "throw2d-scratch-aa"]
"""The committed from-scratch 2D runs whose gate met every bar on two seeds and exported their policy."""


def _without_notes(path: Path) -> dict:
    """The config at ``path`` without its free-text notes and its training seed."""
    cfg = json.loads(path.read_text())
    cfg.pop("notes", None)
    cfg.get("training", {}).pop("seed", None)
    return cfg


def _run_seed(run_name: str) -> int:
    """The training seed a committed run used: its config's ``training.seed`` where it records one,
    else the ``--seed`` of its model card's command."""
    run = ROOT / "policies" / "training" / run_name
    cfg = json.loads((run / "config.json").read_text())
    if "seed" in cfg.get("training", {}):
        return cfg["training"]["seed"]
    card = json.loads(next(run.glob("throw*.card.json")).read_text())
    return int(re.search(r"--seed (\d+)", card["command"]).group(1))


@pytest.mark.parametrize(("mode", "run_name"), ALL_RUNS)
def test_the_committed_recipe_is_the_one_the_from_scratch_run_used(mode, run_name):
    recipe = _without_notes(ROOT / "sim_twin" / "configs" / f"throw_{mode}.json")
    run = _without_notes(ROOT / "policies" / "training" / run_name / "config.json")
    assert recipe == run


@pytest.mark.parametrize(("mode", "run_name"), sorted(RUNS.items()))
def test_the_recipes_training_seed_is_that_of_the_run_the_docs_quote(mode, run_name):
    recipe = json.loads((ROOT / "sim_twin" / "configs" / f"throw_{mode}.json").read_text())
    assert recipe["training"]["seed"] == _run_seed(run_name)


def test_a_changed_recipe_would_be_caught():
    recipe = _without_notes(ROOT / "sim_twin" / "configs" / "throw_2d.json")
    recipe["runner"]["algorithm"]["gamma"] = 0.99
    assert recipe != _without_notes(ROOT / "policies" / "training" / RUNS["2d"] / "config.json")


@pytest.mark.parametrize("run_name", EXPORTED_2D)
def test_the_2d_run_exported_a_policy_that_met_every_bar_on_two_seeds(run_name):
    card = json.loads((ROOT / "policies" / "training" / run_name / "throw2d.card.json").read_text())
    gate = json.loads((ROOT / "policies" / "training" / run_name / "matrices" / "matrix_gate.json").read_text())
    assert card["bars_met"] is True
    passing = {(r["iteration"], r["seed"]) for r in gate["results"] if r["passed"]}
    assert {(card["iteration"], 0), (card["iteration"], 1)} <= passing


CANDIDATE_2D = {("runner", "algorithm", "gamma"): 1.0, ("runner", "algorithm", "use_mixed_precision"): True,
                ("runner", "torch_compile_mode"): "default",
                ("runner", "actor", "class_name"): "sim_twin.training.models:Float32MLPModel",
                ("env", "forced_release", "probability"): 0.0,
                ("training", "curriculum_stage", "iteration"): 300,
                ("training", "curriculum_stage", "rewards", "err_3d"): 0.0,
                ("training", "curriculum_stage", "rewards", "hold"): 0.01,
                ("training", "curriculum_stage", "rewards", "hold_after_s"): 5.0,
                ("training", "per_iteration_syncs"): True}
"""What the next attempt's 2D recipe (sim_twin/configs/throw_2d_candidate.json) changes, and to what."""


def _flat(cfg: dict, prefix: tuple = ()) -> dict:
    out = {}
    for k, v in cfg.items():
        out.update(_flat(v, prefix + (k,)) if isinstance(v, dict) else {prefix + (k,): v})
    return out


def test_the_candidate_recipe_changes_only_what_it_declares():
    recipe = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d.json"))
    candidate = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_candidate.json"))
    changed = {k for k in recipe.keys() | candidate.keys() if recipe.get(k) != candidate.get(k)}
    assert changed == set(CANDIDATE_2D)
    assert {k: candidate[k] for k in CANDIDATE_2D} == CANDIDATE_2D
    # the runs it follows on: gamma 1.0, bfloat16 update, compile with rsl_rl's MLPModel actor and the
    # forced release; then with the float32 actor (training seeds 25-28), the forced release still on;
    # then without it (training seeds 29-32); each with the dense err_3d term and no hold cost; then
    # with err_3d 0 and the hold cost from the first step (training seeds 33-34), then from 5 s of
    # episode time on (training seeds 35-38); the candidate keeps err_3d to iteration 300, then drops
    # it and charges the hold cost after 5 s (its curriculum stage)
    forced = ("env", "forced_release", "probability")
    err_3d = ("env", "rewards", "err_3d")
    hold, grace = ("env", "rewards", "hold"), ("env", "rewards", "hold_after_s")
    stage = {k for k in CANDIDATE_2D if k[:2] == ("training", "curriculum_stage")} | {("training", "per_iteration_syncs")}
    # (the one GPU wait per rollout came after every run below: how fast, not what, they computed)
    actor = ("runner", "actor", "class_name")
    for run_name, differs in [*((f"throw2d-scratch-{n}", {actor, forced, *stage}) for n in ("ap", "at", "au")),
                              *((f"throw2d-scratch-{n}", {forced, *stage}) for n in ("ax", "ay", "az", "aw")),
                              *((f"throw2d-scratch-b{i}", stage) for i in range(4)),
                              *((f"throw2d-scratch-c{i}", {err_3d, hold, *stage}) for i in range(2)),
                              *((f"throw2d-scratch-d{i}", {err_3d, hold, grace, *stage}) for i in range(4))]:
        run = _flat(_without_notes(ROOT / "policies" / "training" / run_name / "config.json"))
        assert {k for k in run.keys() | candidate.keys() if run.get(k) != candidate.get(k)} == differs, run_name
        assert run[forced] == (0.0 if run_name[-2] in "bcd" else 0.05)
        if run_name[-2] in "cd":  # the hold cost from the first iteration: from the first step (c), after 5 s (d)
            assert run[hold] == 0.01 and run.get(grace, 0.0) == (5.0 if run_name[-2] == "d" else 0.0)
            continue
        assert run[err_3d] == recipe[err_3d] == 0.05


def test_the_nominal_share_recipe_is_the_candidate_with_only_its_nominal_fraction():
    """sim_twin/configs/throw_2d_nominal.json: the candidate with a quarter of the episodes on the nominal
    machine (env.randomization.nominal_fraction), the change the far-target overshoot points to."""
    candidate = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_candidate.json"))
    nominal = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_nominal.json"))
    changed = {k for k in candidate.keys() | nominal.keys() if candidate.get(k) != nominal.get(k)}
    assert changed == {("env", "randomization", "nominal_fraction")}
    assert nominal[("env", "randomization", "nominal_fraction")] == 0.25


def test_the_history_recipe_is_the_candidate_with_only_a_longer_observation_history():
    """sim_twin/configs/throw_2d_history.json: the candidate with 8 control steps of joint history
    (env.history_steps) in place of the paper's 4, nothing else changed; its environment builds
    96-value observations."""
    from runtime.observation import observation_size
    from sim_twin.training.mjx_env import EnvConfig

    path = ROOT / "sim_twin" / "configs" / "throw_2d_history.json"
    candidate = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_candidate.json"))
    history = _flat(_without_notes(path))
    changed = {k for k in candidate.keys() | history.keys() if candidate.get(k) != history.get(k)}
    assert changed == {("env", "history_steps")}
    cfg = EnvConfig.from_dict(json.loads(path.read_text())["env"])
    assert cfg.history_steps == 8 and observation_size("2d", cfg.history_steps) == 96


def test_the_sites_recipe_is_the_history_recipe_widened_at_its_curriculum_stage():
    """sim_twin/configs/throw_2d_sites.json: the history recipe whose curriculum stage also widens the
    randomisation over the worn gripper's friction and release delay and the windy site's wind, nothing
    else changed; before the stage its environment is the history recipe's, after it the worn gripper's
    friction (x10) and 340 ms release delay lie inside the ranges and episodes draw a wind."""
    from sim_twin.training.config import CurriculumStage
    from sim_twin.training.privileged import Randomization
    from sim_twin.twin.effects.friction import PassiveFriction

    path = ROOT / "sim_twin" / "configs" / "throw_2d_sites.json"
    history = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_history.json"))
    sites = _flat(_without_notes(path))
    stage = ("training", "curriculum_stage", "randomization")
    changed = {k for k in history.keys() | sites.keys() if history.get(k) != sites.get(k)}
    assert changed == {(*stage, "friction_scale"), (*stage, "friction_sampling"), (*stage, "release_delay_shift_s"),
                       (*stage, "wind_mps")}
    cfg = json.loads(path.read_text())
    before, after = CurriculumStage.from_dict(cfg["training"]["curriculum_stage"]).env_dicts(cfg["env"])
    assert before["randomization"] == cfg["env"]["randomization"]
    wide = Randomization.from_dict(after["randomization"])
    worn, windy = (_profile_params(name) for name in ("worn_gripper", "windy_site"))
    nominal = {p.name: p.nominal for p in PassiveFriction.params}
    worn_friction = max(worn["passive_friction"][k] / nominal[k] for k in nominal)  # x10 (viscous 0.3 against 0.03)
    assert wide.friction_scale[0] <= 1.0 <= worn_friction <= wide.friction_scale[1] and wide.friction_sampling == "log_uniform"
    worn_delay_s = worn["release_delay"]["mean_s"]
    assert wide.release_delay_mean_s + wide.release_delay_shift_s + 2 * wide.release_delay_std_s >= worn_delay_s
    assert wide.wind_mps == windy["sim_twin.diagnosis.unmodelled:CrossWind"]["wind_mps"]


def test_the_settle_recipe_is_the_sites_recipe_with_only_a_smaller_kl_aim_late():
    """sim_twin/configs/throw_2d_sites_settle.json: throw_2d_sites.json with training.desired_kl_stage
    (a quarter of the recipe's KL aim, from an iteration past the sites recipe's curriculum stage),
    nothing else changed."""
    from sim_twin.training.config import TrainingSection

    path = ROOT / "sim_twin" / "configs" / "throw_2d_sites_settle.json"
    sites = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_sites.json"))
    settle = _flat(_without_notes(path))
    changed = {k for k in sites.keys() | settle.keys() if sites.get(k) != settle.get(k)}
    assert changed == {("training", "desired_kl_stage", "iteration"), ("training", "desired_kl_stage", "desired_kl")}
    cfg = json.loads(path.read_text())
    section = TrainingSection.from_dict(cfg["training"])
    assert section.desired_kl_stage.desired_kl == cfg["runner"]["algorithm"]["desired_kl"] / 4
    assert section.desired_kl_stage.iteration > section.curriculum_stage.iteration


def test_the_fewer_winds_recipe_is_the_settle_recipe_with_wind_in_a_quarter_of_the_episodes():
    """sim_twin/configs/throw_2d_sites_fewer_winds.json: throw_2d_sites_settle.json with the stage's
    wind in a quarter of the episodes (randomization.wind_fraction 0.25), nothing else changed; the
    merged stage is one the training accepts."""
    from sim_twin.training.config import TrainingSection
    from sim_twin.training.privileged import Randomization

    path = ROOT / "sim_twin" / "configs" / "throw_2d_sites_fewer_winds.json"
    settle = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_sites_settle.json"))
    fewer = _flat(_without_notes(path))
    changed = {k for k in settle.keys() | fewer.keys() if settle.get(k) != fewer.get(k)}
    assert changed == {("training", "curriculum_stage", "randomization", "wind_fraction")}
    cfg = json.loads(path.read_text())
    _, after = TrainingSection.from_dict(cfg["training"]).curriculum_stage.env_dicts(cfg["env"])
    wide = Randomization.from_dict(after["randomization"])
    assert wide.wind_fraction == 0.25 and wide.wind_mps == 5.0


def _profile_params(name: str) -> dict[str, dict]:
    """{effect: params} of the site profile sim_twin/profiles/<name>.json."""
    profile = json.loads((ROOT / "sim_twin" / "profiles" / f"{name}.json").read_text())
    return {e["effect"]: e["params"] for e in profile["effects"]}


def test_the_3d_history_recipe_is_the_3d_recipe_with_only_a_longer_observation_history():
    """sim_twin/configs/throw_3d_history.json: throw_3d.json with 8 control steps of joint history,
    nothing else changed; its environment builds 113-value observations."""
    from runtime.observation import observation_size
    from sim_twin.training.mjx_env import EnvConfig

    path = ROOT / "sim_twin" / "configs" / "throw_3d_history.json"
    recipe = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_3d.json"))
    history = _flat(_without_notes(path))
    assert {k for k in recipe.keys() | history.keys() if recipe.get(k) != history.get(k)} == {("env", "history_steps")}
    cfg = EnvConfig.from_dict(json.loads(path.read_text())["env"])
    assert cfg.mode == "3d" and observation_size("3d", cfg.history_steps) == 113


def test_the_centred_recipe_puts_the_nominal_machine_near_the_middle_of_its_ranges():
    """sim_twin/configs/throw_2d_centred.json: the candidate with the ranges that had the nominal
    machine at their fast, light end moved so that it sits near their middle (friction in its
    logarithm), each keeping the slow or heavy end the site profiles need; nothing else changed."""
    import math

    from sim_twin.training.mjx_env import nominal_machine

    rand = ("env", "randomization")
    candidate = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_candidate.json"))
    centred = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_centred.json"))
    changed = {k for k in candidate.keys() | centred.keys() if candidate.get(k) != centred.get(k)}
    moved = {"dead_band", "valve_delay_s", "lag_s", "velocity_scale", "friction_scale", "gripper_mass_scale"}
    assert changed == {(*rand, name) for name in moved | {"friction_sampling"}}
    assert centred[(*rand, "friction_sampling")] == "log_uniform"
    nominal = nominal_machine()
    for name in moved:
        lo, hi = centred[(*rand, name)]
        old_lo, old_hi = candidate[(*rand, name)]
        assert lo <= old_lo and (hi == old_hi or name == "velocity_scale"), name  # wider, never narrower
        if name == "velocity_scale":  # the slow end is the low one: kept, the fast end widened
            assert lo == old_lo and hi > old_hi
        if name == "friction_scale":
            middle, width = math.sqrt(lo * hi), math.log(hi / lo)
            assert abs(math.log(middle / nominal[name])) < 0.01 * width
        else:
            middle, width = (lo + hi) / 2, hi - lo
            old_off = abs((old_lo + old_hi) / 2 - nominal[name]) / (old_hi - old_lo)
            assert abs(middle - nominal[name]) / width < min(0.1, old_off), (name, middle, nominal[name])


def test_the_later_swing_recipe_is_the_fewer_winds_recipe_with_a_cost_on_first_swing_releases():
    """sim_twin/configs/throw_2d_sites_later_swing.json: throw_2d_sites_fewer_winds.json with the
    early_release cost (0.5 per control step that ends with the release commanded by 2.0 s), nothing
    else changed; the rewards load."""
    from sim_twin.training.rewards import RewardScales

    path = ROOT / "sim_twin" / "configs" / "throw_2d_sites_later_swing.json"
    fewer = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_2d_sites_fewer_winds.json"))
    later = _flat(_without_notes(path))
    changed = {k for k in fewer.keys() | later.keys() if fewer.get(k) != later.get(k)}
    assert changed == {("env", "rewards", "early_release"), ("env", "rewards", "early_release_s")}
    w = RewardScales.from_dict(json.loads(path.read_text())["env"]["rewards"])
    assert (w.early_release, w.early_release_s) == (0.5, 2.0)


def test_the_later_swing_delay_recipe_widens_only_the_stages_release_delay_shift_to_cover_the_worn_gripper():
    """sim_twin/configs/throw_2d_sites_later_swing_delay.json: throw_2d_sites_later_swing.json with the
    curriculum stage's release-delay episode shift at ±90 ms, nothing else changed; the worn gripper's
    opening delay (sim_twin/profiles/worn_gripper.json) lies inside the shifted range and outside the
    later-swing recipe's."""
    base = ROOT / "sim_twin" / "configs"
    later = _flat(_without_notes(base / "throw_2d_sites_later_swing.json"))
    delay = _flat(_without_notes(base / "throw_2d_sites_later_swing_delay.json"))
    key = ("training", "curriculum_stage", "randomization", "release_delay_shift_s")
    assert {k for k in later.keys() | delay.keys() if later.get(k) != delay.get(k)} == {key}
    worn = next(e for e in json.loads((ROOT / "sim_twin" / "profiles" / "worn_gripper.json").read_text())["effects"]
                if e["effect"] == "release_delay")
    nominal_s = delay[("env", "randomization", "release_delay_mean_s")]
    assert later[key] < worn["params"]["mean_s"] - nominal_s <= delay[key]


def test_the_3d_sites_recipe_is_the_3d_recipe_widened_over_the_worn_gripper_at_its_stage():
    """sim_twin/configs/throw_3d_sites.json: throw_3d.json with a curriculum stage that widens only the
    passive friction (log-uniform) and the release-delay shift, nothing else changed; before the stage
    its environment is the 3D recipe's, after it the worn gripper's friction (x10) and 340 ms opening
    delay lie inside the ranges, which they did not before."""
    from sim_twin.training.config import CurriculumStage
    from sim_twin.training.privileged import Randomization
    from sim_twin.twin.effects.friction import PassiveFriction

    path = ROOT / "sim_twin" / "configs" / "throw_3d_sites.json"
    recipe = _flat(_without_notes(ROOT / "sim_twin" / "configs" / "throw_3d.json"))
    sites = _flat(_without_notes(path))
    stage = ("training", "curriculum_stage")
    changed = {k for k in recipe.keys() | sites.keys() if recipe.get(k) != sites.get(k)}
    assert changed == {(*stage, "iteration"), (*stage, "randomization", "friction_scale"),
                       (*stage, "randomization", "friction_sampling"), (*stage, "randomization", "release_delay_shift_s")}
    cfg = json.loads(path.read_text())
    before, after = CurriculumStage.from_dict(cfg["training"]["curriculum_stage"]).env_dicts(cfg["env"])
    assert before["randomization"] == cfg["env"]["randomization"] and before["mode"] == after["mode"] == "3d"
    narrow, wide = Randomization.from_dict(before["randomization"]), Randomization.from_dict(after["randomization"])
    worn = _profile_params("worn_gripper")
    nominal = {p.name: p.nominal for p in PassiveFriction.params}
    worn_friction = max(worn["passive_friction"][k] / nominal[k] for k in nominal)
    assert narrow.friction_scale[1] < worn_friction <= wide.friction_scale[1] and wide.friction_sampling == "log_uniform"
    worn_delay_s = worn["release_delay"]["mean_s"]
    assert narrow.release_delay_mean_s + narrow.release_delay_shift_s < worn_delay_s
    assert worn_delay_s <= wide.release_delay_mean_s + wide.release_delay_shift_s
