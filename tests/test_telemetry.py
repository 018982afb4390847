"""MCAP telemetry: write a recording, read it back with our reader and with plain mcap (the ROS 2
decoders' checks are in tests/test_ros2_logs.py)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from runtime.telemetry import (
    ROS2_TOPICS,
    TelemetryRecorder,
    read_metadata,
    read_telemetry,
    write_mcap,
)

DATA = Path(__file__).parent / "data"


def _recording(n: int = 50) -> TelemetryRecorder:
    rec = TelemetryRecorder()
    rec.event(100.0, "preparing")
    for k in range(n):
        t = 100.0 + 0.01 * k
        payload = (np.array([k, 0.0, 2.0]), np.array([1.0, 0.0, -0.1 * k])) if k >= 10 else (None, None)
        rec.record(t, np.full(6, 0.1 * k), np.full(6, -k), np.arange(4) * k, np.full(4, 0.01 * k), k >= 20, k >= 30, "swinging" if k < 20 else "released", *payload)
    rec.event(100.2, "released", "release command")
    return rec


def test_roundtrip_bytes_and_file(tmp_path):
    rec = _recording()
    blob = write_mcap(rec, {"throw_id": "t9", "mode": "2d"})
    path = tmp_path / "t9.mcap"
    path.write_bytes(blob)
    for source in (blob, path, str(path)):
        d = read_telemetry(source)
        assert d["t_s"].shape == (50,) and d["q"].shape == (50, 6) and d["valve_u"].shape == (50, 4)
        np.testing.assert_allclose(d["t_s"], 100.0 + 0.01 * np.arange(50))
        np.testing.assert_allclose(d["q"][7], 0.7)
        np.testing.assert_allclose(d["qd_ref"][3], [0, 3, 6, 9])
        assert d["gripper_cmd"].sum() == 30 and d["gripper_open"].sum() == 20
        assert d["payload_pos_m"].shape == (40, 3)  # only ticks where the payload is known
        np.testing.assert_allclose(d["payload_t_s"][0], 100.1)
        assert list(d["phase"][:2]) == ["swinging", "swinging"] and d["phase"][-1] == "released"
        assert list(d["event_phase"]) == ["preparing", "released"]
        assert d["event_detail"][0] is None and d["event_detail"][1] == "release command"
    assert read_metadata(blob) == {"throw_id": "t9", "mode": "2d"}


def test_file_is_standard_mcap_with_ros2_schemas():
    blob = write_mcap(_recording(5))
    reader = make_reader(io.BytesIO(blob))
    summary = reader.get_summary()
    assert reader.get_header().profile == "ros2"
    topics = {ch.topic for ch in summary.channels.values()}
    assert topics == set(ROS2_TOPICS)
    for ch in summary.channels.values():
        assert ch.message_encoding == "cdr"
        assert summary.schemas[ch.schema_id].encoding == "ros2msg"
        assert summary.schemas[ch.schema_id].name == ROS2_TOPICS[ch.topic][0]
    counts = summary.statistics.channel_message_counts
    by_topic = {summary.channels[cid].topic: n for cid, n in counts.items()}
    assert by_topic["/joint_states"] == by_topic["/tf"] == 5 and by_topic["/robot_description"] == 1
    assert by_topic["/throw/events"] == 2 and "/impact" not in by_topic  # no impact in the metadata


def test_stored_json_layout_still_reads():
    """A file in the JSON layout written before the ROS 2 one (tests/data, made by the old writer
    from _recording()) reads back as it did."""
    d = read_telemetry(DATA / "telemetry_json_v1.mcap")
    e = read_telemetry(write_mcap(_recording()))
    for key in ("t_s", "q", "qd", "qd_ref", "valve_u", "payload_t_s", "payload_pos_m", "payload_vel_mps", "event_t_s"):
        np.testing.assert_allclose(d[key], e[key], atol=1e-9, err_msg=key)
    for key in ("phase", "gripper_cmd", "gripper_open", "event_phase", "event_detail"):
        assert list(d[key]) == list(e[key]), key
    assert read_metadata(DATA / "telemetry_json_v1.mcap")["throw_id"] == "t9"


def test_empty_recording_reads_back_empty():
    d = read_telemetry(write_mcap(TelemetryRecorder()))
    assert d["t_s"].shape == (0,) and d["q"].shape == (0, 6) and d["payload_pos_m"].shape == (0, 3)


def test_garbage_is_rejected():
    with pytest.raises(Exception):
        read_telemetry(b"not an mcap file at all")
