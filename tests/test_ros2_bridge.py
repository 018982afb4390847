"""The ROS 2 machine bridge: rmw_zenoh's formats (checked against the examples of rmw_zenoh's
docs/design.md), the mapping file, the bridge's translation and watchdog path, and the whole chain
with the ROS 2 path in the middle (server API -> runtime -> bridge -> ROS 2 topics -> simulated
machine), the bridge's traffic decoded from raw Zenoh samples by the rosbags CDR reader."""

from __future__ import annotations

import io
import json
import threading
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from runtime.machine import JOINT_NAMES
from runtime.protocol import keys
from runtime.protocol.messages import (
    GripperCommand,
    MachineState,
    ValveCommand,
    decode,
    encode,
)
from runtime.ros2 import rmw_zenoh
from runtime.ros2 import types as rt
from runtime.ros2.bridge import MachineBridge
from runtime.ros2.config import BridgeConfig, ConfigError, load
from runtime.telemetry import read_telemetry
from runtime.zenoh_session import open_session
from server.stack import Children, slinger_command
from tests.conftest import free_port, wait_for, wait_online
from tests.fixtures import write_test_policy
from tests.test_stack import TARGET_2D, _landed_throw

JAZZY = get_typestore(Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

MAPPING_TOML = """
domain_id = 7
stale_after_s = 0.15
simulated = true
[topics]
joint_states = "/arm/joint_states"
passive_joint_states = "/gripper/imu_joint_states"
payload = "/payload/odom"
valve_command = "/arm/valve_commands"
[joints.boom]
name = "boom_joint"
scale = 0.017453292519943295
[joints.dipper]
name = "stick_joint"
scale = 0.017453292519943295
offset = 0.1
[joints.telescope]
name = "telescope_joint"
scale = 0.001
[valves.cabin_turn]
index = 3
scale = 100.0
[valves.telescope]
index = 0
scale = 100.0
"""


# --- rmw_zenoh formats --------------------------------------------------------------------------
def test_keys_and_tokens_are_the_design_examples():
    """rmw_zenoh docs/design.md, demo_nodes_cpp talker/listener on `chatter` (std_msgs/String)."""
    assert rt.type_hash("std_msgs/msg/String") == STRING_HASH
    assert rmw_zenoh.topic_key(0, "chatter", "std_msgs/msg/String") == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert rmw_zenoh.topic_key(0, "chatter", "std_msgs/msg/String", "/robot1") == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert rmw_zenoh.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert rmw_zenoh.entity_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "talker", "chatter", "std_msgs/msg/String",
                                  qos="::,7:,:,:,,") == (
        f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    a = rmw_zenoh.attachment(42, 1_700_000_000_000_000_000, bytes(range(16)))
    assert len(a) == 33 and a[16] == 16 and rmw_zenoh.parse_attachment(a) == (42, 1_700_000_000_000_000_000, bytes(range(16)))
    for bad in ("", "a//b", "1abc", "a b", "/x/"):
        with pytest.raises(ValueError):
            rmw_zenoh.topic_key(0, bad, "std_msgs/msg/String")
    with pytest.raises(ValueError):
        rmw_zenoh.parse_attachment(a[:-1])


# --- mapping file -------------------------------------------------------------------------------
def test_config_files_and_refusals(tmp_path):
    toml = tmp_path / "b.toml"
    toml.write_text(MAPPING_TOML)
    c = load(toml)
    assert c.domain_id == 7 and c.joint("boom").name == "boom_joint" and c.joint("cabin_turn").name == "cabin_turn"
    assert c.valve_array([0.1, 0.2, 0.3, 0.4]) == [40.0, 0.2, 0.3, 10.0]
    assert c.valve_u([40.0, 0.2, 0.3, 10.0]) == pytest.approx([0.1, 0.2, 0.3, 0.4])
    (tmp_path / "b.json").write_text(json.dumps(c.model_dump()))
    (tmp_path / "b.yaml").write_text("domain_id: 3\ntopics:\n  joint_states: /js\n")
    assert load(tmp_path / "b.json") == c and load(tmp_path / "b.yaml").topics.joint_states == "/js"
    bad = {"x.toml": "domain_id = 300", "y.toml": "[joints.shovel]\nname = 'a'", "z.toml": "[topics]\njoint_states = 'a b'",
           "w.toml": "[valves.boom]\nindex = 0", "v.toml": "[joints.boom]\nname = 'dipper'", "u.toml": "unknown = 1",
           "t.toml": "[topics]\njoint_states = ''", "s.txt": "", "r.toml": "domain_id = ["}
    for name, text in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError, match=name.split(".")[0]):
            load(tmp_path / name)
    with pytest.raises(ConfigError, match="missing"):
        load(tmp_path / "missing.toml")


# --- the translation, without I/O ---------------------------------------------------------------
class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _bridge(config: BridgeConfig):
    out = {"state": [], "impact": [], "valves": [], "gripper": []}
    clock = _Clock()
    b = MachineBridge("m1", config, out["state"].append, out["impact"].append, out["valves"].append, out["gripper"].append,
                      clock=clock, wall=lambda: 1_000.0 + clock.t)
    return b, out, clock


def test_bridge_maps_units_and_stops_states_when_a_topic_goes_silent(tmp_path):
    (tmp_path / "b.toml").write_text(MAPPING_TOML)
    config = load(tmp_path / "b.toml")
    b, out, clock = _bridge(config)
    active = rt.joint_state(0, ["cabin_turn", "boom_joint", "stick_joint", "telescope_joint"], [0.1, -30.0, 90.0, 500.0], [0.0, 10.0, 0.0, 100.0])
    b.on_joint_state(active)
    assert out["state"] == []  # no passive joints and gripper state yet: no machine state
    b.on_passive_joint_state(rt.joint_state(0, ["gripper_roll", "gripper_pitch"], [0.02, -0.5], [0.0, 0.3]))
    b.on_gripper_state(rt.msg(rt.BOOL, data=False))
    b.on_joint_state(active)
    (s,) = out["state"]
    np.testing.assert_allclose(s.q, [0.1, np.radians(-30.0), np.radians(90.0) + 0.1, 0.5, -0.5, 0.02])
    np.testing.assert_allclose(s.qd, [0.0, np.radians(10.0), 0.0, 0.1, 0.3, 0.0])
    assert s.payload_attached and not s.gripper_open and s.payload_pos_m is None and s.stamp_s == 100.0 and s.simulated
    clock.t += 0.1
    b.on_joint_state(active)
    assert len(out["state"]) == 2
    clock.t += 0.1  # the passive joints (gripper IMU) are now 0.2 s old
    b.on_joint_state(active)
    assert len(out["state"]) == 2 and b.stale == "passive"
    b.on_passive_joint_state(rt.joint_state(0, ["gripper_pitch", "gripper_roll"], [-0.5, 0.02]))
    b.on_joint_state(active)
    assert len(out["state"]) == 2 and b.stale == "gripper_state"  # the gripper state is as old
    b.on_gripper_state(rt.msg(rt.BOOL, data=False))
    b.on_joint_state(active)
    assert len(out["state"]) == 3 and b.stale is None
    # a JointState without a mapped joint or with NaN is dropped, not half-applied
    b.on_joint_state(rt.joint_state(0, ["cabin_turn", "boom_joint"], [0.0, 1.0]))
    b.on_joint_state(rt.joint_state(0, ["cabin_turn", "boom_joint", "stick_joint", "telescope_joint"], [np.nan, 0, 0, 0]))
    assert len(out["state"]) == 3 and b.dropped == 2

    # commands: only the newest runtime epoch, in the ROS array layout; neutral on runtime silence
    b.on_valve_command(encode(ValveCommand(machine_id="m1", stamp_s=1.0, u=[0.1, 0.2, 0.3, 0.4], epoch=5)))
    b.on_valve_command(encode(ValveCommand(machine_id="m1", stamp_s=1.0, u=[0.9, 0.9, 0.9, 0.9], epoch=4)))
    b.on_valve_command(encode(ValveCommand(machine_id="m2", stamp_s=1.0, u=[0.9, 0.9, 0.9, 0.9], epoch=6)))
    b.on_valve_command(b"{not json")
    (v,) = out["valves"]
    assert list(v.data) == [40.0, 0.2, 0.3, 10.0] and v.layout.dim[0].label == "telescope,boom,dipper,cabin_turn"
    clock.t += 0.2
    b.check()
    b.check()
    assert len(out["valves"]) == 2 and not any(out["valves"][1].data)
    b.on_gripper_command(encode(GripperCommand(machine_id="m1", stamp_s=1.0, open=True)))
    assert out["gripper"][0].data is True

    # the opening and the impact
    b.on_payload(rt.odometry(0, "machine", "payload", [5.0, 0.0, 4.0], [3.0, 0.0, 2.0]))
    b.on_gripper_state(rt.msg(rt.BOOL, data=True))
    t_open = clock.t
    clock.t += 1.0
    b.on_impact(rt.point_stamped(1_000.0 + clock.t - 0.25, [9.0, -0.2, 0.0], "machine"))
    (r,) = out["impact"]
    assert r.impact_pos_m == [9.0, -0.2, 0.0] and r.opening_stamp_s == t_open and r.impact_stamp_s == pytest.approx(clock.t - 0.25)
    assert r.release_pos_m == [5.0, 0.0, 4.0] and r.release_vel_mps == [3.0, 0.0, 2.0]


def test_bridge_takes_the_passive_joints_from_a_gripper_imu_whatever_its_yaw():
    from scipy.spatial.transform import Rotation

    from runtime.ros2.imu import imu_from_joints

    b, out, _clock = _bridge(BridgeConfig(topics={"imu": "/gripper/imu"}))
    q = [0.4, -0.5, 1.9, 0.7, -1.2, 0.15]
    qd = [0.3, -0.2, 0.5, 0.1, 0.8, -0.6]
    quat, omega = imu_from_joints(q, qd)
    quat = (Rotation.from_euler("z", -2.0) * Rotation.from_quat(quat)).as_quat()  # the AHRS's north is elsewhere
    imu = rt.msg(rt.IMU, header=rt.header(0, "gripper"), orientation=rt.quaternion(quat), orientation_covariance=np.zeros(9),
                 angular_velocity=rt.vector3(omega), angular_velocity_covariance=np.zeros(9),
                 linear_acceleration=rt.vector3((0, 0, 9.8)), linear_acceleration_covariance=np.zeros(9))
    b.on_imu(imu)
    b.on_gripper_state(rt.msg(rt.BOOL, data=False))
    b.on_joint_state(rt.joint_state(0, JOINT_NAMES[:4], q[:4], qd[:4]))
    (s,) = out["state"]
    np.testing.assert_allclose(s.q, q, atol=1e-9)
    np.testing.assert_allclose(s.qd, qd, atol=1e-9)
    b.on_imu(rt.msg(rt.IMU, header=rt.header(0, "gripper"), orientation=rt.quaternion((0, 0, 0, 0)), orientation_covariance=np.zeros(9),
                    angular_velocity=rt.vector3((0, 0, 0)), angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=rt.vector3((0, 0, 0)), linear_acceleration_covariance=np.zeros(9)))
    assert b.dropped == 1


# --- the bridge process against a ROS 2 machine written here ------------------------------------
def _session(endpoint: str, listen: bool = False):
    return open_session("peer", listen=[endpoint] if listen else [], connect=[] if listen else [endpoint])


def test_bridge_process_reads_ros_topics_and_loses_the_link_when_they_stop(tmp_path):
    import argparse

    from runtime.ros2.bridge import build_parser, run

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    states: list[MachineState] = []
    with _session(endpoint, listen=True) as session:
        sub = session.declare_subscriber(keys.state("m1"), lambda s: states.append(decode(MachineState, s.payload.to_bytes())))
        tokens: list[str] = []
        node = rmw_zenoh.RosNode(session, "fake_machine")
        js = node.publisher("/joint_states", rt.JOINT_STATE)
        grip = node.publisher("/gripper/state", rt.BOOL)
        p = argparse.ArgumentParser()
        build_parser(p)
        stop = threading.Event()
        code: list[int] = []
        th = threading.Thread(target=lambda: code.append(run(p.parse_args(["--machine-id", "m1", "--connect", endpoint]), stop)))
        th.start()
        try:
            wait_for(lambda: any("/MS/" in str(r.result.key_expr) and "joint_states" in str(r.result.key_expr)
                                 for r in session.liveliness().get("@ros2_lv/**", timeout=1.0) if r.ok), 10, "bridge subscription token")
            for r in session.liveliness().get("@ros2_lv/**", timeout=1.0):
                tokens.append(str(r.ok.key_expr) if r.ok else "")
            for k in range(30):
                grip.publish(rt.msg(rt.BOOL, data=False))
                js.publish(rt.joint_state(time.time(), JOINT_NAMES, np.arange(6) * 0.1 + [0, 0, 1.0, 0, 0, 0], np.zeros(6)))
                time.sleep(0.01)
            wait_for(lambda: len(states) >= 20, 5, "machine states from the bridge")
            np.testing.assert_allclose(states[-1].q, np.arange(6) * 0.1 + [0, 0, 1.0, 0, 0, 0])
            n = len(states)
            time.sleep(0.4)  # the machine stops publishing: no more machine states (link lost)
            assert len(states) == n
        finally:
            stop.set()
            th.join(10)
            node.close()
            sub.undeclare()
    assert code == [0]
    assert any("/NN/%/%/slinger_bridge" in t for t in tokens) and any("/MP/%/%/slinger_bridge/%valve_commands/" in t for t in tokens)


# --- the whole chain ----------------------------------------------------------------------------
@pytest.fixture
def ros2_machine(tmp_path, zenoh_endpoint, settings):
    """The simulated machine speaking ROS 2 (`slinger plant --ros2`), the ROS 2 bridge and the
    runtime, all connecting to the server's endpoint with one mapping file (degrees, millimetres,
    per-cent valves in another order, the passive joints from a gripper IMU)."""
    from server.certs import make_site

    site = make_site(settings.resolved_site_dir, ["m1"])
    policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
    mapping = tmp_path / "bridge.toml"
    mapping.write_text(MAPPING_TOML.replace('payload = "/payload/odom"', 'payload = "/payload/odom"\nimu = "/gripper/imu"'))
    children = Children()
    link = ["--connect", zenoh_endpoint, "--listen", "tcp/127.0.0.1:0"]
    logs = tmp_path / "logs"
    children.spawn("plant", slinger_command("plant", "--machine-id", "m1", "--seed", "3", "--ros2", str(mapping), *link), logs)
    children.spawn("bridge", slinger_command("ros2-bridge", "--machine-id", "m1", "--config", str(mapping), *link), logs)
    children.spawn("runtime", slinger_command("runtime", "--machine-id", "m1", "--policy-2d", str(policy), *link,
                                              "--command-key", str(site.command_key("m1")), "--outbox-dir", str(tmp_path / "outbox")), logs)
    yield logs
    children.stop(grace_s=15)
    for c in children.items:
        assert c.proc.returncode is not None


def _typename(dds: str) -> str:
    """sensor_msgs::msg::dds_::JointState_ -> sensor_msgs/msg/JointState"""
    pkg, kind, _dds, name = dds.split("::")
    return f"{pkg}/{kind}/{name[:-1]}"


def test_throw_lands_through_the_ros2_bridge(client, ros2_machine, zenoh_endpoint, settings):
    raw: list[tuple[str, bytes, bytes | None]] = []
    lock = threading.Lock()

    def on_sample(s) -> None:
        with lock:
            if len(raw) < 20000:
                raw.append((str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None))

    with _session(zenoh_endpoint) as spy:
        sub = spy.declare_subscriber("7/**", on_sample)
        try:
            m = wait_online(client, "m1", timeout_s=90)
            assert m["simulated"] is True
            row, _ = _landed_throw(client, lambda: client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D}))
            assert row["status"] == "landed", (row, (ros2_machine / "bridge.log").read_text()[-3000:] if (ros2_machine / "bridge.log").exists() else "")
            assert row["impact"] is not None and np.hypot(*row["impact"][:2]) > 2.0
            # its telemetry is in ROS 2 form, with the measured impact as /impact
            blob = (settings.data_dir / "telemetry" / f"{row['id']}.mcap").read_bytes()
            assert client.get(row["telemetry_url"]).content == blob
            assert read_telemetry(blob)["gripper_cmd"].any()
            impacts = [m for _s, ch, _m, m in make_reader(io.BytesIO(blob), decoder_factories=[DecoderFactory()])
                       .iter_decoded_messages(topics=["/impact"])]
            assert [(p.point.x, p.point.y) for p in impacts] == [pytest.approx(tuple(row["impact"][:2]))]
            tokens = [str(r.ok.key_expr) for r in spy.liveliness().get("@ros2_lv/**", timeout=2.0) if r.ok]
        finally:
            sub.undeclare()
    # every sample on the ROS key space: rmw_zenoh's key, a type the Jazzy typestore knows with its
    # hash, CDR the rosbags reader decodes, the 33-byte attachment
    seen: dict[str, list] = {}
    for key, payload, att in raw:
        domain, *topic, dds, type_hash = key.split("/")
        typename = _typename(dds)
        assert domain == "7" and type_hash == JAZZY.hash_rihs01(typename), key
        msg = JAZZY.deserialize_cdr(payload, typename)
        assert att is not None and rmw_zenoh.parse_attachment(att)[0] >= 1
        seen.setdefault("/" + "/".join(topic), []).append(msg)
    assert set(seen) >= {"/arm/joint_states", "/gripper/imu", "/gripper/state", "/payload/odom", "/arm/valve_commands",
                         "/gripper/command", "/payload/impact"}, sorted(seen)
    js = seen["/arm/joint_states"][-1]
    assert list(js.name) == ["cabin_turn", "boom_joint", "stick_joint", "telescope_joint"]
    assert -77.0 < js.position[1] < 26.0 and 0.0 <= js.position[3] <= 1800.0  # degrees and millimetres on the ROS side
    valves = [v for v in seen["/arm/valve_commands"] if np.any(v.data)]
    assert valves and valves[0].layout.dim[0].label == "telescope,boom,dipper,cabin_turn"
    assert max(abs(x) for v in valves for x in v.data) > 1.0  # per cent
    assert [g.data for g in seen["/gripper/command"]][-1] is True
    for node in ("slinger_bridge", "simulated_machine"):
        assert any(f"/NN/%/%/{node}" in t for t in tokens), tokens
    assert any("/MS/%/%/simulated_machine/%arm%valve_commands/std_msgs::msg::dds_::Float64MultiArray_/" in t for t in tokens)
