"""Anchoring the aim table to the site's logged impacts (sim_twin.adaptation.aim_anchor) and its use by
``slinger adapt``: a fitted profile that predicts the wrong closed-loop bias (another,
replay-equivalent effect) still gives the right correction once the logged throws are in."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.aim import AIM_FORMAT
from runtime.policy import PolicyRunner
from sim_twin.adaptation import adapt as ad
from sim_twin.adaptation.aim_anchor import MIN_THROWS, anchor_table, fit_residual, logged_errors
from sim_twin.twin.profile import RealityProfile
from tests.fixtures import write_test_policy

Y = -0.292  # the 2D targets' crossrange position (sim_twin.evaluation.evaluate.target_on_axis)


def _write_dataset(path, rows):
    path.mkdir(parents=True, exist_ok=True)
    (path / "index.json").write_text(json.dumps({"machine_id": "sim", "throws": rows}))
    return path


def _row(d, err_down, version="v", status="landed", mode="2d"):
    return {"throw_id": f"t{d}{err_down}", "mode": mode, "status": status, "policy_version": version,
            "target_m": [d, Y, 0.0], "impact_m": [d + err_down, Y, 0.0]}


def test_logged_errors_keep_only_the_base_versions_landed_throws(tmp_path):
    ds = _write_dataset(tmp_path / "ds", [_row(8.0, 0.3), _row(9.0, 0.5), _row(8.0, 9.0, version="other"),
                                          _row(8.5, 0.0, status="failed"), {**_row(8.5, 0.0), "impact_m": None},
                                          _row(8.0, 1.0, mode="3d")])
    got = logged_errors(ds, "v", "2d")
    assert got["distance_m"] == pytest.approx(np.hypot([8.0, 9.0], Y))
    assert got["down_m"] == pytest.approx([0.3, 0.5], abs=2e-3)  # the target is off the x axis: downrange is along it
    assert got["skipped"] == {"other policy": 1, "not landed": 1, "no measured impact": 1, "other mode": 1}
    with pytest.raises(FileNotFoundError):
        logged_errors(tmp_path / "missing", "v", "2d")


def test_fit_residual_line_and_constant():
    d = np.repeat([7.5, 8.0, 8.5, 9.0, 9.5], 6)
    fit = fit_residual(d, 0.1 + 0.2 * (d - 8.5))
    assert fit["kind"] == "linear" and fit["coef"] == pytest.approx([0.1, 0.2]) and fit["centre_m"] == pytest.approx(8.5)
    near = fit_residual(np.array([8.0, 8.2] * 10), np.array([0.3, 0.5] * 10))  # span < 1 m: a constant
    assert near["kind"] == "constant" and near["coef"] == pytest.approx([0.4, 0.0])
    assert near["cov"][0][0] == pytest.approx(0.1**2 * 20 / 19 / 20)
    with pytest.raises(ValueError, match="at least 2"):
        fit_residual(np.array([8.0]), np.array([0.1]))


def _history(dist, bias0):
    return [{"round": 0, "downrange_offset_m": [0.0] * len(dist), "crossrange_offset_m": [0.0] * len(dist),
             "bias_m": list(bias0), "mean_crossrange_m": [0.0] * len(dist)}]


def test_anchor_aims_so_that_the_site_lands_on_target():
    """The fitted profile predicts -0.1 m where the site's throws show +0.2 + 0.1 m/m (its bias
    grows with the throw): the anchored aims land the site's throws on target, with the bias
    taken where the policy is aimed (not at the target: that would miss by 0.1 x offset)."""
    dist = [7.5, 8.5, 9.5, 10.0]
    table = {"format": AIM_FORMAT, "distances_m": dist, "downrange_offset_m": [0.1] * 4, "crossrange_offset_m": [0.0] * 4}

    def site(aim):
        return aim + 0.2 + 0.1 * (aim - 8.5)

    rng = np.random.default_rng(0)
    d = np.repeat([7.5, 8.0, 8.5, 9.0, 9.5], 6)
    logged = {"distance_m": d, "down_m": site(d) - d + rng.normal(0, 1e-4, len(d)), "cross_m": np.zeros(len(d))}
    new, info = anchor_table(table, _history(dist, [-0.1] * 4), logged, "2d")
    aims = np.array(dist) + new["downrange_offset_m"]
    assert info["applied"] and site(aims) == pytest.approx(dist, abs=1e-3)
    assert info["down_fit"]["kind"] == "linear" and info["down_fit"]["coef"] == pytest.approx([0.3, 0.1], abs=1e-3)
    assert new["crossrange_offset_m"] == [0.0] * 4  # 2D: downrange only
    assert new["anchor"]["twin_downrange_offset_m"] == [0.1] * 4 and max(info["se_down_m"]) < 0.01
    few = {k: v[: MIN_THROWS - 1] for k, v in logged.items()}
    same, info = anchor_table(table, _history(dist, [-0.1] * 4), few, "2d")
    assert same is table and not info["applied"] and "logged throws" in info["reason"]


def test_anchor_refuses_a_site_no_aim_reaches():
    dist = [8.0, 9.0]
    table = {"format": AIM_FORMAT, "distances_m": dist, "downrange_offset_m": [0.0] * 2, "crossrange_offset_m": [0.0] * 2}
    d = np.repeat([8.0, 9.0], 6)
    logged = {"distance_m": d, "down_m": np.full(len(d), -10.0), "cross_m": np.zeros(len(d))}  # 10 m short: beyond any aim
    with pytest.raises(ValueError, match="no aim"):
        anchor_table(table, _history(dist, [0.0, 0.0]), logged, "2d")


def test_adapt_anchors_to_the_diagnosis_dataset(monkeypatch, tmp_path):
    """End to end with a fake twin whose fitted-profile bias is -0.1 m (the site's is +0.25 m):
    without the logged throws the table is +0.1 m, with them -0.25 m."""
    onnx = write_test_policy(tmp_path / "base", "2d")
    monkeypatch.setattr(ad, "_measure", lambda policy, mode, pp, distances, *a: {
        float(x): (-0.1 + (PolicyRunner.load(policy).aim_correction.offsets_at(x)[0] if PolicyRunner.load(policy).aim_correction else 0.0),
                   0.0, 5, 0.1) for x in distances})
    version = PolicyRunner.load(onnx).version
    ds = _write_dataset(tmp_path / "ds", [_row(x, 0.25, version=version) for x in np.repeat([7.5, 8.0, 8.5, 9.0, 9.5], 4)])
    prof = RealityProfile(name="fitted-cabin_drift")
    plain = ad.adapt(prof, onnx, tmp_path / "a", method="aim", throws=3, rounds=2, distances_m=[8.0, 9.0])
    assert plain["aim_correction"]["downrange_offset_m"] == pytest.approx([0.1, 0.1]) and not plain["anchor"]["applied"]
    res = ad.adapt(prof, onnx, tmp_path / "b", method="aim", throws=3, rounds=2, distances_m=[8.0, 9.0],
                   diagnosis_report={"dataset": str(ds), "which": []})
    assert res["anchor"]["applied"] and res["anchor"]["throws"] == 20
    assert PolicyRunner.load(res["policy"]).aim_correction.offsets_at(8.5)[0] == pytest.approx(-0.25, abs=1e-3)
