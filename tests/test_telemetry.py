"""MCAP telemetry: write a recording, read it back with our reader and with plain mcap."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from mcap.reader import make_reader

from runtime.telemetry import TelemetryRecorder, read_metadata, read_telemetry, write_mcap


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


def test_file_is_standard_mcap_with_json_schemas():
    blob = write_mcap(_recording(5))
    reader = make_reader(io.BytesIO(blob))
    summary = reader.get_summary()
    topics = {ch.topic for ch in summary.channels.values()}
    assert topics == {"/joint_states", "/references", "/valve_commands", "/gripper", "/payload", "/events"}
    for ch in summary.channels.values():
        assert ch.message_encoding == "json"
        assert summary.schemas[ch.schema_id].encoding == "jsonschema"
        json.loads(summary.schemas[ch.schema_id].data)
    assert summary.statistics.message_count == 5 * 4 + 2


def test_empty_recording_reads_back_empty():
    d = read_telemetry(write_mcap(TelemetryRecorder()))
    assert d["t_s"].shape == (0,) and d["q"].shape == (0, 6) and d["payload_pos_m"].shape == (0, 3)


def test_garbage_is_rejected():
    with pytest.raises(Exception):
        read_telemetry(b"not an mcap file at all")
