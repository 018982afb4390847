"""The committed training recipes are the ones the committed from-scratch runs were made with, so
`slinger train --mode 2d|3d` reproduces them (docs/training.md). A run's saved config.json must equal
sim_twin/configs/throw_<mode>.json but for the free-text ``notes``."""

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNS = {"2d": "throw2d-scratch-l", "3d": "throw3d-scratch-l"}
ALL_RUNS = [("2d", "throw2d-scratch-l"), ("2d", "throw2d-scratch-m"), ("3d", "throw3d-scratch-l")]
"""Every committed from-scratch run of the committed recipes (RUNS: the one per mode the docs quote first)."""


def _without_notes(path: Path) -> dict:
    cfg = json.loads(path.read_text())
    cfg.pop("notes", None)
    return cfg


@pytest.mark.parametrize(("mode", "run_name"), ALL_RUNS)
def test_the_committed_recipe_is_the_one_the_from_scratch_run_used(mode, run_name):
    recipe = _without_notes(ROOT / "sim_twin" / "configs" / f"throw_{mode}.json")
    run = _without_notes(ROOT / "policies" / "training" / run_name / "config.json")
    assert recipe == run


def test_a_changed_recipe_would_be_caught():
    recipe = _without_notes(ROOT / "sim_twin" / "configs" / "throw_2d.json")
    recipe["runner"]["algorithm"]["gamma"] = 0.99
    assert recipe != _without_notes(ROOT / "policies" / "training" / RUNS["2d"] / "config.json")


def test_the_2d_run_exported_a_policy_that_met_every_bar_on_two_seeds():
    card = json.loads((ROOT / "policies" / "training" / RUNS["2d"] / "throw2d.card.json").read_text())
    gate = json.loads((ROOT / "policies" / "training" / RUNS["2d"] / "matrices" / "matrix_gate.json").read_text())
    assert card["bars_met"] is True
    passing = {(r["iteration"], r["seed"]) for r in gate["results"] if r["passed"]}
    assert {(card["iteration"], 0), (card["iteration"], 1)} <= passing
