"""Evaluation by the paper's protocol, and the deployed 2D policy's bar (issue: it must
genuinely throw: at an 8.5 m target in the nominal simulated machine its impacts land within
1.0 m on average over 20 throws from random initial arm poses)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_twin.evaluation.evaluate import evaluate, summarise, target_on_axis
from sim_twin.evaluation.cli import markdown_table, parse_targets

POLICY_2D = Path(__file__).resolve().parents[1] / "policies" / "throw2d.onnx"


def test_parse_targets():
    assert parse_targets("7.5:10:0.5") == [7.5, 8.0, 8.5, 9.0, 9.5, 10.0]
    assert parse_targets("8.5") == [8.5]
    assert parse_targets("7,9") == [7.0, 9.0]
    with pytest.raises(ValueError):
        parse_targets("7:9:0")


def test_target_on_axis_distance():
    for mode in ("2d", "3d"):
        t = target_on_axis(mode, 8.5)
        assert np.hypot(t[0], t[1]) == pytest.approx(8.5)
        assert t[2] == 0.0


def test_summarise_statistics():
    rows = [
        {"status": "landed", "downrange_error_m": e, "crossrange_error_m": -e / 2, "duration_s": 2.0}
        for e in (0.1, 0.3)
    ] + [{"status": "failed", "reason": "ground collision"}]
    s = summarise(8.0, rows)
    assert s["success_rate"] == pytest.approx(2 / 3)
    assert s["bias_m"] == pytest.approx(0.2)
    assert s["sigma_downrange_m"] == pytest.approx(0.1)
    assert s["mean_impact_m"] == pytest.approx(8.2)
    assert s["failures"] == {"ground collision": 1}
    assert "| 8.0 |" in markdown_table({"mode": "2d", "policy": "p", "throws_per_target": 3, "profile": "nominal", "targets": [s]})


def test_deployed_2d_policy_hits_8p5_m_within_1_m_over_20_throws():
    report = evaluate(POLICY_2D, "2d", [8.5], throws=20, seed=7, workers=2)
    t = report["targets"][0]
    assert t["throws"] == 20
    assert t["success_rate"] == 1.0
    assert t["mean_abs_error_m"] < 1.0
    # tighter than the bar, from the measured 200-throw evaluation (|bias| ~1 cm, sigma ~3 cm)
    assert abs(t["bias_m"]) < 0.15 and t["sigma_downrange_m"] < 0.15
