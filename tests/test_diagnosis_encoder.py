"""Encoder offsets, a non-separable per-joint effect (:attr:`sim_twin.twin.effects.PerJointEffect.separable`):
a dataset made by ``slinger diagnose generate`` with an offset on one active joint, diagnosed
blind, names ``encoder_offset`` with that joint and its value; the other joints stay nominal."""

from __future__ import annotations

import json
from pathlib import Path

from sim_twin.diagnosis.cli import main as diagnose_main
from sim_twin.diagnosis.diagnose import diagnose

CANDIDATES = ["encoder_offset", "imu_offset", "passive_friction", "release_delay", "grasp_offset"]


def test_generated_boom_encoder_offset_is_named_with_its_joint_and_value(tmp_path: Path):
    truth = -0.04  # rad, boom encoder reads 2.3 degrees low
    prof = tmp_path / "profile.json"
    prof.write_text(json.dumps({"name": "boom-encoder", "effects": [{"effect": "encoder_offset", "params": {"offset_boom": truth}}]}))
    data = tmp_path / "data"
    assert diagnose_main(["generate", "--mode", "2d", "--throws", "10", "--out", str(data), "--profile", str(prof),
                          "--real-log", "--seed", "7", "--workers", "1"]) == 0
    rep = diagnose(data, None, seed=7, candidates=CANDIDATES, plots=False)
    v = rep["verdict"]
    assert v["answer"] == "named" and v["effects"] == ["encoder_offset"], v["text"]
    (fit,) = rep["which"]
    assert abs(fit["params"]["offset_boom"] - truth) < 0.2 * abs(truth), fit["params"]
    assert set(fit["sigma"]) == {"offset_boom"} and fit["sigma"]["offset_boom"] > 0
    assert sorted(fit["not_identifiable"]) == ["offset_cabin_turn", "offset_dipper", "offset_telescope"]
    assert all(fit["params"][n] == 0.0 for n in fit["not_identifiable"])
    hf = rep["how_far"]  # the held-out shrink per channel, never pooled: gap_shrink is the smallest
    shrinks = {ch: r["shrink"] for ch, r in hf["shrink_by_channel"].items() if r["shrink"] is not None}
    shrinks["impact (RMS)"] = hf["impact_gap_shrink"]
    assert set(hf["shrink_by_channel"]) <= set(rep["where"]["carriers"]) and hf["gap_shrink"] == min(shrinks.values())
    assert hf["gap_shrink_channel"] == min(shrinks, key=shrinks.get)
