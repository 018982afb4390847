"""The Drake evaluation paired with the MuJoCo site matrix's nominal column (sim_twin.evaluation.drake_evaluate)."""

from __future__ import annotations

import pytest

from sim_twin.evaluation.drake_evaluate import compare_engines, markdown


def _target(d: float, seeds, down, cross) -> dict:
    return {"target_m": d, "per_throw": {"seed": list(seeds), "downrange_error_m": list(down), "crossrange_error_m": list(cross)},
            "throws": len(seeds), "success_rate": 1.0, "bias_m": 0.0, "sigma_downrange_m": 0.0, "mean_crossrange_m": 0.0, "sigma_crossrange_m": 0.0}


def _reports():
    matrix = {"mode": "2d", "policy_version": "p", "seed": 0, "profiles": [
        {"name": "nominal", "targets": [_target(8.0, range(4), [0.01, 0.03, -0.02, 0.05], [0.0, 0.01, 0.0, 0.0])]},
        {"name": "windy_site", "targets": []}]}
    drake = {"mode": "2d", "policy_version": "p", "seed": 0, "profile": "nominal", "throws_per_target": 3,
             "targets": [_target(8.0, [0, 1, 2], [0.11, 0.13, None], [0.0, 0.02, None])]}
    return drake, matrix


def test_the_same_seeds_are_paired_and_judged_by_the_nominal_bars():
    drake, matrix = _reports()
    comp = compare_engines(drake, matrix)
    row = comp["targets"][0]
    assert row["paired"]["n"] == 2 and row["paired"]["downrange_m"] == pytest.approx(0.10)
    assert row["paired"]["crossrange_m"] == pytest.approx(0.005)
    assert row["mujoco"]["landed"] == 3 and row["mujoco"]["bias_m"] == pytest.approx(0.02 / 3)  # seeds 0-2 only
    assert row["drake"]["landed"] == 2 and row["drake"]["success_rate"] == pytest.approx(2 / 3)
    assert row["mujoco"]["bars"] == {"success": True, "accuracy": True}
    assert row["drake"]["bars"]["success"] is False and row["drake"]["bars"]["accuracy"] is False  # bias 0.12 m > 0.10 m
    assert comp["nominal_column_pass"] == {"mujoco": True, "drake": False}
    assert "| 8.0 |" in markdown(comp)


@pytest.mark.parametrize("change, match", [({"mode": "3d"}, "mode"), ({"seed": 1}, "seed"), ({"profile": "x.json"}, "nominal")])
def test_reports_that_do_not_pair_are_refused(change, match):
    drake, matrix = _reports()
    with pytest.raises(ValueError, match=match):
        compare_engines({**drake, **change}, matrix)


def test_a_seed_outside_the_matrix_is_refused():
    drake, matrix = _reports()
    drake["targets"][0]["per_throw"]["seed"] = [0, 1, 7]
    with pytest.raises(ValueError, match="not in the site matrix"):
        compare_engines(drake, matrix)
