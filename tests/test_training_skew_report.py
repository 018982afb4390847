"""tests.benchmarks.training_skew_report: the skew is nominal minus training distribution, paired throw
by throw over the throws that landed in both; an input without the training-distribution rollout is
refused with a message and writes nothing."""

import json

import pytest

from tests.benchmarks import training_skew_report as skew


def _bench(nominal: list[float | None], dist: list[float | None]) -> dict:
    def rows(xs):  # the rows training_twin_bias writes, the release quantities left at 0
        release = dict.fromkeys(("release_cmd_s", "opening_s", "speed_mps", "elevation_deg", "height_m",
                                 "release_downrange_m", "flight_s", "ballistic_downrange_m"), 0.0)
        return [{**release, "seed": k, "landed": x is not None, "downrange_m": 0.0 if x is None else x} for k, x in enumerate(xs)]

    return {"args": {"policy": "p.onnx", "config": "c.json"},
            "env": {"env": {"10.0": rows(nominal)}, "training-dist": {"10.0": rows(dist)}}}


def test_the_skew_is_paired_over_throws_landed_in_both(tmp_path):
    # the third throw did not land in the training distribution: it leaves the pairs, not the nominal mean
    bench = _bench([0.10, 0.12, 0.50, 0.08], [0.00, 0.04, None, 0.02])
    (row,) = skew.skew_rows(bench)
    assert row["pairs"] == 3
    assert row["skew_m"] == pytest.approx((0.10 + 0.08 + 0.06) / 3)
    assert row["nominal_bias_m"] == pytest.approx(0.20)
    assert row["training_dist_bias_m"] == pytest.approx(0.02)
    (tmp_path / "a.json").write_text(json.dumps(bench))
    assert skew.main([f"run a={tmp_path / 'a.json'}", "--out", str(tmp_path / "out" / "skew")]) == 0
    rep = json.loads((tmp_path / "out" / "skew.json").read_text())
    assert rep["policies"][0]["label"] == "run a" and rep["policies"][0]["rows"][0]["pairs"] == 3
    assert "**+0.080**" in (tmp_path / "out" / "skew.md").read_text()
    assert (tmp_path / "out" / "skew.png").stat().st_size > 0


def test_an_input_without_the_training_distribution_is_refused(tmp_path):
    bench = _bench([0.1, 0.1], [0.0, 0.0])
    del bench["env"]["training-dist"]
    (tmp_path / "a.json").write_text(json.dumps(bench))
    with pytest.raises(SystemExit, match="no 'training-dist' rollout"):
        skew.main([f"a={tmp_path / 'a.json'}", "--out", str(tmp_path / "skew")])
    with pytest.raises(SystemExit, match="expected LABEL=BIAS.json"):
        skew.main([str(tmp_path / "a.json"), "--out", str(tmp_path / "skew")])
    assert not list(tmp_path.glob("skew*"))


def test_the_training_winds_shift_is_given_where_the_distribution_draws_one(tmp_path):
    bench = _bench([0.10, 0.12], [0.00, 0.04])
    (row,) = skew.skew_rows(bench)
    assert row["training_wind_m"] is None  # no wind drawn: the column says "-"
    for r, w in zip(bench["env"]["training-dist"]["10.0"], (-0.02, -0.04), strict=True):
        r["wind_mean_downrange_m"] = w
    (row,) = skew.skew_rows(bench)
    assert row["training_wind_m"] == pytest.approx(-0.03) and row["training_wind_se_m"] == pytest.approx(0.01)
    (tmp_path / "a.json").write_text(json.dumps(bench))
    assert skew.main([f"a={tmp_path / 'a.json'}", "--out", str(tmp_path / "skew")]) == 0
    assert "| -0.030 ± 0.010 |" in (tmp_path / "skew.md").read_text()


def test_parameter_settings_are_tabled_with_their_paired_change_from_the_nominal_machine(tmp_path):
    bench = _bench([0.10, 0.12], [0.00, 0.04])
    bench["env"]["valve_delay=14"] = {"10.0": [dict(r, downrange_m=r["downrange_m"] - 0.1) for r in bench["env"]["env"]["10.0"]]}
    bench["env"]["twin"] = {"10.0": bench["env"]["env"]["10.0"]}  # a rollout of the chain, not a setting
    (row,) = skew.setting_rows(bench)
    assert row["setting"] == "valve_delay=14" and row["bias_m"] == pytest.approx(0.01) and row["change_m"] == pytest.approx(-0.1)
    assert skew.setting_rows(_bench([0.1], [0.0])) == []
    (tmp_path / "a.json").write_text(json.dumps(bench))
    assert skew.main([f"a={tmp_path / 'a.json'}", "--out", str(tmp_path / "skew")]) == 0
    md = (tmp_path / "skew.md").read_text()
    assert "| `valve_delay=14` | +0.010 ± 0.010 (-0.100) |" in md and "`twin`" not in md
