"""Throw telemetry in ROS 2 form, checked with decoders nobody here wrote: mcap-ros2-support's
decoder and rosbags' reader, every type name and hash against the rosbags ROS 2 Jazzy typestore;
the robot description against the twin's MJCF; the /tf frames against runtime.machine."""

from __future__ import annotations

import io
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES, forward_kinematics
from runtime.ros2.robot_description import URDF_PATH
from runtime.telemetry import ROS2_TOPICS, read_telemetry, write_mcap
from tests.test_telemetry import _recording

JAZZY = get_typestore(Stores.ROS2_JAZZY)
META = {"throw_id": "t9", "mode": "2d", "target_m": json.dumps([8.0, -0.292, 0.0]), "impact_m": json.dumps([8.3, -0.1, 0.0]),
        "impact_stamp_s": "100.45"}


@pytest.fixture(scope="module")
def blob() -> bytes:
    return write_mcap(_recording(50), META)


def _decoded(blob: bytes) -> dict[str, list]:
    """Every message decoded by mcap-ros2-support, by topic: (log time ns, message)."""
    out: dict[str, list] = {}
    reader = make_reader(io.BytesIO(blob), decoder_factories=[DecoderFactory()])
    for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
        out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def test_types_and_hashes_match_the_jazzy_typestore(blob):
    summary = make_reader(io.BytesIO(blob)).get_summary()
    assert summary.channels
    for ch in summary.channels.values():
        schema = summary.schemas[ch.schema_id]
        assert schema.name in JAZZY.fielddefs, schema.name
        assert schema.data.decode() == JAZZY.generate_msgdef(schema.name, ros_version=2)[0]
        assert ch.metadata["topic_type_hash"] == JAZZY.hash_rihs01(schema.name)
        assert "durability: 1" in ch.metadata["offered_qos_profiles"] if ch.topic in ("/robot_description", "/tf_static") \
            else "durability: 2" in ch.metadata["offered_qos_profiles"]


def test_rosbags_reads_every_message(tmp_path, blob):
    path = tmp_path / "t9.mcap"
    path.write_bytes(blob)
    seen: dict[str, int] = {}
    with Reader(path) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {t: ty for t, (ty, _) in ROS2_TOPICS.items()}
        for conn, _t, raw in reader.messages():
            msg = JAZZY.deserialize_cdr(raw, conn.msgtype)
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            if conn.topic == "/joint_states":
                assert list(msg.name) == list(JOINT_NAMES) and msg.position.shape == (6,)
            if conn.topic == "/valve_commands":
                assert msg.layout.dim[0].label == ",".join(ACTIVE_JOINTS) and msg.data.shape == (4,)
    assert seen["/joint_states"] == seen["/tf"] == seen["/references"] == 50 and seen["/payload"] == 40
    assert seen["/gripper/command"] == 2 and seen["/gripper/state"] == 2 and seen["/throw/phase"] == 2  # on change


def test_mcap_ros2_decoder_reads_what_was_recorded(blob):
    d = _decoded(blob)
    js = [m for _t, m in d["/joint_states"]]
    np.testing.assert_allclose([m.position[0] for m in js], 0.1 * np.arange(50))
    np.testing.assert_allclose(js[3].header.stamp.sec + js[3].header.stamp.nanosec * 1e-9, 100.03, atol=1e-9)
    assert [m.data for _t, m in d["/gripper/command"]] == [False, True]
    assert [m.data for _t, m in d["/throw/phase"]] == ["swinging", "released"]
    assert [(m.key, m.value) for _t, m in d["/throw/events"]] == [("preparing", ""), ("released", "release command")]
    (_, target), = d["/target"]
    (t_hit, impact), = d["/impact"]
    assert (target.point.x, target.point.y, target.header.frame_id) == (8.0, -0.292, "machine")
    assert (impact.point.x, impact.point.y) == (8.3, -0.1) and t_hit == 100_450_000_000
    odo = d["/payload"][0][1]
    assert odo.header.frame_id == "machine" and odo.pose.pose.position.x == 10.0 and odo.twist.twist.linear.z == pytest.approx(-1.0)
    (_, desc), = d["/robot_description"]
    assert desc.data == URDF_PATH.read_text()
    links = {e.get("name") for e in ET.fromstring(desc.data).iter("link")}
    (_, static), = d["/tf_static"]
    assert [(t.header.frame_id, t.child_frame_id) for t in static.transforms] == [("machine", "chassis")]
    frames = {(t.header.frame_id, t.child_frame_id) for t in d["/tf"][0][1].transforms}
    assert {c for _p, c in frames} | {"machine", "chassis"} == links  # every link has a transform


def _compose(transforms, child: str):
    """Position and rotation matrix of ``child`` in the root, from decoded TransformStamped messages."""
    by_child = {t.child_frame_id: t for t in transforms}
    chain = []
    while child in by_child:
        chain.append(by_child[child])
        child = by_child[child].header.frame_id
    p, r = np.zeros(3), np.eye(3)
    for t in reversed(chain):
        q = t.transform.rotation
        x, y, z, w = q.x, q.y, q.z, q.w
        rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                       [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                       [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        tr = t.transform.translation
        p, r = p + r @ np.array([tr.x, tr.y, tr.z]), r @ rq
    return p, r


def test_tf_puts_the_gripper_where_the_runtime_kinematics_does():
    from runtime.telemetry import TelemetryRecorder

    rec = TelemetryRecorder()
    rng = np.random.default_rng(4)
    qs = [np.r_[rng.uniform(-1, 1, 3), rng.uniform(0, 1.8), rng.uniform(-1, 1, 2)] for _ in range(5)]
    for k, q in enumerate(qs):
        rec.record(1.0 + 0.01 * k, q, np.zeros(6), np.zeros(4), np.zeros(4), False, False, "swinging")
    d = _decoded(write_mcap(rec))
    static = d["/tf_static"][0][1].transforms
    for q, (_t, tf) in zip(qs, d["/tf"]):
        pts = forward_kinematics(np, q, np.zeros(6))
        p, r = _compose(list(static) + list(tf.transforms), "gripper")
        np.testing.assert_allclose(p + r @ [0.0, 0.0, -1.0], pts.gripper_centre, atol=1e-9)
        np.testing.assert_allclose(_compose(list(static) + list(tf.transforms), "gripper_hanger")[0], pts.hanger, atol=1e-9)


def test_shipped_urdf_is_the_export_of_the_mjcf():
    from sim_twin.twin.model import load_model
    from sim_twin.twin.urdf import export_urdf

    assert URDF_PATH.read_text() == export_urdf(load_model()), "regenerate: python -m sim_twin.twin.urdf > runtime/ros2/material_handler.urdf"
    joints = {j.get("name"): j.get("type") for j in ET.fromstring(URDF_PATH.read_text()).iter("joint")}
    assert joints == {"machine_to_chassis": "fixed", "cabin_turn": "continuous", "boom": "revolute", "dipper": "revolute",
                      "telescope": "prismatic", "gripper_pitch": "continuous", "gripper_roll": "continuous"}


def test_our_reader_and_the_diagnosis_read_the_ros2_file(blob):
    from sim_twin.diagnosis import logformat

    d = read_telemetry(blob)
    assert d["q"].shape == (50, 6) and list(d["phase"][18:22]) == ["swinging", "swinging", "released", "released"]
    assert d["gripper_cmd"].sum() == 30 and d["gripper_open"].sum() == 20 and d["payload_pos_m"].shape == (40, 3)
    a = logformat.arrays(logformat.read_messages(blob))
    np.testing.assert_allclose(a["q"], d["q"])
    assert a["k0"] == 0 and a["gripper_cmd"].sum() == 30


def test_foxglove_layout_names_topics_the_file_has():
    layout = json.loads((Path(__file__).parents[1] / "docs" / "foxglove_layout.json").read_text())
    text = json.dumps(layout)
    for topic in ("/joint_states", "/valve_commands", "/target", "/impact", "/robot_description"):
        assert topic in text, topic
    assert any(k.startswith("3D") for k in layout["configById"]) and any(k.startswith("Plot") for k in layout["configById"])
