"""Logged throws of the Drake machine as a real-log-like diagnosis dataset (sim_twin.diagnosis.drake_dataset)."""

from __future__ import annotations

import json

from sim_twin import default_policy
from sim_twin.diagnosis import dataset
from sim_twin.diagnosis.drake_dataset import generate


def test_drake_throws_are_logged_like_a_real_machines(tmp_path):
    index = json.loads(generate(tmp_path / "ds", 3, default_policy("2d"), "2d", seed=0).read_text())
    assert index["source"]["engine"] == "drake" and index["sensors"]["impact_sigma_m"] == 0.05
    assert [t["status"] for t in index["throws"]] == ["landed"] * 3
    assert all("opening_stamp_s" not in t for t in index["throws"])
    throws, _ = dataset.load(tmp_path / "ds")
    assert throws  # the throws whose impact was measured
    for th in throws:
        assert th.open_row is None and len(th.payload_t_s) == 0  # no payload-free flag, no payload channel
        assert th.q.shape[1] == 6 and abs(th.target_m[0] - th.impact_m[0]) < 1.0
