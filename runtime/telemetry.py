"""A throw's 100 Hz telemetry: recorded in memory by the executor, stored as MCAP in ROS 2 form.

MCAP layout (profile ``ros2``; every channel ``cdr`` message encoding with a ``ros2msg`` schema
of ROS 2 Jazzy, from the rosbags typestore; header stamps, log and publish times are the
machine's monotonic stamps):

=====================  ==========================  ==============================================
topic                  type                        content
=====================  ==========================  ==============================================
/robot_description     std_msgs/String             the machine's URDF (runtime.ros2.robot_description),
                                                   once, transient local (as robot_state_publisher)
/tf_static             tf2_msgs/TFMessage          fixed joints (machine -> chassis), once, transient local
/tf                    tf2_msgs/TFMessage          every movable link in its parent, per tick
/joint_states          sensor_msgs/JointState      q (6,) rad/m, qd (6,) rad/s, m/s, JOINT_NAMES
                                                   (the passive joints from the gripper IMU)
/references            sensor_msgs/JointState      velocity: qd_ref (4,) after safety clipping, ACTIVE_JOINTS
/valve_commands        std_msgs/Float64MultiArray  u (4,) in [-1, 1], ACTIVE_JOINTS (dimension label)
/gripper/command       std_msgs/Bool               the runtime's gripper command (true = open) *
/gripper/state         std_msgs/Bool               measured: true = open (payload free) *
/throw/phase           std_msgs/String             the throw's phase *
/throw/events          diagnostic_msgs/KeyValue    phase changes: key = phase, value = detail ("" = none)
/payload               nav_msgs/Odometry           payload position and velocity, frame ``machine``;
                                                   only ticks where known
/target, /impact       geometry_msgs/PointStamped  from the metadata (``target_m``, ``impact_m``), frame ``machine``
=====================  ==========================  ==============================================

Channel metadata as rosbag2 writes it: ``offered_qos_profiles`` (YAML) and ``topic_type_hash``
(RIHS01). ``*``: at the first tick and on every change (a state holds until the next message).
MCAP metadata record ``throw`` holds string fields (throw_id, mode, policy_version, ...).
:func:`read_telemetry` turns a file back into numpy arrays for tests and server-side replay; it
also reads the JSON layout written before (``json`` channels with ``jsonschema`` schemas:
/joint_states, /references, /valve_commands, /gripper, /payload, /events), so stored files stay
readable. docs/ros2.md says how ROS tools open the files.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES

MACHINE_FRAME = "machine"
PROFILE = "ros2"

# (type, transient local) of each topic of the ROS 2 layout
ROS2_TOPICS: dict[str, tuple[str, bool]] = {
    "/robot_description": ("std_msgs/msg/String", True),
    "/tf_static": ("tf2_msgs/msg/TFMessage", True),
    "/tf": ("tf2_msgs/msg/TFMessage", False),
    "/joint_states": ("sensor_msgs/msg/JointState", False),
    "/references": ("sensor_msgs/msg/JointState", False),
    "/valve_commands": ("std_msgs/msg/Float64MultiArray", False),
    "/gripper/command": ("std_msgs/msg/Bool", False),
    "/gripper/state": ("std_msgs/msg/Bool", False),
    "/throw/phase": ("std_msgs/msg/String", False),
    "/throw/events": ("diagnostic_msgs/msg/KeyValue", False),
    "/payload": ("nav_msgs/msg/Odometry", False),
    "/target": ("geometry_msgs/msg/PointStamped", False),
    "/impact": ("geometry_msgs/msg/PointStamped", False),
}

_QOS = ("- history: 1\n  depth: 1\n  reliability: 1\n  durability: {durability}\n"
        "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  avoid_ros_namespace_conventions: false\n")
"""rosbag2's ``offered_qos_profiles`` channel metadata (durability 1 = transient local, 2 = volatile)."""

# the layout written before the ROS 2 one (still read)
_JSON_TOPICS = ("/joint_states", "/references", "/valve_commands", "/gripper", "/payload", "/events")


@dataclass
class TelemetryRecorder:
    """In-memory per-tick record of one throw (pure data, no I/O).

    Call :meth:`record` once per 100 Hz tick and :meth:`event` on every phase change.
    """

    rows: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)

    def record(self, t_s: float, q, qd, qd_ref, valve_u, gripper_cmd: bool, gripper_open: bool, phase: str, payload_pos_m=None, payload_vel_mps=None) -> None:
        """Append one tick. Vectors: q, qd (6,), qd_ref, valve_u (4,), payload (3,) or None."""
        self.rows.append(
            {
                "t_s": float(t_s),
                "q": [float(v) for v in q],
                "qd": [float(v) for v in qd],
                "qd_ref": [float(v) for v in qd_ref],
                "u": [float(v) for v in valve_u],
                "command_open": bool(gripper_cmd),
                "open": bool(gripper_open),
                "phase": phase,
                "pos_m": None if payload_pos_m is None else [float(v) for v in payload_pos_m],
                "vel_mps": None if payload_vel_mps is None else [float(v) for v in payload_vel_mps],
            }
        )

    def event(self, t_s: float, phase: str, detail: str | None = None) -> None:
        self.events.append({"t_s": float(t_s), "phase": phase, "detail": detail})

    def __len__(self) -> int:
        return len(self.rows)


def _ns(t_s: float) -> int:
    return max(0, round(t_s * 1e9))


def _vec3(text: str | None) -> list[float] | None:
    """A (3,) vector from a metadata JSON string, or None (absent or not 3 numbers)."""
    try:
        v = json.loads(text) if text else None
    except (TypeError, ValueError):
        return None
    if isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v):
        return [float(x) for x in v]
    return None


def write_mcap(recorder: TelemetryRecorder, metadata: dict[str, str] | None = None) -> bytes:
    """Serialise a recording to MCAP bytes in the ROS 2 layout (module doc; zstd chunks).

    Args:
        recorder: the throw's recording.
        metadata: string key/values stored as the MCAP metadata record ``throw``; ``target_m``
            and ``impact_m`` (JSON lists of 3 numbers, machine frame, m) also become the /target
            and /impact points, ``impact_stamp_s`` (machine seconds) the impact's stamp.
    """
    from runtime.ros2 import types as rt
    from runtime.ros2.robot_description import UrdfChain, robot_description

    metadata = {k: str(v) for k, v in (metadata or {}).items()}
    buf = io.BytesIO()
    writer = Writer(buf, compression=CompressionType.ZSTD)
    writer.start(profile=PROFILE, library="slinger-runtime")
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    for topic, (typename, latched) in ROS2_TOPICS.items():
        if typename not in schemas:
            schemas[typename] = writer.register_schema(name=typename, encoding="ros2msg", data=rt.msgdef(typename).encode())
        channels[topic] = writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schemas[typename],
                                                  metadata={"offered_qos_profiles": _QOS.format(durability=1 if latched else 2),
                                                            "topic_type_hash": rt.type_hash(typename)})
    seq = 0

    def put(topic: str, t_s: float, message) -> None:
        nonlocal seq
        writer.add_message(channels[topic], log_time=_ns(t_s), data=rt.serialize(message), publish_time=_ns(t_s), sequence=seq)
        seq += 1

    rows = recorder.rows
    t0 = rows[0]["t_s"] if rows else (recorder.events[0]["t_s"] if recorder.events else 0.0)
    chain = UrdfChain()
    put("/robot_description", t0, rt.msg(rt.STRING, data=robot_description()))
    put("/tf_static", t0, rt.msg(rt.TF_MESSAGE, transforms=[rt.transform_stamped(t0, j.parent, j.child, *j.transform())
                                                            for j in chain.fixed]))
    active = list(ACTIVE_JOINTS)
    last: dict[str, object] = {}
    for r in rows:
        t = r["t_s"]
        put("/joint_states", t, rt.joint_state(t, JOINT_NAMES, r["q"], r["qd"]))
        tfs = chain.transforms(dict(zip(JOINT_NAMES, r["q"])))
        put("/tf", t, rt.msg(rt.TF_MESSAGE, transforms=[rt.transform_stamped(t, j.parent, j.child, p, q) for j, p, q in tfs]))
        put("/references", t, rt.joint_state(t, active, velocity=r["qd_ref"]))
        put("/valve_commands", t, rt.float64_array(r["u"], active))
        for topic, value, kind in (("/gripper/command", r["command_open"], rt.BOOL), ("/gripper/state", r["open"], rt.BOOL),
                                   ("/throw/phase", r["phase"], rt.STRING)):
            if last.get(topic, not value) != value:  # on change (and at the first tick), as a latched state
                put(topic, t, rt.msg(kind, data=value))
                last[topic] = value
        if r["pos_m"] is not None and r["vel_mps"] is not None:
            put("/payload", t, rt.odometry(t, MACHINE_FRAME, "payload", r["pos_m"], r["vel_mps"]))
    for e in recorder.events:
        put("/throw/events", e["t_s"], rt.msg(rt.KEY_VALUE, key=e["phase"], value=e["detail"] or ""))
    target, impact = _vec3(metadata.get("target_m")), _vec3(metadata.get("impact_m"))
    if target is not None:
        put("/target", t0, rt.point_stamped(t0, target, MACHINE_FRAME))
    if impact is not None:
        try:
            t_hit = float(metadata["impact_stamp_s"])
        except (KeyError, ValueError):
            t_hit = rows[-1]["t_s"] if rows else t0
        put("/impact", t_hit, rt.point_stamped(t_hit, impact, MACHINE_FRAME))
    writer.add_metadata("throw", metadata)
    writer.finish()
    return buf.getvalue()


def warm() -> None:
    """Load the ROS 2 typestore, message definitions and URDF now, so that the first throw's
    telemetry does not pay for them when it is written at the throw's end (under the runtime's lock)."""
    write_mcap(TelemetryRecorder())


def _open(source: bytes | bytearray | str | Path) -> IO[bytes]:
    if isinstance(source, (bytes, bytearray)):
        return io.BytesIO(bytes(source))
    return open(source, "rb")


def read_messages(source: bytes | bytearray | str | Path) -> dict[str, list[dict]]:
    """The telemetry of a file as plain dicts per topic, in the fields of the JSON layout:
    ``/joint_states`` {t_s, q, qd}, ``/references`` {t_s, phase, qd_ref}, ``/valve_commands``
    {t_s, u}, ``/gripper`` {t_s, command_open, open}, ``/payload`` {t_s, pos_m, vel_mps},
    ``/events`` {t_s, phase, detail}. Reads both the ROS 2 layout and the JSON one; ROS 2
    messages are decoded with the rosbags typestore and matched to /joint_states by time.

    Raises:
        mcap.exceptions.McapError (or ValueError, KeyError) for a file that is not valid MCAP
        or not telemetry.
    """
    per: dict[str, list] = {}
    ros2 = False
    with _open(source) as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.message_encoding == "json":
                if channel.topic in _JSON_TOPICS:
                    per.setdefault(channel.topic, []).append(json.loads(message.data))
            elif channel.message_encoding == "cdr" and channel.topic in ROS2_TOPICS and schema is not None:
                ros2 = True
                per.setdefault(channel.topic, []).append((message.log_time * 1e-9, schema.name, bytes(message.data)))
    if ros2:
        return _from_ros2(per)
    return {t: per.get(t, []) for t in _JSON_TOPICS}


def _from_ros2(per: dict[str, list]) -> dict[str, list[dict]]:
    from runtime.ros2 import types as rt

    # rosbags messages are classes made at run time from .msg definitions: no static types.
    def decoded(topic: str) -> list[tuple[float, Any]]:
        return [(t, rt.deserialize(data, name)) for t, name, data in per.get(topic, [])]

    def by_time(topic: str) -> dict[int, Any]:
        return {round(t * 1e9): m for t, m in decoded(topic)}

    out: dict[str, list[dict]] = {t: [] for t in _JSON_TOPICS}
    refs, valves = by_time("/references"), by_time("/valve_commands")
    latched = {topic: sorted(by_time(topic).items()) for topic in ("/gripper/command", "/gripper/state", "/throw/phase")}
    current: dict[str, Any] = {topic: None for topic in latched}
    for t, js in decoded("/joint_states"):
        t_s = rt.stamp_s(js.header.stamp)
        k = round(t * 1e9)
        for topic, changes in latched.items():  # the newest change at or before this tick
            while changes and changes[0][0] <= k:
                current[topic] = changes.pop(0)[1].data
        out["/joint_states"].append({"t_s": t_s, "q": js.position.tolist(), "qd": js.velocity.tolist()})
        if k in refs:
            out["/references"].append({"t_s": t_s, "phase": current["/throw/phase"] or "", "qd_ref": refs[k].velocity.tolist()})
        if k in valves:
            out["/valve_commands"].append({"t_s": t_s, "u": valves[k].data.tolist()})
        if current["/gripper/command"] is not None and current["/gripper/state"] is not None:
            out["/gripper"].append({"t_s": t_s, "command_open": bool(current["/gripper/command"]),
                                    "open": bool(current["/gripper/state"])})
    for _t, od in decoded("/payload"):
        p, v = od.pose.pose.position, od.twist.twist.linear
        out["/payload"].append({"t_s": rt.stamp_s(od.header.stamp), "pos_m": [p.x, p.y, p.z], "vel_mps": [v.x, v.y, v.z]})
    for t, kv in decoded("/throw/events"):
        out["/events"].append({"t_s": t, "phase": kv.key, "detail": kv.value or None})
    return out


def read_telemetry(source: bytes | bytearray | str | Path) -> dict[str, np.ndarray]:
    """Read an MCAP telemetry file (ROS 2 or the earlier JSON layout) back into arrays.

    Args:
        source: MCAP bytes or a file path.

    Returns:
        dict with ``t_s`` (N,), ``q`` (N, 6), ``qd`` (N, 6), ``qd_ref`` (N, 4), ``phase`` (N,)
        str, ``valve_u`` (N, 4), ``gripper_cmd`` (N,) bool, ``gripper_open`` (N,) bool,
        ``payload_t_s`` (M,), ``payload_pos_m`` (M, 3), ``payload_vel_mps`` (M, 3),
        ``event_t_s`` (E,), ``event_phase`` (E,) str, ``event_detail`` (E,) object (str or None).

    Raises:
        mcap.exceptions.McapError (or ValueError) for a file that is not valid MCAP.
    """
    per = read_messages(source)

    def arr(topic: str, key: str, width: int | None = None, dtype=float) -> np.ndarray:
        rows = [m[key] for m in per[topic]]
        if width is not None and not rows:
            return np.zeros((0, width), dtype=dtype)
        return np.asarray(rows, dtype=dtype)

    return {
        "t_s": arr("/joint_states", "t_s"),
        "q": arr("/joint_states", "q", 6),
        "qd": arr("/joint_states", "qd", 6),
        "qd_ref": arr("/references", "qd_ref", 4),
        "phase": arr("/references", "phase", dtype=str),
        "valve_u": arr("/valve_commands", "u", 4),
        "gripper_cmd": arr("/gripper", "command_open", dtype=bool),
        "gripper_open": arr("/gripper", "open", dtype=bool),
        "payload_t_s": arr("/payload", "t_s"),
        "payload_pos_m": arr("/payload", "pos_m", 3),
        "payload_vel_mps": arr("/payload", "vel_mps", 3),
        "event_t_s": arr("/events", "t_s"),
        "event_phase": arr("/events", "phase", dtype=str),
        "event_detail": np.asarray([m["detail"] for m in per["/events"]], dtype=object),
    }

def read_metadata(source: bytes | bytearray | str | Path) -> dict[str, str]:
    """The ``throw`` metadata record of a telemetry file (empty dict if absent)."""
    with _open(source) as f:
        for record in make_reader(f).iter_metadata():
            if record.name == "throw":
                return dict(record.metadata)
    return {}
