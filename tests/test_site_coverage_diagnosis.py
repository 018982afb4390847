"""The site-coverage diagnosis (tests/benchmarks/site_coverage_diagnosis.py) splits a committed site
profile into one profile per effect that a simulated machine loads, and refuses a profile with
nothing to split."""

import json
from pathlib import Path

import pytest

from sim_twin.twin.profile import RealityProfile
from tests.benchmarks.site_coverage_diagnosis import split_profile


def test_worn_gripper_splits_into_loadable_single_effect_profiles(tmp_path: Path):
    names = split_profile("worn_gripper", tmp_path)
    assert names == ["worn_gripper", "worn_gripper__release_delay", "worn_gripper__passive_friction"]
    whole = RealityProfile.load(tmp_path / "worn_gripper.json")
    assert [e.name for e in whole.effects] == ["release_delay", "passive_friction"]
    for part, effect in zip(names[1:], ["release_delay", "passive_friction"]):
        prof = RealityProfile.load(tmp_path / f"{part}.json")
        assert [e.name for e in prof.effects] == [effect]
    delay = RealityProfile.load(tmp_path / "worn_gripper__release_delay.json").effects[0]
    assert delay.to_dict()["params"]["mean_s"] == pytest.approx(0.34)


def test_a_plugin_effect_part_is_named_by_its_class(tmp_path: Path):
    names = split_profile("heavy_windy", tmp_path)
    assert names[-1] == "heavy_windy__CrossWind"
    assert json.loads((tmp_path / "heavy_windy__CrossWind.json").read_text())["effects"][0]["params"] == {"wind_mps": 5.0}


@pytest.mark.parametrize("name, error", [("sensor_latency", ValueError), ("no_such_site", FileNotFoundError)])
def test_nothing_to_split_is_refused(tmp_path: Path, name, error):
    with pytest.raises(error):
        split_profile(name, tmp_path)


def test_a_split_profile_is_thrown_at_from_its_own_directory(tmp_path: Path, fixture_policy):
    from sim_twin.evaluation.matrix import run_matrix

    split_profile("worn_gripper", tmp_path)
    rep = run_matrix(fixture_policy("2d"), "2d", [8.5], 2, profiles=[("worn_gripper__release_delay", True)], workers=1, profile_dir=tmp_path)
    cell = rep["profiles"][0]["targets"][0]
    assert rep["profiles"][0]["name"] == "worn_gripper__release_delay" and cell["throws"] == 2
    assert cell["per_throw"]["seed"] == [0, 1]
    with pytest.raises(FileNotFoundError):  # not looked up in sim_twin/profiles
        run_matrix(fixture_policy("2d"), "2d", [8.5], 1, profiles=[("worn_gripper", True)], profile_dir=tmp_path / "empty")
