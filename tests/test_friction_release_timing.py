"""The friction/release-timing benchmark (tests/benchmarks/friction_release_timing.py): the worn
gripper's friction alone as a loadable profile, throws paired by seed, and the within-target contrast
only where both swing groups are large enough."""

import pytest

from sim_twin.twin.profile import RealityProfile
from tests.benchmarks import friction_release_timing as frt


def _row(seed, err, t, status="landed"):
    return {"seed": seed, "status": status, "downrange_error_m": err, "release_after_s": t}


def test_the_worn_gripper_friction_alone_is_a_loadable_profile(tmp_path):
    spec = frt.friction_profile()
    assert [e["effect"] for e in spec["effects"]] == ["passive_friction"]
    path = tmp_path / "p.json"
    path.write_text(__import__("json").dumps(spec))
    assert [e.name for e in RealityProfile.load(path).effects] == ["passive_friction"]


def test_throws_are_paired_by_seed_and_only_when_landed_in_both():
    nominal = [_row(1, 0.10, 1.1), _row(2, -0.05, 3.0), _row(3, 0.0, 1.0, "collision"), _row(4, 0.02, 1.2)]
    worn = [_row(2, -0.25, 3.1), _row(1, -0.05, 1.1), _row(3, 0.0, 1.0), _row(4, 0.0, 1.2, "no_release")]
    pairs = frt.paired(nominal, worn)
    assert [p["seed"] for p in pairs] == [1, 2]
    assert pairs[0]["shift_m"] == pytest.approx(-0.15) and pairs[0]["first_swing"] is True
    assert pairs[1]["shift_m"] == pytest.approx(-0.20) and pairs[1]["first_swing"] is False
    s = frt.summary(pairs, 3, 3, 4)
    assert s["paired"] == 2 and s["first_swing"] == 1
    assert s["mean_miss_nominal_m"] == pytest.approx(0.075) and s["mean_miss_worn_m"] == pytest.approx(0.15)
    assert s["mean_shift_first_swing_m"] == pytest.approx(-0.15) and s["mean_shift_later_m"] == pytest.approx(-0.20)
    empty = frt.summary([], 0, 0, 4)
    assert empty["mean_shift_m"] is None and empty["mean_miss_worn_m"] is None


def test_the_within_target_contrast_needs_both_groups():
    def cell(target, n_first, n_later, first_shift, later_shift):
        pairs = [{"first_swing": True, "shift_m": first_shift}] * n_first + [{"first_swing": False, "shift_m": later_shift}] * n_later
        return {"policy": "p", "target_m": target, "paired": n_first + n_later, "first_swing": n_first,
                "mean_shift_first_swing_m": first_shift if n_first else None, "mean_shift_later_m": later_shift if n_later else None,
                "pairs": pairs}

    figs = frt.figures([cell(8.0, 50, 50, -0.10, -0.14), cell(10.0, 95, 5, -0.30, -0.50)])
    by = {f["what"]: f for f in figs}
    assert by["p: first-swing releases"]["value"] == pytest.approx(72.5)
    assert by["p: later minus first-swing shift, same target"]["value"] == pytest.approx(-0.04)  # 10 m has too few later throws
    assert "8 m" in by["p: later minus first-swing shift, same target"]["conditions"]
    only_first = frt.figures([cell(8.0, 100, 0, -0.1, None)])
    assert not any("later minus" in f["what"] for f in only_first)
